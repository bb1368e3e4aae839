//! Running one manifest line, and reading back what became of it. A task leaves its line in
//! `sweep_task.json` in its output folder when it starts and `sweep_error.txt` when it fails; a
//! finished run has `report.json` (a label folder `labels.json`). So a task is done, failed,
//! started but unfinished (still running, or killed by the scheduler: see its log) or missing
//! (never started). A rerun of an unfinished run resumes from its checkpoint; a done task is
//! skipped unless forced.

use std::path::PathBuf;

use anyhow::{Context, Result};

use crate::jobs::label::{self, LABELS_FILE};
use crate::jobs::reconstruct::{prepare_run, prior_context, run_prepared, views_with_prior, ReconstructReport};

use super::manifest::{Job, RunSpec, SweepLine};

/// The task's line, written when it starts.
pub const TASK_FILE: &str = "sweep_task.json";
/// The task's error chain, written when it fails.
pub const ERROR_FILE: &str = "sweep_error.txt";
/// A finished reconstruct run's report.
pub const REPORT_FILE: &str = "report.json";

/// What became of a task.
#[derive(Clone, Debug, PartialEq)]
pub enum TaskStatus {
    /// Finished; the file holding its result.
    Done(PathBuf),
    /// Failed with this message.
    Failed(String),
    /// Started but no result and no error: still running, or killed (time or memory limit).
    Unfinished,
    /// Never started.
    Missing,
    /// The folder holds another task's run (the manifest changed since).
    Stale,
}

impl std::fmt::Display for TaskStatus {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            TaskStatus::Done(p) => write!(f, "done ({})", p.display()),
            TaskStatus::Failed(m) => write!(f, "failed: {}", m.lines().next().unwrap_or("")),
            TaskStatus::Unfinished => write!(f, "started but not finished (still running, or killed: see its log)"),
            TaskStatus::Missing => write!(f, "missing (never started)"),
            TaskStatus::Stale => write!(f, "its folder holds a run of another manifest line"),
        }
    }
}

fn result_file(job: &Job) -> PathBuf {
    match job {
        Job::Reconstruct(r) => r.out.join(REPORT_FILE),
        Job::Label(l) => l.out.join(LABELS_FILE),
    }
}

/// What became of `line`, from its output folder.
pub fn status(line: &SweepLine) -> TaskStatus {
    let out = line.job.out();
    let task_file = out.join(TASK_FILE);
    let Ok(text) = std::fs::read_to_string(&task_file) else { return TaskStatus::Missing };
    match serde_json::from_str::<SweepLine>(&text) {
        Ok(l) if l == *line => {}
        _ => return TaskStatus::Stale,
    }
    if let Ok(msg) = std::fs::read_to_string(out.join(ERROR_FILE)) {
        return TaskStatus::Failed(msg);
    }
    let result = result_file(&line.job);
    if result.is_file() {
        TaskStatus::Done(result)
    } else {
        TaskStatus::Unfinished
    }
}

/// Runs `line` (skipped when already done, unless `force`); on failure leaves the error in the
/// task's folder and returns it. Returns whether it ran.
pub fn run(line: &SweepLine, force: bool) -> Result<bool> {
    if !force && matches!(status(line), TaskStatus::Done(_)) {
        return Ok(false);
    }
    let out = line.job.out();
    std::fs::create_dir_all(out).with_context(|| format!("cannot create the task folder {}", out.display()))?;
    for stale in [out.join(ERROR_FILE), result_file(&line.job)] {
        if stale.exists() {
            std::fs::remove_file(&stale).with_context(|| format!("cannot remove {}", stale.display()))?;
        }
    }
    let task_file = out.join(TASK_FILE);
    std::fs::write(&task_file, serde_json::to_string_pretty(line)?).with_context(|| format!("cannot write {}", task_file.display()))?;
    let result = match &line.job {
        Job::Reconstruct(spec) => run_spec(spec).map(|r| eprintln!("{}", r.summary())),
        Job::Label(opts) => label::run(opts).map(|r| eprintln!("labelled {} views of {} with {} in {:.0} s", r.views.len(), r.scene, r.source, r.seconds)),
    };
    if let Err(e) = &result {
        let path = out.join(ERROR_FILE);
        std::fs::write(&path, format!("{e:#}\n")).with_context(|| format!("cannot write {} after the task failed with: {e:#}", path.display()))?;
    }
    result.map(|_| true).with_context(|| format!("sweep task {:?} ({})", line.name, out.display()))
}

/// One reconstruct run as the ablation and trade-off jobs make it: the ground-truth mesh at the
/// spec's training resolution, the prior's labels, then fit, evaluate and write the run folder.
pub fn run_spec(spec: &RunSpec) -> Result<ReconstructReport> {
    let source = spec.source()?;
    let opts = spec.options();
    let prepared = prepare_run(&opts, &source)?;
    let ctx = prior_context(opts.fit.seed, opts.idarb_weights.clone());
    let (views, description) = views_with_prior(&prepared, &source, &ctx, opts.labelled_views)?;
    eprintln!("scene {}, prior {description} → {}", prepared.spec.name, opts.out.display());
    run_prepared(&prepared, views, &opts, &source, &description)
}

//! A sweep manifest: one JSON line per independent task (a reconstruct run or a labelling job),
//! each naming the study it belongs to, so that any scheduler can run line N on its own (a Slurm
//! array task, a GNU parallel job, a Kubernetes Indexed Job) and `sweep gather` can rebuild the
//! study's tables from the run folders afterwards. Task N is line N, counted from 0.

use crate::fit::geometry_pass::GeometryPassConfig;
use crate::jobs::geometry::GeometrySource;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use serde::{Deserialize, Serialize};

use crate::fit::config::FitConfig;
use crate::jobs::label::LabelOptions;
use crate::jobs::reconstruct::ReconstructOptions;
use crate::jobs::tradeoff::TradeoffPoint;
use crate::prior::source::PriorSource;
use crate::render::effects::Effects;

/// One task of a sweep.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SweepLine {
    /// The study whose tables this task feeds.
    pub study: Study,
    /// The task's name in tables and messages (the prior tag, the trade-off point's name, the scene).
    pub name: String,
    pub job: Job,
}

/// What a task belongs to; tasks with equal studies are gathered together.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "kebab-case")]
pub enum Study {
    /// A prior ablation (`jobs::ablation`) written to `out`, with its prior-quality sweep levels.
    Ablation { out: PathBuf, levels: Vec<f64> },
    /// A point of a time/accuracy trade-off (`jobs::tradeoff`) written to `out`.
    Tradeoff { out: PathBuf, point: TradeoffPoint },
    /// Label folders (`reconstruct label`); gathering only checks that each was made.
    Labels,
}

/// What a task runs.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "job", rename_all = "kebab-case")]
pub enum Job {
    Reconstruct(Box<RunSpec>),
    Label(LabelOptions),
}

impl Job {
    /// The task's output folder.
    pub fn out(&self) -> &Path {
        match self {
            Job::Reconstruct(r) => &r.out,
            Job::Label(l) => &l.out,
        }
    }
}

/// One reconstruct run as data: the settings of [`ReconstructOptions`] a sweep varies, the label
/// source, the training resolution divisor and where the geometry comes from (each task runs its own
/// geometry pass when it reconstructs; the pass is seeded, so tasks of one study get the same mesh).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RunSpec {
    pub scene: String,
    pub geometry: GeometrySource,
    pub geometry_pass: GeometryPassConfig,
    /// Data folder overriding the spec's.
    pub data: Option<PathBuf>,
    /// `--prior` source tag (none, idarb, labels:DIR, oracle, idarb-sim:LEVEL).
    pub prior: String,
    pub fit: FitConfig,
    /// Choose the training mode from the scene's effects instead of `fit.mode`.
    pub auto_mode: bool,
    pub eval_spp: u32,
    /// Relight at most this many test views (None = all).
    pub eval_test_views: Option<usize>,
    /// Training views the prior labels (None = all).
    pub labelled_views: Option<usize>,
    /// Effects forced instead of the scene's choice.
    pub effects: Option<Effects>,
    /// Training resolution divisor (1 = the dataset's).
    pub downscale: usize,
    pub idarb_weights: Option<PathBuf>,
    /// The run folder (its checkpoint makes a rerun resume).
    pub out: PathBuf,
}

impl RunSpec {
    /// The spec of a run of `o` with `prior` at training resolution / `downscale`.
    pub fn new(o: &ReconstructOptions, prior: &PriorSource, downscale: usize) -> RunSpec {
        RunSpec {
            scene: o.scene.clone(),
            geometry: o.geometry,
            geometry_pass: o.geometry_pass.clone(),
            data: o.data.clone(),
            prior: prior.tag(),
            fit: FitConfig { prior_source: prior.tag(), ..o.fit.clone() },
            auto_mode: o.auto_mode,
            eval_spp: o.eval_spp,
            eval_test_views: o.eval_test_views,
            labelled_views: (o.labelled_views != usize::MAX).then_some(o.labelled_views),
            effects: o.effects_override,
            downscale,
            idarb_weights: o.idarb_weights.clone(),
            out: o.out.clone(),
        }
    }

    /// The job options of this run (progress lines on, for the task's log).
    pub fn options(&self) -> ReconstructOptions {
        let mut o = ReconstructOptions::new(&self.scene, self.fit.clone(), self.eval_spp, self.out.clone());
        o.data = self.data.clone();
        o.geometry = self.geometry;
        o.geometry_pass = self.geometry_pass.clone();
        o.auto_mode = self.auto_mode;
        o.eval_test_views = self.eval_test_views;
        o.labelled_views = self.labelled_views.unwrap_or(usize::MAX);
        o.effects_override = self.effects;
        o.idarb_weights = self.idarb_weights.clone();
        o.downscale = self.downscale;
        o
    }

    pub fn source(&self) -> Result<PriorSource> {
        self.prior.parse()
    }
}

/// Writes `lines` to `path` (appended to what is there when `append`), one JSON object per line.
pub fn write(path: &Path, lines: &[SweepLine], append: bool) -> Result<()> {
    let mut text = if append && path.exists() { std::fs::read_to_string(path).with_context(|| format!("cannot read the manifest {}", path.display()))? } else { String::new() };
    if !text.is_empty() && !text.ends_with('\n') {
        text.push('\n');
    }
    for l in lines {
        text.push_str(&serde_json::to_string(l)?);
        text.push('\n');
    }
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    }
    std::fs::write(path, text).with_context(|| format!("cannot write the manifest {}", path.display()))
}

/// The tasks of the manifest at `path`; a line that does not parse is an error naming the file
/// and the line. Blank lines are not allowed (they would shift the task numbers).
pub fn read(path: &Path) -> Result<Vec<SweepLine>> {
    let text = std::fs::read_to_string(path).with_context(|| format!("cannot read the manifest {}", path.display()))?;
    let mut lines = Vec::new();
    for (i, line) in text.lines().enumerate() {
        if line.trim().is_empty() {
            bail!("manifest {} line {}: blank line (task N is line N + 1; remove it)", path.display(), i + 1);
        }
        let l: SweepLine = serde_json::from_str(line).with_context(|| format!("manifest {} line {} (task {i}) is not a sweep task", path.display(), i + 1))?;
        lines.push(l);
    }
    if lines.is_empty() {
        bail!("manifest {} has no task", path.display());
    }
    Ok(lines)
}

/// Environment variables that carry the task number, in the order they are consulted: Slurm job
/// arrays, then Kubernetes Indexed Jobs.
pub const TASK_VARIABLES: [&str; 2] = ["SLURM_ARRAY_TASK_ID", "JOB_COMPLETION_INDEX"];

/// The task to run: `explicit` (`--task N`), else the first of [`TASK_VARIABLES`] that `env`
/// gives; checked against the manifest's `count` lines.
pub fn task_index(explicit: Option<usize>, env: impl Fn(&str) -> Option<String>, count: usize) -> Result<usize> {
    let n = match explicit {
        Some(n) => n,
        None => {
            let Some((var, value)) = TASK_VARIABLES.iter().find_map(|v| env(v).map(|x| (*v, x))) else {
                bail!("no task number: pass --task N or set {}", TASK_VARIABLES.join(" or "));
            };
            value.trim().parse().with_context(|| format!("{var}={value:?} is not a task number"))?
        }
    };
    if n >= count {
        bail!("task {n} does not exist: the manifest has {count} tasks (0 to {})", count.saturating_sub(1));
    }
    Ok(n)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn task_number_comes_from_the_flag_then_slurm_then_kubernetes() {
        let env = |pairs: &'static [(&'static str, &'static str)]| move |k: &str| pairs.iter().find(|p| p.0 == k).map(|p| p.1.to_string());
        assert_eq!(task_index(Some(2), env(&[("SLURM_ARRAY_TASK_ID", "1")]), 3).unwrap(), 2);
        assert_eq!(task_index(None, env(&[("SLURM_ARRAY_TASK_ID", "1"), ("JOB_COMPLETION_INDEX", "0")]), 3).unwrap(), 1);
        assert_eq!(task_index(None, env(&[("JOB_COMPLETION_INDEX", "0")]), 3).unwrap(), 0);
        assert!(task_index(None, env(&[]), 3).is_err());
        assert!(task_index(None, env(&[("SLURM_ARRAY_TASK_ID", "x")]), 3).unwrap_err().to_string().contains("SLURM_ARRAY_TASK_ID"));
        assert!(task_index(Some(3), env(&[]), 3).unwrap_err().to_string().contains("3 tasks"));
    }

    #[test]
    fn run_spec_round_trips_the_options() {
        let mut o = ReconstructOptions::new("default", FitConfig { iterations: 7, ..FitConfig::default() }, 4, "runs/x".into());
        o.eval_test_views = Some(2);
        o.labelled_views = 10;
        o.auto_mode = true;
        let spec = RunSpec::new(&o, &PriorSource::IdarbSim(0.5), 1);
        let back = spec.options();
        assert_eq!(back.fit, FitConfig { prior_source: "idarb-sim:0.5".into(), ..o.fit.clone() });
        assert_eq!((back.eval_test_views, back.labelled_views, back.auto_mode, back.out), (Some(2), 10, true, PathBuf::from("runs/x")));
        assert_eq!(spec.source().unwrap(), PriorSource::IdarbSim(0.5));
        let all = RunSpec::new(&ReconstructOptions::new("default", FitConfig::default(), 4, "r".into()), &PriorSource::None, 1);
        assert_eq!((all.labelled_views, all.options().labelled_views), (None, usize::MAX));
    }
}

//! Gathering a sweep: reads the finished runs' `report.json` and writes each study's tables and
//! plots with the one-process jobs' own writers (`ablation.md` / `.json` / `prior_quality.png`,
//! `tradeoff.csv` / `.png` plus the Pareto front in `tradeoff.md`), naming every task that is
//! missing, failed or unfinished, in the tables and in the returned list.
//!
//! A gathered ablation row's wall time is the run's own stages (scene preparation included, as
//! each task prepares its scene); everything else comes from the run's report unchanged.

use std::fmt::Write;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use serde::Deserialize;

use crate::eval::protocol::Evaluation;
use crate::jobs::ablation::{self, AblationReport, AblationRow};
use crate::jobs::tradeoff::{front_table, result_of, write_outputs, TradeoffResult};

use super::manifest::{Job, Study, SweepLine};
use super::task::{status, TaskStatus};

/// A task that has no result.
#[derive(Clone, Debug, PartialEq)]
pub struct Problem {
    /// Its line in the manifest (from 0).
    pub task: usize,
    pub name: String,
    pub folder: PathBuf,
    pub status: TaskStatus,
}

impl std::fmt::Display for Problem {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "task {} `{}` ({}): {}", self.task, self.name, self.folder.display(), self.status)
    }
}

/// The tables written and the tasks without a result.
#[derive(Debug, Default)]
pub struct Gathered {
    pub ablations: Vec<(PathBuf, AblationReport)>,
    pub tradeoffs: Vec<(PathBuf, Vec<TradeoffResult>)>,
    /// Label folders made.
    pub labels: usize,
    pub problems: Vec<Problem>,
    /// The Markdown files written, with their text.
    pub tables: Vec<(PathBuf, String)>,
}

/// The parts of a run's `report.json` the tables use.
#[derive(Deserialize)]
struct RunReport {
    scene: String,
    /// The source's description.
    prior: String,
    evaluation: Evaluation,
    stage_seconds: Vec<(String, f64)>,
}

fn read_report(path: &Path) -> Result<RunReport> {
    let text = std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
    serde_json::from_str(&text).with_context(|| format!("{} is not a run report", path.display()))
}

/// The Markdown section that names the tasks without a result.
pub fn problems_markdown(problems: &[&Problem]) -> String {
    let mut s = String::new();
    if !problems.is_empty() {
        s.push_str("\n## Runs missing or failed (not in the tables)\n\n");
        for p in problems {
            let _ = writeln!(s, "- {p}");
        }
    }
    s
}

/// The finished runs of `lines` (task numbers kept) and the problems of the others.
fn collect<'a>(lines: &[(usize, &'a SweepLine)], problems: &mut Vec<Problem>) -> Vec<(&'a SweepLine, RunReport)> {
    let mut done = Vec::new();
    for &(task, line) in lines {
        let problem = |status| Problem { task, name: line.name.clone(), folder: line.job.out().to_path_buf(), status };
        match status(line) {
            TaskStatus::Done(path) => match &line.job {
                Job::Reconstruct(_) => match read_report(&path) {
                    Ok(r) => done.push((line, r)),
                    Err(e) => problems.push(problem(TaskStatus::Failed(format!("{e:#}")))),
                },
                Job::Label(_) => {}
            },
            other => problems.push(problem(other)),
        }
    }
    done
}

/// Gathers every study of the manifest `lines` into its tables.
pub fn gather(lines: &[SweepLine]) -> Result<Gathered> {
    // Studies in the order of their first line; a trade-off's lines share its folder.
    let mut studies: Vec<(Study, Vec<(usize, &SweepLine)>)> = Vec::new();
    let same = |a: &Study, b: &Study| match (a, b) {
        (Study::Ablation { out: x, .. }, Study::Ablation { out: y, .. }) | (Study::Tradeoff { out: x, .. }, Study::Tradeoff { out: y, .. }) => x == y,
        (Study::Labels, Study::Labels) => true,
        _ => false,
    };
    for (i, l) in lines.iter().enumerate() {
        match studies.iter_mut().find(|s| same(&s.0, &l.study)) {
            Some(s) => s.1.push((i, l)),
            None => studies.push((l.study.clone(), vec![(i, l)])),
        }
    }
    let mut g = Gathered::default();
    for (study, members) in studies {
        let first_problem = g.problems.len();
        let done = collect(&members, &mut g.problems);
        let problems: Vec<&Problem> = g.problems[first_problem..].iter().collect();
        match study {
            Study::Ablation { out, levels } => {
                std::fs::create_dir_all(&out).with_context(|| format!("cannot create {}", out.display()))?;
                let scene = done.first().map_or_else(|| members[0].1.name.clone(), |d| d.1.scene.clone());
                let rows = done
                    .into_iter()
                    .map(|(line, r)| AblationRow { prior: line.name.clone(), description: r.prior, evaluation: r.evaluation, seconds: r.stage_seconds.iter().map(|s| s.1).sum() })
                    .collect();
                let report = ablation::finish(scene, rows, &levels, &out)?;
                let md = report.markdown() + &problems_markdown(&problems);
                let path = out.join("ablation.md");
                std::fs::write(&path, &md).with_context(|| format!("cannot write {}", path.display()))?;
                g.tables.push((path, md));
                g.ablations.push((out, report));
            }
            Study::Tradeoff { out, .. } => {
                std::fs::create_dir_all(&out).with_context(|| format!("cannot create {}", out.display()))?;
                let results: Vec<TradeoffResult> = done
                    .into_iter()
                    .filter_map(|(line, r)| match &line.study {
                        Study::Tradeoff { point, .. } => Some(result_of(point, &r.evaluation, &r.stage_seconds)),
                        _ => None,
                    })
                    .collect();
                write_outputs(&out, &results)?;
                let md = format!("# Time/accuracy trade-off: Pareto front\n\n{}\n![trade-off](tradeoff.png)\n{}", front_table(&results), problems_markdown(&problems));
                let path = out.join("tradeoff.md");
                std::fs::write(&path, &md).with_context(|| format!("cannot write {}", path.display()))?;
                g.tables.push((path, md));
                g.tradeoffs.push((out, results));
            }
            Study::Labels => g.labels += members.len() - problems.len(),
        }
    }
    Ok(g)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::config::FitConfig;
    use crate::jobs::ablation::AblationOptions;
    use crate::jobs::reconstruct::ReconstructOptions;
    use crate::jobs::sweep::manifest;
    use crate::jobs::sweep::plan;
    use crate::jobs::sweep::task::{ERROR_FILE, REPORT_FILE, TASK_FILE};
    use crate::prior::source::PriorSource;

    fn temp(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("reconstruct-sweep-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        d
    }

    /// A finished run as `run_prepared` leaves it: the task file and a report.
    fn finish_run(line: &SweepLine, eval: &Evaluation) {
        let out = line.job.out();
        std::fs::create_dir_all(out).unwrap();
        std::fs::write(out.join(TASK_FILE), serde_json::to_string(line).unwrap()).unwrap();
        let report = serde_json::json!({"scene": "default", "prior": format!("{} (described)", line.name), "config": {}, "evaluation": eval,
            "stage_seconds": [["load scene", 1.0], ["optimise", 2.5]], "history": []});
        std::fs::write(out.join(REPORT_FILE), report.to_string()).unwrap();
    }

    #[test]
    fn plans_the_ablation_and_gathers_done_failed_and_missing_runs() -> Result<()> {
        let dir = temp("gather");
        let base = ReconstructOptions::new("default", FitConfig { iterations: 5, ..FitConfig::default() }, 2, dir.join("ablation"));
        let opts = AblationOptions { base, sources: vec![PriorSource::None, PriorSource::IdarbSim(1.0), PriorSource::Oracle], sweep: vec![0.0, 1.0, 2.0] };
        let lines = plan::ablation(&opts);
        // Sweep levels 0 and 1 are the oracle and idarb-sim rows already planned: one line more.
        let names: Vec<&str> = lines.iter().map(|l| l.name.as_str()).collect();
        assert_eq!(names, ["none", "idarb-sim:1", "oracle", "idarb-sim:2"]);
        let Job::Reconstruct(spec) = &lines[3].job else { panic!("a reconstruct line") };
        assert_eq!((spec.out.clone(), spec.fit.prior_source.as_str(), spec.fit.iterations), (dir.join("ablation/idarb-sim_2"), "idarb-sim:2", 5));

        // The manifest round-trips, and a damaged line is named.
        let path = dir.join("sweep.jsonl");
        manifest::write(&path, &lines, false)?;
        assert_eq!(manifest::read(&path)?, lines);
        let text = std::fs::read_to_string(&path)?;
        std::fs::write(dir.join("bad.jsonl"), text.replacen("\"study\"", "\"stduy\"", 2))?;
        let err = format!("{:#}", manifest::read(&dir.join("bad.jsonl")).unwrap_err());
        assert!(err.contains("bad.jsonl line 1 (task 0)"), "{err}");

        // Task 0 and 1 finished, task 2 failed, task 3 never ran.
        let eval = |albedo: f64, relight: f64| Evaluation { albedo_psnr_scaled: Some(albedo), relight_psnr_scaled: Some(relight), relight_psnr_raw: Some(relight - 1.0), ..Evaluation::default() };
        finish_run(&lines[0], &eval(20.0, 23.5));
        finish_run(&lines[1], &eval(26.0, 27.25));
        std::fs::create_dir_all(lines[2].job.out())?;
        std::fs::write(lines[2].job.out().join(TASK_FILE), serde_json::to_string(&lines[2])?)?;
        std::fs::write(lines[2].job.out().join(ERROR_FILE), "out of memory\n")?;

        let g = gather(&lines)?;
        let (out, report) = &g.ablations[0];
        assert_eq!(out, &dir.join("ablation"));
        let rows: Vec<(&str, Option<f64>, f64)> = report.rows.iter().map(|r| (r.prior.as_str(), r.evaluation.relight_psnr_scaled, r.seconds)).collect();
        assert_eq!(rows, [("none", Some(23.5), 3.5), ("idarb-sim:1", Some(27.25), 3.5)]);
        assert_eq!(report.rows[1].description, "idarb-sim:1 (described)");
        // Of the sweep levels 0, 1, 2 only level 1 has a finished run.
        assert_eq!(report.sweep, vec![(1.0, Some(27.25), Some(26.25))]);
        assert_eq!(g.problems.iter().map(|p| (p.task, p.status.clone())).collect::<Vec<_>>(), [(2, TaskStatus::Failed("out of memory\n".into())), (3, TaskStatus::Missing)]);
        let md = std::fs::read_to_string(dir.join("ablation/ablation.md"))?;
        assert!(md.contains("| none | – | 20.00 | 22.50 | 23.50 |"), "{md}");
        assert!(md.contains("task 2 `oracle`") && md.contains("failed: out of memory") && md.contains("task 3 `idarb-sim:2`") && md.contains("never started"), "{md}");
        assert!(dir.join("ablation/ablation.json").is_file() && dir.join("ablation/prior_quality.png").is_file());

        // A run folder left by another manifest line is not taken for this one.
        let mut other = lines[0].clone();
        other.name = "renamed".into();
        assert_eq!(status(&other), TaskStatus::Stale);
        std::fs::remove_dir_all(&dir).ok();
        Ok(())
    }

    #[test]
    fn trade_off_points_gather_into_one_study() -> Result<()> {
        let dir = temp("tradeoff");
        let base = ReconstructOptions::new("default", FitConfig::default(), 2, dir.join("tradeoff"));
        let points = crate::jobs::tradeoff::default_points(30);
        let lines = plan::tradeoff(&base, &points[..3])?;
        let Job::Reconstruct(spec) = &lines[2].job else { panic!("a reconstruct line") };
        assert_eq!((spec.out.clone(), spec.fit.spp, spec.fit.iterations), (crate::jobs::tradeoff::point_folder(&dir.join("tradeoff"), 2, &points[2]), points[2].spp, 30));
        let Job::Reconstruct(spec) = &lines[1].job else { panic!("a reconstruct line") };
        assert_eq!(spec.downscale, 2, "{:?} trains at half resolution", points[1].name);
        finish_run(&lines[0], &Evaluation { relight_psnr_scaled: Some(21.0), ..Evaluation::default() });
        finish_run(&lines[2], &Evaluation { relight_psnr_scaled: Some(22.0), ..Evaluation::default() });
        let g = gather(&lines)?;
        assert_eq!(g.tradeoffs.len(), 1, "one study for the three points");
        let names: Vec<&str> = g.tradeoffs[0].1.iter().map(|r| r.point.name.as_str()).collect();
        assert_eq!(names, [points[0].name.as_str(), points[2].name.as_str()]);
        assert_eq!(g.tradeoffs[0].1[1].optimise_seconds, 2.5);
        assert_eq!(g.problems.iter().map(|p| p.task).collect::<Vec<_>>(), [1]);
        let csv = std::fs::read_to_string(dir.join("tradeoff/tradeoff.csv"))?;
        assert_eq!(csv.lines().count(), 3, "{csv}");
        assert!(std::fs::read_to_string(dir.join("tradeoff/tradeoff.md"))?.contains("task 1 `split-sum 128²`"));
        std::fs::remove_dir_all(&dir).ok();
        Ok(())
    }
}

//! The prior ablation: the same scene, seed, budget and settings optimised with each label
//! source (none, idarb-sim, oracle, and idarb / labels:DIR when asked), plus a prior-quality sweep
//! (the simulated error scaled from 0 to 2× IDArb's) against relighting PSNR. Writes
//! `ablation.md`, `ablation.json` and `prior_quality.png`; each run keeps its own run folder.

use std::fmt::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result};
use serde::Serialize;

use crate::eval::protocol::Evaluation;
use crate::prior::source::PriorSource;
use crate::report::plot::{write_line_plot, LinePlot, Series};

use super::reconstruct::{prior_context, run_prepared, views_with_prior, ReconstructOptions};
use super::shared_preparation::SharedPreparation;

#[derive(Clone, Debug)]
pub struct AblationOptions {
    /// Settings shared by every run (`out` is the ablation folder).
    pub base: ReconstructOptions,
    /// Sources of the table, in order.
    pub sources: Vec<PriorSource>,
    /// Levels of the prior-quality sweep (idarb-sim:LEVEL); levels already in `sources` are reused.
    pub sweep: Vec<f64>,
}

#[derive(Clone, Debug, Serialize)]
pub struct AblationRow {
    pub prior: String,
    pub description: String,
    pub evaluation: Evaluation,
    pub seconds: f64,
}

#[derive(Clone, Debug, Serialize)]
pub struct AblationReport {
    pub scene: String,
    pub rows: Vec<AblationRow>,
    /// (level, relighting PSNR scaled, raw) of the sweep.
    pub sweep: Vec<(f64, Option<f64>, Option<f64>)>,
}

fn f(v: Option<f64>, d: usize) -> String {
    v.map_or("–".into(), |v| format!("{v:.d$}"))
}

impl AblationReport {
    pub fn markdown(&self) -> String {
        let mut s = format!("# Prior ablation: {}\n\n", self.scene);
        s.push_str("| prior | albedo PSNR raw | albedo PSNR scaled | relight PSNR raw | relight PSNR scaled | roughness MSE | metallic MSE | normal error (°) | wall time (s) |\n");
        s.push_str("|---|---:|---:|---:|---:|---:|---:|---:|---:|\n");
        for r in &self.rows {
            let e = &r.evaluation;
            let _ = writeln!(
                s,
                "| {} | {} | {} | {} | {} | {} | {} | {} | {:.0} |",
                r.prior,
                f(e.albedo_psnr_raw, 2),
                f(e.albedo_psnr_scaled, 2),
                f(e.relight_psnr_raw, 2),
                f(e.relight_psnr_scaled, 2),
                f(e.roughness_mse, 4),
                f(e.metallic_mse, 4),
                f(e.normal_error_deg, 2),
                r.seconds
            );
        }
        s.push_str("\nSources:\n");
        for r in &self.rows {
            let _ = writeln!(s, "- `{}`: {}", r.prior, r.description);
        }
        if !self.sweep.is_empty() {
            s.push_str("\n## Prior quality (idarb-sim level: 0 = oracle, 1 = IDArb's published error)\n\n| level | relight PSNR scaled | relight PSNR raw |\n|---:|---:|---:|\n");
            for (l, sc, raw) in &self.sweep {
                let _ = writeln!(s, "| {l} | {} | {} |", f(*sc, 2), f(*raw, 2));
            }
            s.push_str("\n![prior quality](prior_quality.png)\n");
        }
        s
    }
}

/// The prior-quality sweep of the full ablation (`examples/ablation.rs`): idarb-sim levels from
/// the oracle (0) through IDArb's published error (1) to twice it, in half steps. The `ablation`
/// command is a few-minute miniature and sweeps only when asked (`--sweep`).
pub const FULL_SWEEP: [f64; 5] = [0.0, 0.5, 1.0, 1.5, 2.0];

/// The sources of every ablation's table, the `ablation` command's and the example's: no prior,
/// simulated IDArb labels at IDArb's published error, and the ground truth as labels (the bounds
/// the prior can reach). The example adds `idarb` and `labels:DIR` when asked.
pub fn default_sources() -> Vec<PriorSource> {
    vec![PriorSource::None, PriorSource::IdarbSim(1.0), PriorSource::Oracle]
}

/// The sources an ablation runs, in table order: `sources`, then the sweep levels not among them
/// (level 0 is the oracle).
pub fn all_sources(opts: &AblationOptions) -> Vec<PriorSource> {
    let mut sources = opts.sources.clone();
    for &l in &opts.sweep {
        let s = if l == 0.0 { PriorSource::Oracle } else { PriorSource::IdarbSim(l) };
        if !sources.contains(&s) {
            sources.push(s);
        }
    }
    sources
}

/// The run folder of `source` inside the ablation folder `out`.
pub fn run_folder(out: &Path, source: &PriorSource) -> PathBuf {
    out.join(source.tag().replace([':', '/'], "_"))
}

pub fn run(opts: &AblationOptions) -> Result<AblationReport> {
    let base = &opts.base;
    std::fs::create_dir_all(&base.out).with_context(|| format!("cannot create {}", base.out.display()))?;
    let mut shared = SharedPreparation::new(&base.out);
    let ctx = prior_context(base.fit.seed, base.idarb_weights.clone());
    let (mut rows, mut scene) = (Vec::new(), base.scene.clone());
    for source in &all_sources(opts) {
        let t = Instant::now();
        let mut o = base.clone();
        o.out = run_folder(&base.out, source);
        o.fit.prior_source = source.tag();
        let prepared = shared.get(&o, source)?;
        scene = prepared.spec.name.clone();
        let (views, description) = match views_with_prior(prepared, source, &ctx, base.labelled_views) {
            Ok(v) => v,
            Err(e) => {
                eprintln!("ablation: skipping --prior {}: {e:#}", source.tag());
                continue;
            }
        };
        eprintln!("ablation: {} → {}", source.tag(), o.out.display());
        let report = run_prepared(prepared, views, &o, source, &description)?;
        rows.push(AblationRow { prior: source.tag(), description, evaluation: report.evaluation, seconds: t.elapsed().as_secs_f64() });
    }
    finish(scene, rows, &opts.sweep, &base.out)
}

/// The report of finished rows (in table order): picks the sweep's rows, draws
/// `prior_quality.png` and writes `ablation.json` and `ablation.md` into `out`.
pub fn finish(scene: String, rows: Vec<AblationRow>, levels: &[f64], out: &Path) -> Result<AblationReport> {
    let level_of = |r: &AblationRow| -> Option<f64> {
        match r.prior.parse::<PriorSource>().ok()? {
            PriorSource::Oracle => Some(0.0),
            PriorSource::IdarbSim(l) => Some(l),
            _ => None,
        }
    };
    let mut sweep: Vec<(f64, Option<f64>, Option<f64>)> =
        rows.iter().filter_map(|r| level_of(r).filter(|l| levels.contains(l)).map(|l| (l, r.evaluation.relight_psnr_scaled, r.evaluation.relight_psnr_raw))).collect();
    sweep.sort_by(|a, b| a.0.total_cmp(&b.0));
    let report = AblationReport { scene, rows, sweep };
    if !report.sweep.is_empty() {
        let none = report.rows.iter().find(|r| r.prior == "none").and_then(|r| r.evaluation.relight_psnr_scaled);
        write_prior_quality_plot(&report.scene, &report.sweep, none, &out.join("prior_quality.png"))?;
    }
    crate::atomic_write::write(&out.join("ablation.json"), serde_json::to_string_pretty(&report)?)?;
    crate::atomic_write::write(&out.join("ablation.md"), report.markdown())?;
    Ok(report)
}

/// Relighting PSNR (scaled) against the simulated prior error, with the no-prior level as a line.
pub fn write_prior_quality_plot(scene: &str, sweep: &[(f64, Option<f64>, Option<f64>)], none: Option<f64>, path: &std::path::Path) -> Result<()> {
    let (lo, hi) = (sweep.first().map_or(0.0, |s| s.0), sweep.last().map_or(1.0, |s| s.0));
    let mut series = vec![Series { name: "idarb-sim (scaled)".into(), points: sweep.iter().filter_map(|(l, s, _)| Some((*l, (*s)?))).collect() }];
    if let Some(n) = none {
        series.push(Series { name: "no prior (scaled)".into(), points: vec![(lo, n), (hi, n)] });
    }
    write_line_plot(
        &LinePlot { title: format!("{scene}: relighting PSNR vs prior error"), x_label: "simulated error (× IDArb's)".into(), y_label: "relighting PSNR (dB)".into(), log_y: false, series },
        path,
    )
}

/// The ablation folder for a scene.
pub fn default_out(scene: &str) -> PathBuf {
    PathBuf::from(format!("runs/ablation-{scene}"))
}

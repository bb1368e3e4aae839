//! What accuracy costs in time: one scene optimised under a sweep of settings (shading mode,
//! samples per pixel, denoiser, resolution, effects — shadows and interreflection bounces —,
//! iterations, labelled-view count), recording the
//! optimisation wall time and the relighting PSNR of each; writes `tradeoff.csv`, `tradeoff.png`
//! (time against PSNR with the Pareto front) and returns the front.

use std::fmt::Write;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use serde::{Deserialize, Serialize};

use crate::eval::protocol::Evaluation;

use crate::prior::source::PriorSource;
use crate::render::effects::Effects;
use crate::render::view::ShadingMode;
use crate::report::pareto::pareto_front;
use crate::report::plot::{write_pareto_plot, ScatterPoint};

use super::reconstruct::{prior_context, run_prepared, views_with_prior, ReconstructOptions};
use super::shared_preparation::SharedPreparation;
use super::run_identity::{digest_of, SHORT_DIGEST};

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TradeoffPoint {
    pub name: String,
    /// Legend group (what the point varies).
    pub group: String,
    pub mode: ShadingMode,
    pub spp: u32,
    pub denoise: bool,
    pub iterations: usize,
    /// Training resolution divisor (1 = the dataset's).
    pub downscale: usize,
    /// Forced effects (None = the scene's choice), in training and evaluation alike.
    pub effects: Option<Effects>,
    pub prior: String,
    pub labelled_views: usize,
}

#[derive(Clone, Debug, Serialize)]
pub struct TradeoffResult {
    pub point: TradeoffPoint,
    pub optimise_seconds: f64,
    pub relight_psnr_scaled: Option<f64>,
    pub relight_psnr_raw: Option<f64>,
    pub albedo_psnr_scaled: Option<f64>,
}

/// The default sweep (≥ 12 points) around a base of `iterations`.
pub fn default_points(iterations: usize) -> Vec<TradeoffPoint> {
    let p = |name: &str, group: &str, mode, spp, denoise, it, downscale, effects, prior: &str, labelled| TradeoffPoint {
        name: name.into(),
        group: group.into(),
        mode,
        spp,
        denoise,
        iterations: it,
        downscale,
        effects,
        prior: prior.into(),
        labelled_views: labelled,
    };
    use ShadingMode::{MonteCarlo as Mc, SplitSum as Ss};
    let (i, short, long) = (iterations, (iterations / 3).max(1), iterations * 3);
    let bounces = |b| Some(Effects::with_bounces(b));
    let no_shadows = Some(Effects { shadows: false, specular: true, indirect_bounces: 0 });
    vec![
        p("split-sum", "split-sum", Ss, 1, false, i, 1, None, "none", 0),
        p("split-sum 128²", "resolution", Ss, 1, false, i, 2, None, "none", 0),
        p("MC 1 spp", "MC spp", Mc, 1, false, i, 1, None, "none", 0),
        p("MC 4 spp", "MC spp", Mc, 4, false, i, 1, None, "none", 0),
        p("MC 8 spp", "MC spp", Mc, 8, false, i, 1, None, "none", 0),
        p("MC 16 spp", "MC spp", Mc, 16, false, i, 1, None, "none", 0),
        p("MC 4 spp + denoiser", "MC + denoiser", Mc, 4, true, i, 1, None, "none", 0),
        p("MC 4 spp, no shadows", "effects", Mc, 4, false, i, 1, no_shadows, "none", 0),
        p("MC 4 spp, direct light only", "effects", Mc, 4, false, i, 1, bounces(0), "none", 0),
        p("MC 4 spp, 1 bounce", "effects", Mc, 4, false, i, 1, bounces(1), "none", 0),
        p("MC 4 spp 128²", "resolution", Mc, 4, false, i, 2, None, "none", 0),
        p("MC 16 spp 128²", "resolution", Mc, 16, false, i, 2, None, "none", 0),
        p(&format!("MC 4 spp {short} it"), "iterations", Mc, 4, false, short, 1, None, "none", 0),
        p(&format!("MC 4 spp {long} it"), "iterations", Mc, 4, false, long, 1, None, "none", 0),
        p("MC 4 spp + idarb-sim, 10 views", "labelled views", Mc, 4, false, i, 1, None, "idarb-sim", 10),
        p("MC 4 spp + idarb-sim, 100 views", "labelled views", Mc, 4, false, i, 1, None, "idarb-sim", 100),
    ]
}

pub fn run(base: &ReconstructOptions, points: &[TradeoffPoint]) -> Result<Vec<TradeoffResult>> {
    std::fs::create_dir_all(&base.out).with_context(|| format!("cannot create {}", base.out.display()))?;
    let mut shared = SharedPreparation::new(&base.out);
    let mut results = Vec::new();
    for (k, pt) in points.iter().enumerate() {
        let (o, source) = point_options(base, k, pt)?;
        let prep = shared.get(&o, &source)?;
        let ctx = prior_context(base.fit.seed, base.idarb_weights.clone());
        let (views, description) = views_with_prior(prep, &source, &ctx, pt.labelled_views)?;
        eprintln!("trade-off {}/{}: {}", k + 1, points.len(), pt.name);
        let report = run_prepared(prep, views, &o, &source, &description)?;
        results.push(result_of(pt, &report.evaluation, &report.stage_seconds));
        write_outputs(&base.out, &results)?;
    }
    Ok(results)
}

/// The run folder of point `k` inside the trade-off folder: `<k>-<digest>`, the digest of what the
/// point sets (mode, samples, denoiser, resolution, forced effects, prior, labelled views; not its
/// name nor its iteration count, which extends a run), so a point list that changes between runs
/// never resumes another point's checkpoint. (A checkpoint also refuses any run of another identity.)
pub fn point_folder(out: &Path, k: usize, pt: &TradeoffPoint) -> PathBuf {
    let settings = (pt.mode, pt.spp, pt.denoise, pt.downscale, pt.effects, &pt.prior, pt.labelled_views);
    out.join(format!("{k:02}-{}", &digest_of(&settings)[..SHORT_DIGEST]))
}

/// The options of point `k` (its run folder [`point_folder`]) and its label source.
pub fn point_options(base: &ReconstructOptions, k: usize, pt: &TradeoffPoint) -> Result<(ReconstructOptions, PriorSource)> {
    let source: PriorSource = pt.prior.parse()?;
    let mut o = base.clone();
    o.out = point_folder(&base.out, k, pt);
    o.fit.mode = pt.mode;
    o.fit.spp = pt.spp;
    o.fit.denoise = pt.denoise;
    o.fit.iterations = pt.iterations;
    o.fit.prior_source = source.tag();
    o.effects_override = pt.effects;
    o.labelled_views = pt.labelled_views;
    o.downscale = pt.downscale;
    Ok((o, source))
}

/// The trade-off record of a finished run of `pt`.
pub fn result_of(pt: &TradeoffPoint, e: &Evaluation, stage_seconds: &[(String, f64)]) -> TradeoffResult {
    let optimise_seconds = stage_seconds.iter().find(|s| s.0 == "optimise").map_or(f64::NAN, |s| s.1);
    TradeoffResult {
        point: pt.clone(),
        optimise_seconds,
        relight_psnr_scaled: e.relight_psnr_scaled,
        relight_psnr_raw: e.relight_psnr_raw,
        albedo_psnr_scaled: e.albedo_psnr_scaled,
    }
}

/// Writes `tradeoff.csv` and `tradeoff.png` (time against PSNR, Pareto front marked) into `out`.
pub fn write_outputs(out: &Path, results: &[TradeoffResult]) -> Result<()> {
    let mut csv = String::from("name,group,mode,spp,denoise,iterations,downscale,shadows,bounces,prior,labelled_views,optimise_seconds,relight_psnr_scaled,relight_psnr_raw,albedo_psnr_scaled\n");
    let o = |v: Option<f64>| v.map_or(String::new(), |v| format!("{v:.3}"));
    for r in results {
        let p = &r.point;
        let _ = writeln!(
            csv,
            "\"{}\",{},{:?},{},{},{},{},{},{},{},{},{:.2},{},{},{}",
            p.name,
            p.group,
            p.mode,
            p.spp,
            p.denoise,
            p.iterations,
            p.downscale,
            p.effects.map_or("auto".into(), |e| e.shadows.to_string()),
            p.effects.map_or("auto".into(), |e| e.indirect_bounces.to_string()),
            p.prior,
            p.labelled_views,
            r.optimise_seconds,
            o(r.relight_psnr_scaled),
            o(r.relight_psnr_raw),
            o(r.albedo_psnr_scaled)
        );
    }
    crate::atomic_write::write(&out.join("tradeoff.csv"), csv)?;
    let points: Vec<ScatterPoint> = results
        .iter()
        .filter_map(|r| Some(ScatterPoint { label: r.point.name.clone(), x: r.optimise_seconds, y: r.relight_psnr_scaled?, group: r.point.group.clone() }))
        .collect();
    write_pareto_plot(&points, "optimisation wall time (s)", "relighting PSNR, scaled (dB)", "What accuracy costs in time", true, &out.join("tradeoff.png"))
}

/// The Pareto front (fastest to most accurate) as a Markdown table, with the extra seconds each
/// extra dB costs between consecutive front points.
pub fn front_table(results: &[TradeoffResult]) -> String {
    let pts: Vec<(f64, f64)> = results.iter().map(|r| (r.optimise_seconds, r.relight_psnr_scaled.unwrap_or(f64::NAN))).collect();
    let front = pareto_front(&pts);
    let mut s = String::from("| setting | optimisation (s) | relighting PSNR scaled (dB) | extra s per extra dB |\n|---|---:|---:|---:|\n");
    for (k, &i) in front.iter().enumerate() {
        let cost = if k == 0 {
            "–".to_string()
        } else {
            let j = front[k - 1];
            format!("{:.0}", (pts[i].0 - pts[j].0) / (pts[i].1 - pts[j].1))
        };
        let _ = writeln!(s, "| {} | {:.0} | {:.2} | {cost} |", results[i].point.name, pts[i].0, pts[i].1);
    }
    s
}

/// The trade-off folder for a scene.
pub fn default_out(scene: &str) -> PathBuf {
    PathBuf::from(format!("runs/tradeoff-{scene}"))
}

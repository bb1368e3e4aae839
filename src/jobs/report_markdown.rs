//! The human-readable report of a reconstruct run: `report.md` with the settings, the effects and
//! why, the metrics of the NeRFactor protocol, the time of each stage, and PNG curves of the loss
//! terms and the training PSNR.

use std::fmt::Write;
use std::path::Path;

use anyhow::Result;

use crate::fit::history::IterationRecord;
use crate::report::plot::{write_line_plot, LinePlot, Series};

use super::reconstruct::ReconstructReport;

/// Points of a curve averaged over windows of `window` iterations (raw per-step values are noisy).
fn smoothed(history: &[IterationRecord], window: usize, f: impl Fn(&IterationRecord) -> f64) -> Vec<(f64, f64)> {
    history
        .chunks(window.max(1))
        .filter_map(|c| {
            let vals: Vec<f64> = c.iter().map(&f).filter(|v| v.is_finite()).collect();
            (!vals.is_empty()).then(|| ((c[0].iteration + c.len() / 2) as f64, vals.iter().sum::<f64>() / vals.len() as f64))
        })
        .collect()
}

/// The run folder's plots folder (holding `loss.png` and `psnr.png`).
pub const PLOTS_DIR: &str = "plots";

/// Writes `loss.png` and `psnr.png` into `plots` (the run folder's [`PLOTS_DIR`]); returns their
/// titles and paths relative to the run folder.
pub fn write_plots(plots: &Path, history: &[IterationRecord]) -> Result<Vec<(String, String)>> {
    let window = (history.len() / 100).max(1);
    std::fs::create_dir_all(plots)?;
    let loss = LinePlot {
        title: "Loss terms (weighted)".into(),
        x_label: "iteration".into(),
        y_label: "loss".into(),
        log_y: true,
        series: vec![
            Series { name: "total".into(), points: smoothed(history, window, |r| r.terms.total) },
            Series { name: "image".into(), points: smoothed(history, window, |r| r.terms.image) },
            Series { name: "smoothness".into(), points: smoothed(history, window, |r| r.terms.smoothness) },
            Series { name: "shading".into(), points: smoothed(history, window, |r| r.terms.shading) },
            Series { name: "prior".into(), points: smoothed(history, window, |r| r.terms.prior) },
            Series { name: "light balance".into(), points: smoothed(history, window, |r| r.terms.light) },
        ]
        .into_iter()
        .filter(|s| s.points.iter().any(|p| p.1 > 0.0))
        .collect(),
    };
    write_line_plot(&loss, &plots.join("loss.png"))?;
    let psnr = LinePlot {
        title: "Training batches: PSNR of the render (sRGB, alpha > 0.8)".into(),
        x_label: "iteration".into(),
        y_label: "PSNR (dB)".into(),
        log_y: false,
        series: vec![Series { name: "batch PSNR".into(), points: smoothed(history, window, |r| r.terms.psnr) }],
    };
    write_line_plot(&psnr, &plots.join("psnr.png"))?;
    Ok(vec![("Loss".into(), format!("{PLOTS_DIR}/loss.png")), ("Training PSNR".into(), format!("{PLOTS_DIR}/psnr.png"))])
}

fn opt(v: Option<f64>, digits: usize) -> String {
    v.map_or("–".into(), |v| format!("{v:.digits$}"))
}

pub fn markdown(r: &ReconstructReport, plots: &[(String, String)]) -> String {
    let e = &r.evaluation;
    let c = &r.config;
    let mut s = String::new();
    let _ = writeln!(s, "# reconstruct run: {}\n", r.scene);
    let _ = writeln!(s, "- data: `{}`", r.data_dir.display());
    let _ = writeln!(s, "- geometry: {} ({}); UV atlas: {}", r.geometry.used.tag(), r.geometry.why, r.atlas);
    if let Some(h) = &r.geometry.hull {
        let _ = writeln!(s, "- visual hull: {} vertices, {} triangles, {:.1} s ({})", h.vertices, h.triangles, h.seconds, h.summary);
    }
    if let Some(p) = &r.geometry.pass {
        let _ = writeln!(s, "- geometry pass: {} iterations over {} views at {}×{}, {:.1} s", p.config.iterations, p.views, p.resolution[0], p.resolution[1], p.seconds);
    }
    if let Some(sc) = &r.geometry.scores {
        let _ = writeln!(s, "- {}", crate::jobs::geometry::scores_summary(sc).replace('\n', "\n  "));
    }
    let _ = writeln!(s, "- prior: **{}**", r.prior);
    let _ = writeln!(
        s,
        "- shading: {:?}{}; {} iterations × {} views; textures {}², light 6×{}²; seed {}",
        c.mode,
        if c.mode == crate::render::view::ShadingMode::MonteCarlo { format!(" ({} spp{})", c.spp, if c.denoise { ", denoised" } else { "" }) } else { String::new() },
        c.iterations,
        c.batch,
        c.texture_res,
        c.light_res,
        c.seed
    );
    let _ = writeln!(s, "- training mode: {}", r.training_mode);
    let _ = writeln!(s, "- effects: {}", r.effects.to_string().replace('\n', "\n  "));
    let _ = writeln!(s, "\n## Results (NeRFactor protocol)\n");
    let _ = writeln!(s, "| metric | value |\n|---|---:|");
    let rows = [
        ("re-rendered training views, PSNR (dB)", opt(e.train_psnr, 2)),
        ("validation views under the learned light, PSNR (dB)", opt(e.val_psnr, 2)),
        ("albedo PSNR raw (dB)", opt(e.albedo_psnr_raw, 2)),
        ("albedo PSNR scaled (dB)", opt(e.albedo_psnr_scaled, 2)),
        ("relighting PSNR raw (dB)", opt(e.relight_psnr_raw, 2)),
        ("relighting PSNR scaled (dB)", opt(e.relight_psnr_scaled, 2)),
        ("roughness MSE", opt(e.roughness_mse, 4)),
        ("metallic MSE", opt(e.metallic_mse, 4)),
        ("normal error (°)", opt(e.normal_error_deg, 2)),
    ];
    for (k, v) in rows {
        let _ = writeln!(s, "| {k} | {v} |");
    }
    for line in &e.not_computed {
        let _ = writeln!(s, "\nNot computed — {line}.");
    }
    if let Some(sc) = e.albedo_scale {
        let _ = writeln!(s, "\nAlbedo scale (first validation view, linear): {:.3}, {:.3}, {:.3}", sc[0], sc[1], sc[2]);
    }
    if !e.relight.is_empty() {
        let mut probes: Vec<&str> = e.relight.iter().map(|r| r.probe.as_str()).collect();
        probes.dedup();
        let _ = writeln!(s, "\n### Relighting per probe (mean over test views)\n\n| probe | raw (dB) | scaled (dB) |\n|---|---:|---:|");
        for p in probes {
            let rs: Vec<_> = e.relight.iter().filter(|r| r.probe == p).collect();
            let m = |f: &dyn Fn(&crate::eval::protocol::RelightRecord) -> f64| rs.iter().map(|r| f(r)).sum::<f64>() / rs.len() as f64;
            let _ = writeln!(s, "| {p} | {:.2} | {:.2} |", m(&|r| r.psnr_raw), m(&|r| r.psnr_scaled));
        }
    }
    let _ = writeln!(s, "\n## Time per stage\n\n| stage | seconds |\n|---|---:|");
    let total: f64 = r.stage_seconds.iter().map(|x| x.1).sum();
    for (k, v) in &r.stage_seconds {
        let _ = writeln!(s, "| {k} | {v:.1} |");
    }
    let _ = writeln!(s, "| **total** | **{total:.1}** |");
    if !plots.is_empty() {
        let _ = writeln!(s, "\n## Curves\n");
        for (title, path) in plots {
            let _ = writeln!(s, "![{title}]({path})\n");
        }
    }
    s
}

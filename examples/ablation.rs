//! The prior ablation (issue 5): none / idarb-sim / oracle (and idarb or labels:DIR when asked) on
//! one scene with the same seed, budget and settings, plus the prior-quality sweep; writes
//! ablation.md, ablation.json and prior_quality.png.
//!
//! cargo run --release --example ablation -- [--scene nerfactor_hotdog] [--iterations N]
//!     [--mode auto|split-sum|mc] [--sweep 0.5,1.5,2] [--labels DIR] [--idarb] [--out DIR]
//!     [--plan sweep.jsonl [--append]]   (write the runs to a sweep manifest instead: docs/scale.md)

use std::path::PathBuf;

use anyhow::Result;
use clap::Parser;
use reconstruct::fit::config::FitConfig;
use reconstruct::jobs::ablation::{default_out, default_sources, run, write_prior_quality_plot, AblationOptions, FULL_SWEEP};
use reconstruct::jobs::reconstruct::ReconstructOptions;
use reconstruct::jobs::sweep::plan::{self as sweep_plan, write_plan, PlanArgs};
use reconstruct::prior::source::PriorSource;
use reconstruct::render::view::ShadingMode;

#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

#[derive(Parser)]
struct Args {
    #[arg(long, default_value = "nerfactor_hotdog")]
    scene: String,
    /// Iterations (default: the default run's budget, so the `none` row is the default command).
    #[arg(long)]
    iterations: Option<usize>,
    /// auto (Monte Carlo when the scene needs shadows or interreflection), split-sum or mc.
    #[arg(long, default_value = "auto")]
    mode: String,
    /// idarb-sim levels of the prior-quality sweep (0 = oracle); empty for none.
    #[arg(long, value_delimiter = ',', default_values_t = FULL_SWEEP)]
    sweep: Vec<f64>,
    /// Also run --prior labels:DIR.
    #[arg(long)]
    labels: Option<PathBuf>,
    /// Also run --prior idarb (cached labels or the network with IDARB_WEIGHTS).
    #[arg(long)]
    idarb: bool,
    /// Monte Carlo samples of the evaluation renders (the default command's).
    #[arg(long, default_value_t = 16)]
    eval_spp: u32,
    #[arg(long)]
    out: Option<PathBuf>,
    /// Only redraw prior_quality.png from an existing ablation.json in the output folder.
    #[arg(long)]
    replot: bool,
    #[command(flatten)]
    plan: PlanArgs,
}

fn main() -> Result<()> {
    reconstruct::allocator::keep_freed_pages();
    let a = Args::parse();
    let mode = match a.mode.as_str() {
        "auto" => None,
        "mc" => Some(ShadingMode::MonteCarlo),
        "split-sum" => Some(ShadingMode::SplitSum),
        other => anyhow::bail!("--mode {other}: use auto, split-sum or mc"),
    };
    let defaults = FitConfig::default();
    let fit = FitConfig { mode: mode.unwrap_or(ShadingMode::SplitSum), iterations: a.iterations.unwrap_or(defaults.iterations), ..defaults };
    let out = a.out.unwrap_or_else(|| default_out(&a.scene));
    if a.replot {
        let path = out.join("ablation.json");
        let text = std::fs::read_to_string(&path).map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
        let v: serde_json::Value = serde_json::from_str(&text)?;
        let sweep: Vec<(f64, Option<f64>, Option<f64>)> = serde_json::from_value(v["sweep"].clone())?;
        let none = v["rows"].as_array().and_then(|rows| rows.iter().find(|r| r["prior"] == "none")).and_then(|r| r["evaluation"]["relight_psnr_scaled"].as_f64());
        write_prior_quality_plot(v["scene"].as_str().unwrap_or("scene"), &sweep, none, &out.join("prior_quality.png"))?;
        println!("wrote {}", out.join("prior_quality.png").display());
        return Ok(());
    }
    let base = ReconstructOptions { auto_mode: mode.is_none(), ..ReconstructOptions::new(&a.scene, fit, a.eval_spp, out.clone()) };
    let mut sources = default_sources();
    if a.idarb {
        sources.push(PriorSource::Idarb);
    }
    if let Some(d) = a.labels {
        sources.push(PriorSource::LabelsDir(d));
    }
    let opts = AblationOptions { base, sources, sweep: a.sweep };
    if let Some(path) = &a.plan.plan {
        println!("{}", write_plan(path, &sweep_plan::ablation(&opts), a.plan.append)?);
        return Ok(());
    }
    let report = run(&opts)?;
    println!("{}", report.markdown());
    println!("wrote {}", out.join("ablation.md").display());
    Ok(())
}

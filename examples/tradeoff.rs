//! What accuracy costs in time (issue 5): sweeps shading mode, samples per pixel, the denoiser,
//! resolution, effects (shadows, interreflection bounces), iterations and labelled-view count on one scene; writes tradeoff.csv and
//! tradeoff.png (Pareto front marked) and prints the front.
//!
//! cargo run --release --example tradeoff -- [--scene nerfactor_hotdog] [--iterations 200] [--out DIR]
//!     [--plan sweep.jsonl [--append]]   (write the runs to a sweep manifest instead: docs/scale.md)

use std::path::PathBuf;

use anyhow::Result;
use clap::Parser;
use reconstruct::fit::config::FitConfig;
use reconstruct::jobs::reconstruct::ReconstructOptions;
use reconstruct::jobs::sweep::plan::{self as sweep_plan, write_plan, PlanArgs};
use reconstruct::jobs::tradeoff::{default_out, default_points, front_table, run};

#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

#[derive(Parser)]
struct Args {
    #[arg(long, default_value = "nerfactor_hotdog")]
    scene: String,
    /// Base iteration count (the sweep also runs ⅓× and 3×).
    #[arg(long, default_value_t = 200)]
    iterations: usize,
    /// Test views relit per point (all 8 probes each).
    #[arg(long, default_value_t = 2)]
    test_views: usize,
    #[arg(long, default_value_t = 8)]
    eval_spp: u32,
    #[arg(long)]
    out: Option<PathBuf>,
    #[command(flatten)]
    plan: PlanArgs,
}

fn main() -> Result<()> {
    reconstruct::allocator::keep_freed_pages();
    let a = Args::parse();
    let out = a.out.unwrap_or_else(|| default_out(&a.scene));
    let base = ReconstructOptions {
        progress: false,
        labelled_views: 100,
        eval_test_views: Some(a.test_views),
        ..ReconstructOptions::new(&a.scene, FitConfig { checkpoint_every: 0, ..FitConfig::default() }, a.eval_spp, out.clone())
    };
    if let Some(path) = &a.plan.plan {
        println!("{}", write_plan(path, &sweep_plan::tradeoff(&base, &default_points(a.iterations))?, a.plan.append)?);
        return Ok(());
    }
    let results = run(&base, &default_points(a.iterations))?;
    println!("{}", front_table(&results));
    println!("wrote {} and {}", out.join("tradeoff.csv").display(), out.join("tradeoff.png").display());
    Ok(())
}

//! The geometry stage alone on a scene: visual hull, then the geometry pass, with the cost of a
//! pass step split into its parts (G-buffers, shading, backward, update) and the
//! geometry scores of the hull and of the result against the ground truth (when the data has a
//! mesh and depth maps). For measuring shape recovery without the material passes.
//!
//!     cargo run --release --example bench_geometry [-- --scene nerfactor_hotdog --iterations 600 --json]
//!
//! Without `--scene` it runs on the hotdog when the shared data is present, else on the embedded
//! default scene. `--json` prints one object with the timings and scores.

use std::time::Instant;

use anyhow::Result;
use clap::Parser;
use reconstruct::fit::geometry_pass::GeometryPassConfig;
use reconstruct::geometry::bvh::Bvh;
use reconstruct::jobs::geometry::{obtain_geometry, score_geometry, scores_summary, GeometrySource, PassLabels};
use reconstruct::jobs::reconstruct::prior_context;
use reconstruct::prior::source::{make_prior, PriorSource};
use reconstruct::scene::spec::shared_dir;
use reconstruct::scene::SceneSpec;

#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

#[derive(Parser)]
struct Args {
    /// Scene name or spec file (default: nerfactor_hotdog when the shared data is present, else default).
    #[arg(long)]
    scene: Option<String>,
    /// Data folder overriding the spec's.
    #[arg(long)]
    data: Option<std::path::PathBuf>,
    /// Geometry-pass iterations (default: the pass's default).
    #[arg(long)]
    iterations: Option<usize>,
    /// Weight of the per-vertex colour smoothness (default: the pass's default).
    #[arg(long)]
    kd_smoothness: Option<f64>,
    /// Position step per edge (default: the pass's default).
    #[arg(long)]
    step_per_edge: Option<f64>,
    /// Large Steps λ (default: the pass's default).
    #[arg(long)]
    lambda: Option<f64>,
    /// Views per step (default: the pass's default).
    #[arg(long)]
    batch: Option<usize>,
    /// The last stage's edge in pixel footprints (default: the pass's default).
    #[arg(long)]
    final_edge_pixels: Option<f64>,
    /// Every stage at the views' full resolution (the pass's `coarse_views` off).
    #[arg(long)]
    full_resolution: bool,
    /// Write the reconstructed mesh (OBJ) here.
    #[arg(long)]
    save: Option<std::path::PathBuf>,
    /// Print one JSON object instead of tables.
    #[arg(long)]
    json: bool,
    /// Label source for the pass's normal prior (none, oracle, idarb-sim, labels:DIR, idarb).
    #[arg(long, default_value = "none")]
    prior: String,
    /// Weight of the pass's normal prior in its last stage (default: the pass's default).
    #[arg(long)]
    normal_prior: Option<f64>,
    /// The earlier stages' weight of the normal prior as a share of the last stage's (default: the
    /// pass's default; 1 holds one weight in every stage).
    #[arg(long)]
    normal_prior_coarse_share: Option<f64>,
    /// Write every step's loss here, one per line (for comparing runs step by step).
    #[arg(long)]
    losses: Option<std::path::PathBuf>,
    /// Seed of the pass (its view batches; default: the pass's default), to measure how far
    /// apart two runs of the same settings land.
    #[arg(long)]
    seed: Option<u64>,
}

fn main() -> Result<()> {
    reconstruct::allocator::keep_freed_pages();
    let args = Args::parse();
    let scene = args.scene.clone().unwrap_or_else(|| {
        if shared_dir().join("data/nerfactor/hotdog_2163").is_dir() { "nerfactor_hotdog".into() } else { "default".into() }
    });
    let mut spec = SceneSpec::find(&scene)?;
    if let Some(d) = &args.data {
        spec = spec.with_data_dir(d);
    }
    let dataset = spec.load_dataset()?;
    let mut pass = GeometryPassConfig::default();
    if let Some(n) = args.iterations {
        pass.iterations = n;
    }
    if let Some(w) = args.kd_smoothness {
        pass.kd_smoothness = w;
    }
    if let Some(w) = args.step_per_edge {
        pass.step_per_edge = w;
    }
    if let Some(l) = args.lambda {
        pass.lambda = l;
    }
    if let Some(b) = args.batch {
        pass.batch = b;
    }
    if let Some(e) = args.final_edge_pixels {
        pass.final_edge_pixels = e;
    }
    pass.coarse_views &= !args.full_resolution;
    if let Some(w) = args.normal_prior {
        pass.normal_prior = w;
    }
    if let Some(s) = args.normal_prior_coarse_share {
        pass.normal_prior_coarse_share = s;
    }
    if let Some(s) = args.seed {
        pass.seed = s;
    }
    let t = Instant::now();
    let source: PriorSource = args.prior.parse()?;
    let prior = make_prior(&source, &prior_context(0, None))?;
    let labels = PassLabels { prior: prior.as_ref(), views: (0..dataset.train.len()).collect() };
    let labels = (source != PriorSource::None).then_some(&labels);
    let outcome = obtain_geometry(&spec, &dataset, GeometrySource::Reconstruct, &pass, labels, !args.json)?;
    let total = t.elapsed().as_secs_f64();
    let bvh = Bvh::build(&outcome.mesh);
    let scores = score_geometry(&spec, &dataset, &outcome.mesh, &bvh, outcome.hull.as_ref());
    if let Some(path) = &args.save {
        reconstruct::geometry::obj::write_obj(path, &outcome.mesh, &[])?;
    }
    let p = outcome.report.pass.as_ref().expect("reconstruction records its pass");
    if let Some(path) = &args.losses {
        let lines: String = p.history.iter().map(|h| format!("{} {:e} {:e} {}\n", h.iteration, h.loss, h.mask_mse, h.step_taken)).collect();
        std::fs::write(path, lines)?;
    }
    let hull = outcome.report.hull.as_ref().expect("reconstruction records its hull");
    let steps = p.history.len().max(1) as f64;
    let per_step = |s: f64| 1e3 * s / steps;
    let split = [
        ("G-buffers", p.timings.gbuffer),
        ("shading", p.timings.shading),
        ("backward", p.timings.backward),
        ("update (Large Steps solve, flip checks)", p.timings.update),
        ("remesh between stages, fold checks", p.timings.remesh),
    ];
    if args.json {
        let split_json: serde_json::Map<String, serde_json::Value> = split.iter().map(|(k, v)| (k.to_string(), per_step(*v).into())).collect();
        let out = serde_json::json!({
            "scene": scene,
            "hull": { "seconds": hull.seconds, "triangles": hull.triangles, "target_edge": hull.target_edge },
            "pass": { "seconds": p.seconds, "iterations": p.history.len(), "views_per_step": p.config.batch,
                      "resolution": p.resolution, "stages": p.stages, "triangles": outcome.mesh.triangles.len(), "ms_per_step": split_json },
            "stage_seconds": total,
            "scores": scores,
        });
        println!("{}", serde_json::to_string_pretty(&out)?);
        return Ok(());
    }
    println!("scene {scene}: visual hull {:.1} s ({} triangles, target edge {:.4}), geometry pass {:.1} s", hull.seconds, hull.triangles, hull.target_edge, p.seconds);
    println!(
        "pass: {} steps × {} views at {}×{}, final mesh {} triangles; ms per step:",
        p.history.len(),
        p.config.batch,
        p.resolution[0],
        p.resolution[1],
        outcome.mesh.triangles.len()
    );
    for st in &p.stages {
        println!(
            "stage from iteration {}: target edge {:.4}, {} vertices, {} triangles, views at {:.2} of their resolution, {:.1} % of the surface facing inward at its end {}",
            st.first_iteration,
            st.target_edge,
            st.vertices,
            st.triangles,
            st.view_scale,
            100.0 * st.inward_share_at_end.unwrap_or(f64::NAN),
            st.note
        );
    }
    println!("| part | ms per step |\n|---|---:|");
    for (name, s) in split {
        println!("| {name} | {:.1} |", per_step(s));
    }
    println!("| whole step | {:.1} |", 1e3 * p.history.iter().map(|h| h.seconds).sum::<f64>() / steps);
    println!("(no BVH rebuild: the pass finds its G-buffers by projecting the triangles, render::gbuffer_raster)");
    println!("{}", scores_summary(&scores));
    Ok(())
}

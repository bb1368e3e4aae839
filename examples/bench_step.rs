//! Time of one gradient step (render + backward + Adam; one 256² view; kd/ks textures and the
//! light as parameters) for split-sum and for Monte Carlo at 4 and 16 spp, direct light and with
//! 3 interreflection bounces (and 4 spp with the cross-bilateral denoiser, `--denoise`), and beside it, measured in the same run, the same step in Mitsuba 3
//! (`llvm_ad_rgb`, `prb` at max_depth 2 and 5) on the same mesh, textures, light and resolution
//! (tools/mitsuba/gradient_step.py; skipped with a note when Mitsuba or its LLVM is missing).
//!
//! Each row also gives the rays a step traced (counted by the renderer, `render::ray_count`: the
//! tally's growth over the step) and secondary rays per second of the whole step. A second table
//! splits the step into its phases (`fit::history::StepPhases`: render, loss, backward, update;
//! medians of each phase over the timed steps).
//!
//! cargo run --release --example bench_step [-- --scene nerfactor_hotdog --steps 10 --no-mitsuba --json --only "16 spp"]
//!
//! `--json` prints one object `{"rows": [...]}` to stdout (notes go to stderr): per setting `mode`,
//! `spp`, `bounces`, `reconstruct_s` (median), the ray counts, the phases' medians (`render_s`,
//! `loss_s`, `backward_s`, `update_s`), and `mitsuba_s` only where Mitsuba ran.

use std::path::PathBuf;
use std::process::Command;
use std::time::Instant;

use anyhow::{Context, Result};
use clap::Parser;
use reconstruct::fit::config::FitConfig;
use reconstruct::fit::fitter::Fit;
use reconstruct::fit::history::StepPhases;
use reconstruct::fit::parameters::Parameters;
use reconstruct::fit::export::{write_light, write_model};
use reconstruct::image::io::write_exr;
use reconstruct::fit::geometry_pass::GeometryPassConfig;
use reconstruct::jobs::reconstruct::{prepare, shading_context, GeometrySource, Prepared};
use reconstruct::scene_data::ground_truth_mesh;
use reconstruct::light::CubeMap;
use reconstruct::material::texture_maps::MaterialTextures;
use reconstruct::render::effects::Effects;
use reconstruct::render::ray_count::{self, RayCount};
use reconstruct::render::view::ShadingMode;

#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

#[derive(Parser)]
struct Args {
    #[arg(long, default_value = "nerfactor_hotdog")]
    scene: String,
    /// Timed steps per setting (after one warm-up step).
    #[arg(long, default_value_t = 10)]
    steps: usize,
    #[arg(long, default_value_t = 512)]
    texture_res: usize,
    #[arg(long, default_value_t = 64)]
    light_res: usize,
    #[arg(long)]
    no_mitsuba: bool,
    /// Print one JSON object (rows of mode, spp, bounces, reconstruct_s, ...) instead of tables.
    #[arg(long)]
    json: bool,
    /// Run only the settings whose name contains this text (for example "4 spp, direct"), to
    /// profile one setting with `perf record`.
    #[arg(long)]
    only: Option<String>,
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() -> Result<()> {
    reconstruct::allocator::keep_freed_pages();
    let args = Args::parse();
    let prepared = prepare(&args.scene, None, GeometrySource::GroundTruth, &GeometryPassConfig::default(), &FitConfig { texture_res: args.texture_res, ..FitConfig::default() }, 1, false)?;
    // One view, the first training view, as the Mitsuba script uses.
    let view = prepared.views[0].clone();
    // Tables and notes go to stdout, or to stderr when stdout carries the JSON.
    let say = |text: String| if args.json { eprintln!("{text}") } else { println!("{text}") };
    say(format!(
        "scene {}: view {} ({}×{}, {} covered pixels), textures {}², light 6×{}², the scene's effects: {}",
        prepared.spec.name,
        view.name,
        view.camera.width,
        view.camera.height,
        view.len(),
        args.texture_res,
        args.light_res,
        prepared.effects.to_string().lines().next().unwrap_or_default()
    ));
    // Both sides start from the same values: ground-truth materials baked into the atlas and the
    // training probe as the light.
    let textures = MaterialTextures::bake_from(&ground_truth_mesh(&prepared.spec)?, &prepared.atlas, args.texture_res)?;
    let light = CubeMap::from_latlong(&prepared.spec.load_train_probe()?.radiance_image(), args.light_res);
    // (name, mode, spp, effects, denoiser, Mitsuba max_depth of the same light transport; Mitsuba's
    // step has no denoiser, so that row has no counterpart)
    let bounced = Effects::with_bounces(3);
    let settings: Vec<(String, ShadingMode, u32, Effects, bool, Option<u32>)> = vec![
        ("split-sum".into(), ShadingMode::SplitSum, 0, Effects::DIRECT, false, None),
        ("MC 4 spp, direct light".into(), ShadingMode::MonteCarlo, 4, Effects::DIRECT, false, Some(2)),
        ("MC 16 spp, direct light".into(), ShadingMode::MonteCarlo, 16, Effects::DIRECT, false, Some(2)),
        ("MC 4 spp, 3 bounces".into(), ShadingMode::MonteCarlo, 4, bounced, false, Some(5)),
        ("MC 16 spp, 3 bounces".into(), ShadingMode::MonteCarlo, 16, bounced, false, Some(5)),
        ("MC 4 spp, 3 bounces, denoised".into(), ShadingMode::MonteCarlo, 4, bounced, true, None),
    ];
    let mut rows = Vec::new();
    for (name, mode, spp, effects, denoise, depth) in settings {
        if args.only.as_ref().is_some_and(|only| !name.contains(only.as_str())) {
            continue;
        }
        let config = FitConfig { mode, spp: spp.max(1), batch: 1, iterations: args.steps + 1, texture_res: args.texture_res, light_res: args.light_res, checkpoint_every: 0, denoise, ..FitConfig::default() };
        let mut ctx = shading_context(&prepared, &config);
        ctx.effects = effects;
        let mut fit = Fit::new(config.clone(), Parameters::from_values(&textures, &light)?, vec![view.clone()], ctx)?;
        let (mut times, mut phases, mut rays) = (Vec::new(), Vec::new(), RayCount::ZERO);
        for k in 0..=args.steps {
            let (t, before) = (Instant::now(), ray_count::traced_so_far());
            let record = match fit.step() {
                Ok(record) => record,
                Err(e) => {
                    say(format!("{name}: {e:#}"));
                    break;
                }
            };
            if k > 0 {
                times.push(t.elapsed().as_secs_f64());
                phases.push(record.phases);
                rays += ray_count::traced_so_far() - before;
            }
        }
        if !times.is_empty() {
            // Rays of the mean step (steps draw new samples, so counts vary a little).
            let n = times.len() as u64;
            let per_step = RayCount { primary: rays.primary / n, shadow: rays.shadow / n, bounce: rays.bounce / n };
            let phase = |f: fn(&StepPhases) -> f64| median(phases.iter().map(f).collect());
            let phases = StepPhases { render: phase(|p| p.render), loss: phase(|p| p.loss), backward: phase(|p| p.backward), update: phase(|p| p.update) };
            rows.push(Row { name, mode, spp, bounces: effects.indirect_bounces, denoise, depth, secs: median(times), phases, rays: per_step });
        }
    }
    let mitsuba = if args.no_mitsuba { None } else { run_mitsuba(&prepared, &textures, &light, &args).map_err(|e| say(format!("Mitsuba: skipped ({e:#})"))).ok() };
    let mitsuba_step = |depth: u32, spp: u32, key: &str| mitsuba.as_ref().and_then(|m: &serde_json::Value| m["max_depth"][depth.to_string()][spp.to_string()][key].as_f64());
    if args.json {
        let out: Vec<serde_json::Value> = rows
            .iter()
            .map(|r| {
                let mode = match r.mode {
                    ShadingMode::SplitSum => "splitsum",
                    ShadingMode::MonteCarlo => "montecarlo",
                };
                let mut v = serde_json::json!({
                    "mode": mode, "spp": r.spp, "bounces": r.bounces, "denoise": r.denoise, "reconstruct_s": r.secs,
                    "primary_rays": r.rays.primary, "shadow_rays": r.rays.shadow, "bounce_rays": r.rays.bounce,
                    "secondary_mrays_per_s": r.rays.secondary_mrays_per_s(r.secs),
                    "render_s": r.phases.render, "loss_s": r.phases.loss, "backward_s": r.phases.backward, "update_s": r.phases.update,
                });
                if let Some((d, m)) = r.depth.and_then(|d| mitsuba_step(d, r.spp, "median_s").map(|m| (d, m))) {
                    v["mitsuba_s"] = serde_json::json!(m);
                    v["mitsuba_max_depth"] = serde_json::json!(d);
                }
                v
            })
            .collect();
        println!("{}", serde_json::json!({ "scene": prepared.spec.name, "view": view.name, "covered_pixels": view.len(), "steps": args.steps, "threads": rayon::current_num_threads(), "rows": out }));
        return Ok(());
    }
    println!("\n| step (render + backward + Adam), 1 view | reconstruct (s) | secondary rays / step | secondary Mrays/s | Mitsuba 3 llvm_ad_rgb prb (s) |\n|---|---:|---:|---:|---:|");
    for r in &rows {
        let m = r.depth.and_then(|d| mitsuba_step(d, r.spp, "median_s"));
        let label = r.depth.map_or(String::new(), |d| format!(" (max_depth {d})"));
        let mrays = if r.rays.secondary() > 0 { format!("{:.2}", r.rays.secondary_mrays_per_s(r.secs)) } else { "–".into() };
        println!("| {} | {:.3} | {} | {mrays} | {}{label} |", r.name, r.secs, r.rays.secondary(), m.map_or("–".into(), |v| format!("{v:.3}")));
    }
    println!("\n| phases of the step (medians, ms) | render | loss | backward | update |\n|---|---:|---:|---:|---:|");
    for r in &rows {
        let p = r.phases;
        println!("| {} | {:.1} | {:.1} | {:.1} | {:.1} |", r.name, 1e3 * p.render, 1e3 * p.loss, 1e3 * p.backward, 1e3 * p.update);
    }
    if let Some(m) = &mitsuba {
        println!("\nMitsuba {} ({}, {} threads); first step incl. JIT (s):", m["mitsuba_version"].as_str().unwrap_or("?"), m["variant"].as_str().unwrap_or("?"), m["threads"]);
        for r in &rows {
            if let Some(d) = r.depth {
                println!("  max_depth {d}, {} spp: {:.2}", r.spp, mitsuba_step(d, r.spp, "first_s").unwrap_or(f64::NAN));
            }
        }
    }
    Ok(())
}

/// One measured setting: median step time and the rays of a step.
struct Row {
    name: String,
    mode: ShadingMode,
    spp: u32,
    bounces: u32,
    denoise: bool,
    /// Mitsuba's max_depth for the same light transport (None: not compared).
    depth: Option<u32>,
    secs: f64,
    phases: StepPhases,
    rays: RayCount,
}

/// Writes the step's inputs (atlas mesh with ground-truth-baked textures, the training light,
/// camera, target) and runs the Mitsuba script on them.
fn run_mitsuba(prepared: &Prepared, textures: &MaterialTextures, light: &CubeMap, args: &Args) -> Result<serde_json::Value> {
    let dir = std::env::temp_dir().join(format!("reconstruct-bench-step-{}", std::process::id()));
    write_model(&dir, &prepared.atlas.mesh, textures)?;
    write_light(&dir, light)?;
    let view = &prepared.dataset.train[0];
    let cam = &view.camera;
    let c2w: Vec<Vec<f32>> = (0..4).map(|r| (0..4).map(|c| cam.c2w.col(c)[r]).collect()).collect();
    std::fs::write(dir.join("camera.json"), serde_json::json!({"c2w": c2w, "fov_x": cam.fov_x, "width": cam.width, "height": cam.height}).to_string())?;
    write_exr(&dir.join("target.exr"), &view.load_rgba()?)?;
    let script = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tools/mitsuba/gradient_step.py");
    let out = Command::new("python3").arg(&script).arg(&dir).args(["--json", "--steps", &args.steps.to_string()]).output().context("running python3")?;
    anyhow::ensure!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr).trim());
    let text = String::from_utf8_lossy(&out.stdout);
    let json = text.lines().rev().find(|l| l.trim_start().starts_with('{')).context("no JSON from the Mitsuba script")?;
    let _ = std::fs::remove_dir_all(&dir);
    Ok(serde_json::from_str(json)?)
}

//! Render speed on the hotdog's ground-truth mesh (66k triangles; the embedded default scene's
//! mesh when the shared data is missing): ms per 256² frame for the G-buffer, split-sum and Monte
//! Carlo shading at 1/4/16 spp with and without shadows and bounces, the rays each frame traced
//! (counted by the renderer: `render::ray_count`) and secondary rays per second; then how the cost
//! grows, a sweep over resolution (64² to 512², 4 spp) and spp (1 to 64, 128²) with direct light
//! and shadows, each step's cost ratio shown per doubling of pixels × samples.
//!
//!     cargo run --release --example bench_render [-- --json]
//!
//! `--json` prints one object `{"rows": [...]}`; each row has `stage`, `spp`, `bounces`,
//! `ms_per_frame`, `secondary_mrays_per_s` and the raw counts, and beside the wall-clock figures
//! the CPU time of a frame over all threads (`cpu_ms_per_frame`, `secondary_mrays_per_cpu_s`; the
//! sweep's `cpu_cost_ratio_per_doubling`): on a machine shared with other jobs these move much
//! less than wall time.

use std::time::Instant;

use clap::Parser;
use reconstruct::geometry::bvh::Bvh;
use reconstruct::geometry::ground_truth::load_ground_truth;
use reconstruct::light::CubeMap;
use reconstruct::render::effects::Effects;
use reconstruct::render::gbuffer::GBuffer;
use reconstruct::render::montecarlo::{self, McSettings};
use reconstruct::render::ray_count::RayCount;
use reconstruct::render::splitsum;
use reconstruct::render::view::{ray_epsilon, PreparedLight};
use reconstruct::scene_data::default_scene;
use reconstruct::scene::spec::shared_dir;
use reconstruct::scene::Camera;
use serde_json::json;

#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

#[derive(Parser)]
struct Args {
    /// Print one JSON object instead of tables.
    #[arg(long)]
    json: bool,
}

/// CPU time all threads of this process have run, in ns (the sum over /proc/self/task/*/schedstat;
/// None off Linux). Wall-clock times swing with other jobs on a loaded machine; CPU time per frame
/// much less so.
fn process_cpu_ns() -> Option<u64> {
    let mut total = 0u64;
    for task in std::fs::read_dir("/proc/self/task").ok()? {
        let text = std::fs::read_to_string(task.ok()?.path().join("schedstat")).ok()?;
        total += text.split_whitespace().next()?.parse::<u64>().ok()?;
    }
    Some(total)
}

/// Median wall time of `runs` calls and median CPU time (all threads) of a call, in milliseconds,
/// and the last call's value.
fn time_ms<T>(runs: usize, mut f: impl FnMut() -> T) -> (f64, Option<f64>, T) {
    let mut last = None;
    let (mut wall, mut cpu) = (Vec::new(), Vec::new());
    for _ in 0..runs {
        let (t, c0) = (Instant::now(), process_cpu_ns());
        let v = std::hint::black_box(f());
        wall.push(t.elapsed().as_secs_f64() * 1e3);
        if let (Some(c0), Some(c1)) = (c0, process_cpu_ns()) {
            cpu.push(c1.saturating_sub(c0) as f64 * 1e-6);
        }
        last = Some(v);
    }
    let median = |mut v: Vec<f64>| {
        v.sort_by(|a, b| a.total_cmp(b));
        v[v.len() / 2]
    };
    let cpu = (cpu.len() == runs).then(|| median(cpu));
    (median(wall), cpu, last.expect("runs > 0"))
}

/// How many timed calls give a median steady enough to compare with its neighbours: enough to fill
/// `budget_ms` of wall time at the cost of one untimed warm-up call, at least 3 and at most 101.
/// Small frames (a few ms) vary by ±20 % from call to call here; a fixed count of 3 let one slow
/// call move a cost ratio of the sweep by 0.3.
fn runs_within<T>(budget_ms: f64, mut f: impl FnMut() -> T) -> usize {
    let t = Instant::now();
    std::hint::black_box(f());
    let once = t.elapsed().as_secs_f64() * 1e3;
    ((budget_ms / once.max(1e-3)) as usize).clamp(3, 101) | 1
}

/// Pixels whose primary ray hit the object: the ones Monte Carlo shades.
fn covered_pixels(g: &GBuffer) -> usize {
    g.surfels.iter().flatten().count()
}

/// One measured setting.
struct Row {
    stage: String,
    width: usize,
    /// Pixels the object covers at this resolution: the ones Monte Carlo shades.
    covered: usize,
    spp: u32,
    bounces: u32,
    ms: f64,
    /// CPU time of a frame over all threads (median), where the OS reports it.
    cpu_ms: Option<f64>,
    rays: RayCount,
}

impl Row {
    fn secondary_mrays(&self) -> f64 {
        self.rays.secondary_mrays_per_s(self.ms / 1e3)
    }

    /// Secondary rays per CPU second (all threads together): what one core traces while shading.
    fn secondary_mrays_per_cpu_s(&self) -> Option<f64> {
        self.cpu_ms.map(|c| self.rays.secondary_mrays_per_s(c / 1e3))
    }

    fn json(&self) -> serde_json::Value {
        json!({
            "stage": self.stage, "resolution": self.width, "covered_pixels": self.covered, "spp": self.spp, "bounces": self.bounces,
            "ms_per_frame": self.ms, "secondary_mrays_per_s": self.secondary_mrays(),
            "cpu_ms_per_frame": self.cpu_ms, "secondary_mrays_per_cpu_s": self.secondary_mrays_per_cpu_s(),
            "primary_rays": self.rays.primary, "shadow_rays": self.rays.shadow, "bounce_rays": self.rays.bounce,
        })
    }
}

fn main() -> anyhow::Result<()> {
    reconstruct::allocator::keep_freed_pages();
    let args = Args::parse();
    let gt = shared_dir().join("data/nerfactor/hotdog_2163/gt");
    let (mesh, what) = if gt.exists() {
        (load_ground_truth(&gt)?, "hotdog ground truth")
    } else {
        eprintln!("note: {} not found; benchmarking the embedded default scene instead", gt.display());
        (default_scene::mesh(), "embedded default scene")
    };
    let probe = reconstruct::image::io::read_probe(&default_scene::fixture_probe_dir().join("courtyard.hdr"))?;
    let light = PreparedLight::new(CubeMap::from_latlong(&probe, 128));
    let t_build = Instant::now();
    let bvh = Bvh::build(&mesh);
    let build_ms = t_build.elapsed().as_secs_f64() * 1e3;
    light.split_sum();
    light.sampler();
    let camera = |res: usize| Camera::look_at(glam::Vec3::new(2.5, -2.6, 2.0), glam::Vec3::ZERO, glam::Vec3::Z, 0.6911, res, res);
    let scene = montecarlo::TraceScene { mesh: &mesh, bvh: &bvh, materials: &mesh };
    let eps = ray_epsilon(&mesh);
    let mut rows = Vec::new();

    // Fixed 256² frame: every stage.
    let gbuf = GBuffer::trace(&mesh, &bvh, &camera(256));
    let params = gbuf.material_params(&mesh);
    let covered = covered_pixels(&gbuf);
    let (g_ms, g_cpu, g) = time_ms(9, || GBuffer::trace(&mesh, &bvh, &camera(256)));
    rows.push(Row { stage: "gbuffer".into(), width: 256, covered, spp: 1, bounces: 0, ms: g_ms, cpu_ms: g_cpu, rays: g.rays() });
    let (ss, lut) = light.split_sum();
    let (s_ms, s_cpu, _) = time_ms(9, || splitsum::shade(&gbuf, &params, ss, lut, Effects::DIRECT));
    rows.push(Row { stage: "splitsum".into(), width: 256, covered, spp: 0, bounces: 0, ms: s_ms, cpu_ms: s_cpu, rays: RayCount::ZERO });
    let no_shadows = Effects { shadows: false, specular: true, indirect_bounces: 0 };
    let effects = [("mc_no_shadows", no_shadows), ("mc_direct", Effects::DIRECT), ("mc_bounces", Effects::with_bounces(1)), ("mc_bounces", Effects::with_bounces(3))];
    for spp in [1u32, 4, 16] {
        for (stage, effects) in effects {
            let settings = McSettings { spp, seed: 1, effects, ray_epsilon: eps };
            let runs = if spp == 16 { 3 } else { 5 };
            let (ms, cpu_ms, out) = time_ms(runs, || montecarlo::shade(&gbuf, &params, light.sampler(), &scene, &settings, 0));
            rows.push(Row { stage: stage.into(), width: 256, covered, spp, bounces: effects.indirect_bounces, ms, cpu_ms, rays: out.rays });
        }
    }

    // Growth sweep: direct light with shadows. Each setting is timed for about this long, so the
    // medians of small and large frames are equally steady (about 5 s for the whole sweep).
    const SWEEP_BUDGET_MS: f64 = 400.0;
    let mut sweep = Vec::new();
    let sweep_row = |res: usize, spp: u32| {
        let g = GBuffer::trace(&mesh, &bvh, &camera(res));
        let p = g.material_params(&mesh);
        let settings = McSettings { spp, seed: 1, effects: Effects::DIRECT, ray_epsilon: eps };
        let frame = || montecarlo::shade(&g, &p, light.sampler(), &scene, &settings, 0);
        let (ms, cpu_ms, out) = time_ms(runs_within(SWEEP_BUDGET_MS, frame), frame);
        Row { stage: "sweep_mc_direct".into(), width: res, covered: covered_pixels(&g), spp, bounces: 0, ms, cpu_ms, rays: out.rays }
    };
    let by_resolution: Vec<Row> = [64, 128, 256, 512].into_iter().map(|r| sweep_row(r, 4)).collect();
    let by_spp: Vec<Row> = [1, 2, 4, 8, 16, 32, 64].into_iter().map(|s| sweep_row(128, s)).collect();
    // Cost ratio per doubling of pixels × samples between consecutive settings, in wall time and
    // in CPU time (the steadier of the two when other jobs share the machine).
    for series in [&by_resolution, &by_spp] {
        for (k, r) in series.iter().enumerate() {
            let per_doubling = |cost: &dyn Fn(&Row) -> Option<f64>| -> Option<f64> {
                let prev = series[..k].last()?;
                // Work is what Monte Carlo shades: covered pixels × samples. The covered share
                // of the image changes a little with resolution (the outline's pixels), so
                // width² would misstate the growth between resolutions.
                let work = |r: &Row| r.covered as f64 * r.spp as f64;
                Some((cost(r)? / cost(prev)?).powf(1.0 / (work(r) / work(prev)).log2()))
            };
            sweep.push((r, per_doubling(&|r| Some(r.ms)), per_doubling(&|r| r.cpu_ms)));
        }
    }

    if args.json {
        let mut out: Vec<serde_json::Value> = rows.iter().map(Row::json).collect();
        for (r, ratio, cpu_ratio) in &sweep {
            let mut v = r.json();
            v["cost_ratio_per_doubling"] = json!(ratio);
            v["cpu_cost_ratio_per_doubling"] = json!(cpu_ratio);
            out.push(v);
        }
        println!("{}", json!({ "scene": what, "triangles": mesh.triangles.len(), "covered_pixels_256": covered, "threads": rayon::current_num_threads(), "bvh_build_ms": build_ms, "rows": out }));
        return Ok(());
    }
    println!("# Render benchmark: {what}, {} triangles, 256x256, {covered} covered pixels, {} rayon threads", mesh.triangles.len(), rayon::current_num_threads());
    println!("BVH build: {build_ms:.1} ms\n");
    println!("| stage | spp | bounces | ms / frame | CPU ms / frame | primary rays | shadow rays | bounce rays | secondary Mrays/s | per CPU s |");
    println!("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    let opt = |x: Option<f64>| x.map_or("-".to_string(), |x| format!("{x:.2}"));
    for r in &rows {
        let (mrays, per_cpu) = if r.rays.secondary() > 0 { (format!("{:.2}", r.secondary_mrays()), opt(r.secondary_mrays_per_cpu_s())) } else { ("-".into(), "-".into()) };
        println!("| {} | {} | {} | {:.2} | {} | {} | {} | {} | {mrays} | {per_cpu} |", r.stage, r.spp, r.bounces, r.ms, opt(r.cpu_ms), r.rays.primary, r.rays.shadow, r.rays.bounce);
    }
    println!("\nCost growth, Monte Carlo with direct light and shadows (the ratio is per doubling of covered pixels × spp; 2.0 is linear):\n");
    println!("| resolution | covered pixels | spp | ms / frame | CPU ms / frame | secondary Mrays/s | cost ratio per doubling | in CPU time |");
    println!("|---:|---:|---:|---:|---:|---:|---:|---:|");
    for (r, ratio, cpu_ratio) in &sweep {
        println!("| {0}² | {1} | {2} | {3:.2} | {4} | {5:.2} | {6} | {7} |", r.width, r.covered, r.spp, r.ms, opt(r.cpu_ms), r.secondary_mrays(), opt(*ratio), opt(*cpu_ratio));
    }
    println!("\nRays are counted by the renderer (render::ray_count): shadow rays are any-hit occlusion tests, bounce rays the closest-hit rays of interreflection paths.");
    Ok(())
}

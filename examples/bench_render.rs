//! Render speed: ms per 256² frame for the G-buffer, split-sum and Monte Carlo shading at 1/4/16
//! spp with and without shadows, and rays per second. Uses the hotdog's ground-truth mesh
//! (66k triangles) when ../shared is present, else the embedded default scene's mesh.
//!
//!     cargo run --release --example bench_render

use std::time::Instant;

use reconstruct::geometry::bvh::Bvh;
use reconstruct::geometry::ground_truth::load_ground_truth;
use reconstruct::light::CubeMap;
use reconstruct::render::effects::Effects;
use reconstruct::render::gbuffer::GBuffer;
use reconstruct::render::montecarlo::{self, McSettings};
use reconstruct::render::splitsum;
use reconstruct::render::view::{ray_epsilon, PreparedLight};
use reconstruct::scene::default_scene;
use reconstruct::scene::spec::shared_dir;
use reconstruct::scene::Camera;

#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// Median wall time of `runs` calls, in milliseconds.
fn time_ms<T>(runs: usize, mut f: impl FnMut() -> T) -> f64 {
    let mut times: Vec<f64> = (0..runs)
        .map(|_| {
            let t = Instant::now();
            std::hint::black_box(f());
            t.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    times.sort_by(|a, b| a.total_cmp(b));
    times[runs / 2]
}

fn main() -> anyhow::Result<()> {
    let gt = shared_dir().join("data/nerfactor/hotdog_2163/gt");
    let (mesh, what) = if gt.exists() {
        (load_ground_truth(&gt)?, "hotdog ground truth")
    } else {
        println!("note: {} not found; benchmarking the embedded default scene instead", gt.display());
        (default_scene::mesh(), "embedded default scene")
    };
    let probe = reconstruct::image::io::read_probe(&default_scene::fixture_probe_dir().join("courtyard.hdr"))?;
    let light = PreparedLight::new(CubeMap::from_latlong(&probe, 128));
    let t_build = Instant::now();
    let bvh = Bvh::build(&mesh);
    let build_ms = t_build.elapsed().as_secs_f64() * 1e3;
    light.split_sum();
    light.sampler();
    let cam = Camera::look_at(glam::Vec3::new(2.5, -2.6, 2.0), glam::Vec3::ZERO, glam::Vec3::Z, 0.6911, 256, 256);
    let gbuf = GBuffer::trace(&mesh, &bvh, &cam);
    let params = gbuf.material_params(&mesh);
    let covered = gbuf.surfels.iter().filter(|s| s.is_some()).count();

    println!("# Render benchmark: {what}, {} triangles, 256x256, {covered} covered pixels, {} rayon threads", mesh.triangles.len(), rayon::current_num_threads());
    println!("BVH build: {build_ms:.1} ms\n");
    println!("| stage | ms / frame | Mrays/s |");
    println!("|---|---:|---:|");
    let g_ms = time_ms(9, || GBuffer::trace(&mesh, &bvh, &cam));
    println!("| G-buffer (primary rays) | {g_ms:.2} | {:.2} |", (256.0 * 256.0) / g_ms / 1e3);
    let (ss, lut) = light.split_sum();
    let s_ms = time_ms(9, || splitsum::shade(&gbuf, &params, ss, lut, Effects::DIRECT));
    println!("| split-sum shading | {s_ms:.2} | - |");
    let scene = montecarlo::TraceScene { mesh: &mesh, bvh: &bvh, materials: &mesh };
    let no_shadows = Effects { shadows: false, specular: true, indirect_bounces: 0 };
    let effects = [("shadows off", no_shadows), ("shadows on", Effects::DIRECT), ("1 bounce", Effects::with_bounces(1)), ("3 bounces", Effects::with_bounces(3))];
    for spp in [1u32, 4, 16] {
        for (name, effects) in effects {
            let settings = McSettings { spp, seed: 1, effects, ray_epsilon: ray_epsilon(&mesh) };
            let runs = if spp == 16 { 3 } else { 5 };
            let mut rays = 0;
            let ms = time_ms(runs, || rays = montecarlo::shade(&gbuf, &params, light.sampler(), &scene, &settings, 0).shadow_rays);
            let mrays = if effects.shadows { format!("{:.2}", rays as f64 / ms / 1e3) } else { "-".into() };
            println!("| MC {spp:>2} spp, {name} | {ms:.2} | {mrays} |");
        }
    }
    println!("\nMrays/s for MC counts the rays after the primary ones: shadow rays (one per strategy and sample) and, with bounces, the rays of the paths' later vertices.");
    Ok(())
}

//! Ray throughput on the hotdog ground-truth mesh (66k triangles).
//!
//!     cargo run --release --example bench_rays [-- <gt dir>]
//!
//! Coherent rays: 512² camera rays for 8 views (closest hit). Incoherent rays: from G-buffer hit
//! points (offset along the normal) in uniformly random directions, like shadow / bounce rays
//! (closest hit and any hit). Compares obvhs build presets for both of `Bvh`'s layouts: the float
//! 8-wide tree (the default; AVX2 and scalar node tests) and obvhs' CWBVH (node tests AVX-512 and
//! AVX2 8-wide where the CPU has them, and obvhs' own SSE test), and obvhs' binary BVH2 with its
//! own traversal. The first table is rayon-parallel wall clock, the second one thread's CPU time.
//! With `--features tinybvh`, tinybvh's layouts on the same rays, one thread, taking turns with
//! ours (`tinybvh`); for its 8-wide BVH8_CPU layout build with
//! `RUSTFLAGS="-C target-feature=+avx2,+fma"`. With `--features embree` (needs Debian
//! `libembree-dev`), Intel Embree 3 the same way (`embree`). Both are off by default.

use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use glam::{Mat4, Vec3, Vec3A};
use obvhs::bvh2::builder::build_bvh2_from_tris;
use obvhs::ray::{Ray, RayHit};
use obvhs::triangle::Triangle;
use obvhs::BvhBuildParams;
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use rayon::prelude::*;
use reconstruct::geometry::bvh::{Bvh, Layout};
use reconstruct::geometry::bvh_wide::NodeTest;
use reconstruct::geometry::ground_truth::load_ground_truth;
use reconstruct::geometry::Mesh;
use reconstruct::render::gbuffer::GBuffer;
use reconstruct::scene::camera::Camera;

#[cfg(feature = "embree")]
#[path = "bench_rays/embree.rs"]
mod embree;
#[cfg(any(feature = "embree", feature = "tinybvh"))]
#[path = "bench_rays/side_by_side.rs"]
mod side_by_side;
#[cfg(feature = "tinybvh")]
#[path = "bench_rays/tinybvh.rs"]
mod tinybvh;

fn cameras(size: usize) -> Vec<Camera> {
    // Eight views on a ring 4.03 units from the origin, 30° above the plate (like the dataset).
    (0..8)
        .map(|k| {
            let phi = k as f32 * std::f32::consts::TAU / 8.0;
            let eye = 4.03 * Vec3::new(phi.cos() * 0.866, phi.sin() * 0.866, 0.5);
            // OpenGL camera: x right, y up, looking down −z.
            let back = eye.normalize();
            let right = Vec3::Z.cross(back).normalize();
            let up = back.cross(right);
            let c2w = Mat4::from_cols(right.extend(0.0), up.extend(0.0), back.extend(0.0), eye.extend(1.0));
            Camera { c2w, fov_x: 0.6911, width: size, height: size }
        })
        .collect()
}

fn random_dir(rng: &mut Pcg64) -> Vec3 {
    let z: f32 = rng.random_range(-1.0..1.0);
    let phi: f32 = rng.random_range(0.0..std::f32::consts::TAU);
    let r = (1.0 - z * z).max(0.0).sqrt();
    Vec3::new(r * phi.cos(), r * phi.sin(), z)
}

/// CPU time this thread has run, in ns (Linux schedstat). With other jobs competing for the
/// cores, wall-clock rates drift run to run; per-CPU-second rates on one thread do not.
fn thread_cpu_ns() -> Option<u64> {
    std::fs::read_to_string("/proc/thread-self/schedstat").ok()?.split_whitespace().next()?.parse().ok()
}

/// Passes over the rays per query in [`cpu_rates`]; the best pass counts.
const ROUNDS: usize = 7;
/// Each timed pass traces the rays as many times as this many CPU seconds take: the VM's
/// thread clock advances in 4 ms ticks, which made a single trip over 161k rays (≈ 50 ms) step
/// by 8 %.
const PASS_SECONDS: f64 = 0.25;

/// Single-thread rays per CPU second of each query `f(q, ..)`, q < `queries`, over `rays` (best of [`ROUNDS`] passes). The
/// queries take turns within each round, so load that drifts during the run affects all alike and
/// their ratios are measured side by side.
fn cpu_rates(rays: &[(Vec3, Vec3)], queries: usize, f: &dyn Fn(usize, Vec3, Vec3) -> bool) -> Vec<Option<f64>> {
    let mut best: Vec<Option<f64>> = vec![None; queries];
    // Trips over the rays per pass, from one untimed trip of each query.
    let mut trips = vec![1usize; queries];
    for (q, trip) in trips.iter_mut().enumerate() {
        let t = Instant::now();
        std::hint::black_box(rays.iter().filter(|(o, d)| f(q, *o, *d)).count());
        *trip = (PASS_SECONDS / t.elapsed().as_secs_f64().max(1e-6)).ceil().clamp(1.0, 1000.0) as usize;
    }
    for _ in 0..ROUNDS {
        for q in 0..queries {
            let Some(t0) = thread_cpu_ns() else { return best };
            for _ in 0..trips[q] {
                std::hint::black_box(rays.iter().filter(|(o, d)| f(q, *o, *d)).count());
            }
            let Some(t1) = thread_cpu_ns() else { return best };
            let rate = (trips[q] * rays.len()) as f64 / ((t1 - t0).max(1) as f64 * 1e-9) / 1e6;
            best[q] = Some(best[q].map_or(rate, |b: f64| b.max(rate)));
        }
    }
    best
}

fn fmt_rate(r: Option<f64>) -> String {
    r.map_or("n/a".into(), |r| format!("{r:.2}"))
}

fn mrays(n: usize, t: Duration) -> f64 {
    n as f64 / t.as_secs_f64() / 1e6
}

fn main() -> Result<()> {
    let gt = std::env::args().nth(1).map(PathBuf::from).unwrap_or_else(|| {
        std::env::var_os("RECONSTRUCT_SHARED_DIR")
            .map(PathBuf::from)
            .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared"))
            .join("data/nerfactor/hotdog_2163/gt")
    });
    let mesh: Mesh = load_ground_truth(&gt).with_context(|| format!("loading the hotdog from {}", gt.display()))?;
    println!("hotdog: {} triangles, {} vertices, {} threads", mesh.triangles.len(), mesh.positions.len(), rayon::current_num_threads());

    // Coherent: primary rays. Incoherent: random directions from the visible surface points.
    let cams = cameras(512);
    let primary: Vec<(Vec3, Vec3)> =
        cams.iter().flat_map(|c| (0..c.width * c.height).map(move |i| (c.origin(), c.ray_dir((i % c.width) as f32 + 0.5, (i / c.width) as f32 + 0.5)))).collect();
    let reference_bvh = Bvh::build(&mesh);
    let mut rng = Pcg64::seed_from_u64(1);
    let mut secondary = Vec::new();
    for c in &cams {
        let gb = GBuffer::trace(&mesh, &reference_bvh, &c.resized(256, 256));
        for s in gb.surfels.iter().flatten() {
            let d = random_dir(&mut rng);
            let n = if d.dot(s.geo_normal) >= 0.0 { s.geo_normal } else { -s.geo_normal };
            secondary.push((s.position + 1e-4 * n, d));
        }
    }
    println!("{} coherent rays, {} incoherent rays\n", primary.len(), secondary.len());
    println!("Wall clock, rayon over all threads (sensitive to other load on the machine):\n");
    println!("| structure | build preset | build ms | MB | coherent closest Mray/s | incoherent closest Mray/s | incoherent any-hit Mray/s | primary hit rate |");
    println!("|---|---|---|---|---|---|---|---|");
    let coherent_subset = &primary[..2 * 512 * 512];
    let mut cpu_rows = Vec::new();

    let presets = [
        ("fast", BvhBuildParams::fast_build()),
        ("medium", BvhBuildParams::medium_build()),
        ("slow (spatial splits)", BvhBuildParams::slow_build()),
        // Leaves of at most one block of four triangles, and leaves collapsed less eagerly.
        ("medium, leaves ≤ 4", BvhBuildParams { max_prims_per_leaf: 4, ..BvhBuildParams::medium_build() }),
        ("medium, leaf cost 1", BvhBuildParams { collapse_traversal_cost: 1.0, ..BvhBuildParams::medium_build() }),
    ];
    let layouts = [(Layout::Float8, "float 8-wide (Bvh)"), (Layout::Cwbvh, "CWBVH")];
    for ((name, params), (layout, structure)) in presets.into_iter().flat_map(|p| layouts.map(|l| (p, l))) {
        let t = Instant::now();
        let bvh = Bvh::build_layout(&mesh, params, layout);
        let build = t.elapsed();
        // Warm-up and hit counting.
        let hits = primary.par_iter().filter(|(o, d)| bvh.closest_hit(*o, *d, 0.0, f32::INFINITY).is_some()).count();
        let best_of = |f: &dyn Fn() -> usize| -> Duration {
            (0..5)
                .map(|_| {
                    let t = Instant::now();
                    std::hint::black_box(f());
                    t.elapsed()
                })
                .min()
                .unwrap_or_default()
        };
        let coh = best_of(&|| primary.par_iter().filter(|(o, d)| bvh.closest_hit(*o, *d, 0.0, f32::INFINITY).is_some()).count());
        let inc = best_of(&|| secondary.par_iter().filter(|(o, d)| bvh.closest_hit(*o, *d, 0.0, f32::INFINITY).is_some()).count());
        let any = best_of(&|| secondary.par_iter().filter(|(o, d)| bvh.any_hit(*o, *d, 0.0, f32::INFINITY)).count());
        println!(
            "| {structure} | {name} | {:.0} | {:.1} | {:.2} | {:.2} | {:.2} | {:.3} |",
            build.as_secs_f64() * 1e3,
            bvh.footprint_bytes() as f64 / 1e6,
            mrays(primary.len(), coh),
            mrays(secondary.len(), inc),
            mrays(secondary.len(), any),
            hits as f64 / primary.len() as f64
        );
        // Every node test the CPU has, on the same BVH, taking turns (`cpu_rates`). The float
        // layout has an AVX2 test and a scalar one (which `NodeTest::Obvhs` selects).
        let candidates = match layout {
            Layout::Cwbvh => vec![NodeTest::Avx512, NodeTest::Avx2, NodeTest::Obvhs],
            Layout::Float8 => vec![NodeTest::Avx2, NodeTest::Obvhs],
        };
        let tests: Vec<NodeTest> = candidates.into_iter().filter(|t| t.supported()).collect();
        let coherent = cpu_rates(coherent_subset, tests.len(), &|k, o, d| bvh.closest_hit_using(tests[k], o, d, 0.0, f32::INFINITY).is_some());
        let incoherent = cpu_rates(&secondary, tests.len(), &|k, o, d| bvh.closest_hit_using(tests[k], o, d, 0.0, f32::INFINITY).is_some());
        let occlusion = cpu_rates(&secondary, tests.len(), &|k, o, d| bvh.any_hit_using(tests[k], o, d, 0.0, f32::INFINITY));
        for (k, test) in tests.iter().enumerate() {
            cpu_rows.push(format!(
                "| {structure}, {} node test{} | {name} | {} | {} | {} |",
                match (layout, test) {
                    (Layout::Float8, NodeTest::Obvhs) => "scalar",
                    (Layout::Float8, _) => "AVX2 8-wide",
                    _ => test.name(),
                },
                if layout == Layout::Float8 && *test == bvh.node_test() { " (default)" } else { "" },
                fmt_rate(coherent[k]),
                fmt_rate(incoherent[k]),
                fmt_rate(occlusion[k]),
            ));
        }
    }

    // BVH2 with obvhs' own triangle test, for the structure comparison.
    let tris: Vec<Triangle> = (0..mesh.triangles.len())
        .map(|t| {
            let [a, b, c] = mesh.triangle_positions(t);
            Triangle { v0: a.into(), v1: b.into(), v2: c.into() }
        })
        .collect();
    let t = Instant::now();
    let bvh2 = build_bvh2_from_tris(&tris, BvhBuildParams::medium_build(), &mut Duration::default());
    let build = t.elapsed();
    let closest = |o: Vec3, d: Vec3| {
        let mut hit = RayHit::none();
        let ray = Ray::new_inf(Vec3A::from(o), Vec3A::from(d) + Vec3A::ZERO);
        bvh2.ray_traverse(ray, &mut hit, |r, id| tris[bvh2.primitive_indices[id] as usize].intersect(r))
    };
    let any = |o: Vec3, d: Vec3| {
        let ray = Ray::new_inf(Vec3A::from(o), Vec3A::from(d) + Vec3A::ZERO);
        !bvh2.ray_traverse_miss(ray, |r, id| tris[bvh2.primitive_indices[id] as usize].intersect(r))
    };
    let time = |f: &dyn Fn() -> usize| {
        let t = Instant::now();
        std::hint::black_box(f());
        t.elapsed()
    };
    time(&|| primary.par_iter().filter(|(o, d)| closest(*o, *d)).count());
    let coh = time(&|| primary.par_iter().filter(|(o, d)| closest(*o, *d)).count());
    let inc = time(&|| secondary.par_iter().filter(|(o, d)| closest(*o, *d)).count());
    let anyt = time(&|| secondary.par_iter().filter(|(o, d)| any(*o, *d)).count());
    println!(
        "| BVH2 (obvhs traversal) | medium | {:.0} | | {:.2} | {:.2} | {:.2} | |",
        build.as_secs_f64() * 1e3,
        mrays(primary.len(), coh),
        mrays(secondary.len(), inc),
        mrays(secondary.len(), anyt)
    );
    cpu_rows.push(format!(
        "| BVH2 (obvhs traversal) | medium | {} | {} | {} |",
        fmt_rate(cpu_rates(coherent_subset, 1, &|_, o, d| closest(o, d))[0]),
        fmt_rate(cpu_rates(&secondary, 1, &|_, o, d| closest(o, d))[0]),
        fmt_rate(cpu_rates(&secondary, 1, &|_, o, d| any(o, d))[0]),
    ));
    println!("\nOne thread, rays per CPU second (Mray/s; /proc/thread-self/schedstat):\n");
    println!("| structure | build preset | coherent closest | incoherent closest | incoherent any-hit |");
    println!("|---|---|---|---|---|");
    for row in cpu_rows {
        println!("{row}");
    }
    #[cfg(feature = "tinybvh")]
    tinybvh::compare(&mesh, &reference_bvh, coherent_subset, &secondary, &cpu_rates);
    #[cfg(feature = "embree")]
    embree::compare(&mesh, &reference_bvh, coherent_subset, &secondary, &cpu_rates);
    Ok(())
}

//! tinybvh (Jacco Bikker's single-header C++ BVH library, through the `tinybvh-rs` crate, a
//! dev-dependency) on bench_rays' rays, side by side with our `Bvh` ([`super::side_by_side`]).
//!
//! Layouts: tinybvh's binary "Wald" BVH (its reference binned-SAH `Build`, and `BuildHQ` with
//! spatial splits) with its own traversal, and BVH8_CPU (8-wide AVX2 nodes, leaves of 4 triangles,
//! converted from the binary BVH through MBVH8). tinybvh-rs 0.1.0-beta.3 exposes closest-hit
//! traversal only (no `IsOccluded`), and BVH8_CPU's only when this crate is compiled with the
//! `avx2` target feature (`RUSTFLAGS="-C target-feature=+avx2,+fma"`); its CWBVH layout has no
//! CPU traversal in the wrapper (a GPU layout). The wrapper's `Ray` is smaller and less aligned than the
//! C++ one it vendors, so rays are padded here ([`CxxRay`]).

use glam::Vec3;
use reconstruct::geometry::bvh::Bvh;
use reconstruct::geometry::Mesh;
#[cfg(target_feature = "avx2")]
use tinybvh_rs::mbvh;
use tinybvh_rs::{bvh, Intersection, Intersector, Ray, INFINITE};

use super::side_by_side::{build_ms, report, Alternative, CpuRates};

/// tinybvh's `BVH_FAR`: its "no hit yet" distance.
const FAR: f32 = INFINITE;

/// tinybvh 1.6.8's `Ray` as g++ lays it out from the vendored header: 128 bytes, 64-byte aligned;
/// origin, mask, direction, instance index, reciprocal direction, hit instance, t, u, v, prim (the
/// first 64 bytes, which tinybvh-rs' `Ray` matches field for field), then 64 bytes of user data.
/// tinybvh-rs 0.1.0-beta.3's `Ray` is only those 64 bytes and 16-byte aligned, so its `Ray::new`
/// (C++ returning a 128-byte value into it) crashed here; the rays are built here instead, in this
/// padded and aligned wrapper, and handed to C++ by pointer.
#[repr(C, align(64))]
struct CxxRay {
    ray: Ray,
    _user_data: [u8; 64],
}

/// tinybvh's reciprocal for rD (`tinybvh_safercp`): components within ±1e-12 map to ±`FAR`.
fn safe_rcp(x: f32) -> f32 {
    if x.abs() > 1e-12 {
        1.0 / x
    } else if x >= 0.0 {
        FAR
    } else {
        -FAR
    }
}

/// Closest hit (triangle, t) through a tinybvh layout, or None. The direction is not normalised
/// (tinybvh's `Ray` constructor would), so t is in units of |d| like ours.
fn closest(layout: &dyn Intersector, o: Vec3, d: Vec3) -> Option<(u32, f32)> {
    let mut ray = CxxRay {
        ray: Ray {
            origin: o.into(),
            padding_0: 0xFFFF, // mask: RAY_MASK_INTERSECT_ALL
            dir: d.into(),
            padding_1: 0, // instance index
            r_d: [safe_rcp(d.x), safe_rcp(d.y), safe_rcp(d.z)],
            padding_2: 0, // hit instance
            hit: Intersection { t: FAR, u: 0.0, v: 0.0, prim: 0 },
        },
        _user_data: [0; 64],
    };
    // `intersect` hands C++ a pointer to `ray.ray`, the start of the 128 aligned bytes it expects.
    layout.intersect(&mut ray.ray);
    (ray.ray.hit.t < FAR).then_some((ray.ray.hit.prim, ray.ray.hit.t))
}

fn alternative<'a>(name: &str, layout: &'a dyn Intersector) -> Alternative<'a> {
    Alternative { name: name.into(), closest: Box::new(move |o, d| closest(layout, o, d)), any_hit: None }
}

/// Build tinybvh's layouts over `mesh` and print their build times, hit agreement with `ours` and
/// rates beside ours.
pub fn compare(mesh: &Mesh, ours: &Bvh, coherent: &[(Vec3, Vec3)], incoherent: &[(Vec3, Vec3)], cpu_rates: CpuRates) {
    // All triangles, in mesh order, so tinybvh's primitive index is the mesh's triangle index.
    let positions: Vec<[f32; 4]> =
        (0..mesh.triangles.len()).flat_map(|t| mesh.triangle_positions(t).map(|p| [p.x, p.y, p.z, 0.0])).collect();
    let build = |hq: bool| {
        let slice = positions.as_slice().into();
        if hq {
            bvh::BVH::new_hq(slice)
        } else {
            bvh::BVH::new(slice)
        }
    };
    // BVH8_CPU wants leaves of at most 4 triangles, converted through the 8-wide MBVH.
    #[cfg(target_feature = "avx2")]
    let build8 = |hq: bool| -> Result<tinybvh_rs::bvh8_cpu::BVH, tinybvh_rs::Error> {
        let mut b = build(hq)?;
        b.split_leaves(4);
        let m = mbvh::BVH::new(&b);
        tinybvh_rs::bvh8_cpu::BVH::new(&m)
    };

    println!("\n## tinybvh 1.6.8 (tinybvh-rs 0.1.0-beta.3) against `Bvh` on the same rays\n");
    println!("| structure | build ms (wall, all threads, fastest of 3) |");
    println!("|---|---|");
    println!("| CWBVH (Bvh), medium preset | {:.1} |", build_ms(&|| drop(std::hint::black_box(Bvh::build(mesh)))));
    println!("| tinybvh BVH (Build, binned SAH) | {:.1} |", build_ms(&|| drop(std::hint::black_box(build(false)))));
    println!("| tinybvh BVH (BuildHQ, spatial splits) | {:.1} |", build_ms(&|| drop(std::hint::black_box(build(true)))));
    #[cfg(target_feature = "avx2")]
    {
        println!("| tinybvh BVH8_CPU (Build → MBVH8 → BVH8_CPU) | {:.1} |", build_ms(&|| drop(std::hint::black_box(build8(false)))));
        println!("| tinybvh BVH8_CPU (BuildHQ → MBVH8 → BVH8_CPU) | {:.1} |", build_ms(&|| drop(std::hint::black_box(build8(true)))));
    }

    let (plain, hq) = match (build(false), build(true)) {
        (Ok(p), Ok(h)) => (p, h),
        (Err(e), _) | (_, Err(e)) => {
            println!("tinybvh build failed: {e}");
            return;
        }
    };
    #[cfg(target_feature = "avx2")]
    let wide = match (build8(false), build8(true)) {
        (Ok(p), Ok(h)) => (p, h),
        (Err(e), _) | (_, Err(e)) => {
            println!("tinybvh BVH8_CPU conversion failed: {e}");
            return;
        }
    };
    #[cfg_attr(not(target_feature = "avx2"), allow(unused_mut))]
    let mut alternatives = vec![alternative("tinybvh BVH (Build)", &plain), alternative("tinybvh BVH (BuildHQ)", &hq)];
    #[cfg(target_feature = "avx2")]
    alternatives.extend([alternative("tinybvh BVH8_CPU (Build)", &wide.0), alternative("tinybvh BVH8_CPU (BuildHQ)", &wide.1)]);
    #[cfg(not(target_feature = "avx2"))]
    println!("\n(BVH8_CPU not measured: tinybvh-rs offers its traversal only when built with RUSTFLAGS=\"-C target-feature=+avx2,+fma\".)");
    report(ours, &alternatives, coherent, incoherent, cpu_rates);
}

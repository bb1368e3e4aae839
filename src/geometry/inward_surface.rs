//! How much of a closed mesh's surface faces into the mesh: the share of its area whose outer side
//! lies inside the surface, by ray parity. A healthy closed surface scores about 0 (a ray that
//! grazes a shared edge can miscount; three rays per point vote). An optimised mesh that has folded
//! through itself (a sheet pushed inside the object, a pocket turned inside out) scores the fold's
//! share of the area. Neither the geometry pass's flip guard nor the manifold check can see such a
//! fold: every triangle and every edge is fine locally, the surface only crosses itself. The
//! geometry pass records the share at the end of each stage (`fit::geometry_pass::StageRecord`).

use anyhow::Result;
use glam::Vec3;

use super::bvh::Bvh;
use super::surface_samples::sample_surface;
use super::Mesh;

/// Surface points the share is estimated from: its standard error is at most 0.5/√2000 ≈ 0.011,
/// and a share near 0 is resolved to a few points in 2000.
pub const INWARD_SAMPLES: usize = 2000;

/// Above this share of its surface facing inward a mesh counts as folded: the geometry pass then
/// re-extracts its surface (`fit::geometry_pass`, `enclosed_surface.rs`) and a run warns when its
/// final mesh is. A healthy hotdog pass measured 0.05 % (ray-parity miscounts), the estimate's
/// standard error near 0 is below 0.3 % at `INWARD_SAMPLES`, and a folded hotdog pass measured
/// 17.6 % (docs/geometry.md, *Folds through the surface*).
pub const FOLDED_SHARE: f64 = 0.01;

/// Above this share more of the surface faces into the mesh than out of it: the mesh has turned
/// inside out, which an optimisation does only when it has diverged (the folds a healthy pass makes
/// measured 0–18 %). No re-extraction repairs it (what such a mesh encloses is not the object: in
/// the one case seen, 94 %, the re-extracted surface had about 40× the hull's triangles and remeshing it
/// ran for minutes while growing), so the geometry pass stops with an error instead.
pub const INSIDE_OUT_SHARE: f64 = 0.5;

/// Crossings followed along one ray before it counts as lost in a tangle (and votes "inside").
const MAX_CROSSINGS: usize = 256;

/// The share of `mesh`'s area (estimated from `samples` area-weighted points, seeded) whose outer
/// side lies inside the surface. `bvh` must be built on `mesh`. Fails for a mesh without area.
pub fn inward_share(mesh: &Mesh, bvh: &Bvh, samples: usize, seed: u64) -> Result<f64> {
    let points = sample_surface(mesh, samples, seed)?;
    let (lo, hi) = mesh.bounds().ok_or_else(|| anyhow::anyhow!("inward share: the mesh has no vertices"))?;
    // Rays start this far off the surface and step this far past each crossing: far above the
    // rounding of positions (~1e-7 of the size), far below any triangle of a mesh meant to be traced.
    let eps = 1e-5 * (hi - lo).length().max(f32::MIN_POSITIVE);
    let inward = points
        .iter()
        .filter(|s| {
            let n = mesh.face_normal_scaled(s.triangle as usize).normalize_or_zero();
            if n == Vec3::ZERO {
                return false;
            }
            let (u, v) = n.any_orthonormal_pair();
            // The normal and two directions 30° off it: a ray along a shared edge or a vertex is
            // outvoted by the other two.
            let dirs = [n, (n * 0.866 + u * 0.5).normalize(), (n * 0.866 - u * 0.25 + v * 0.433).normalize()];
            dirs.iter().filter(|&&d| odd_crossings(bvh, s.position, d, eps)).count() >= 2
        })
        .count();
    Ok(inward as f64 / points.len().max(1) as f64)
}

/// Whether the ray from `origin` along `dir` crosses the surface an odd number of times.
fn odd_crossings(bvh: &Bvh, origin: Vec3, dir: Vec3, eps: f32) -> bool {
    let crossings = bvh.hits_along(origin, dir, eps, eps).take(MAX_CROSSINGS).count();
    crossings == MAX_CROSSINGS || crossings % 2 == 1
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::icosphere::icosphere;

    fn share(mesh: &Mesh) -> f64 {
        inward_share(mesh, &Bvh::build(mesh), 4000, 7).expect("the test meshes have area")
    }

    #[test]
    fn a_sphere_faces_outward_and_a_sheet_inside_it_is_counted() -> Result<()> {
        let outer = icosphere(Vec3::ZERO, 1.0, 4);
        assert!(share(&outer) < 0.005, "sphere: {}", share(&outer));

        // A second sphere inside, facing out: its whole area faces into the outer one.
        // Expected share r²/(r² + 1) = 0.2 for r = 0.5.
        let mut folded = outer.clone();
        folded.append(icosphere(Vec3::new(0.1, 0.0, -0.1), 0.5, 4));
        let s = share(&folded);
        assert!((s - 0.2).abs() < 0.03, "sphere with an inner sheet: {s}");

        // The same inner sphere turned inside out is a cavity, a healthy closed surface.
        let mut cavity = icosphere(Vec3::new(0.1, 0.0, -0.1), 0.5, 4);
        for t in cavity.triangles.iter_mut() {
            t.swap(1, 2);
        }
        let mut hollow = outer.clone();
        hollow.append(cavity);
        assert!(share(&hollow) < 0.005, "hollow sphere: {}", share(&hollow));

        // A sphere turned inside out faces inward everywhere.
        let mut inverted = outer;
        for t in inverted.triangles.iter_mut() {
            t.swap(1, 2);
        }
        assert!(share(&inverted) > 0.995, "inverted sphere: {}", share(&inverted));
        Ok(())
    }
}

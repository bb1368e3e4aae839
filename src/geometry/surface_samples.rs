//! Area-weighted random points on a mesh's surface: every unit of area is equally likely, whatever
//! the tessellation. Geometry metrics average over these points, so a finely meshed region does not
//! weigh more than a coarsely meshed one of the same area. Seeded, so the same mesh and seed give the
//! same points in any thread count.

use anyhow::{bail, Result};
use glam::{DVec3, Vec3};
use rand::distr::weighted::WeightedIndex;
use rand::distr::Distribution;
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg32;

use super::Mesh;

/// A point on the surface and the triangle it lies on.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfaceSample {
    pub position: Vec3,
    /// Index into the mesh's triangle list.
    pub triangle: u32,
}

/// Twice the area of each triangle (0 for degenerate or non-finite ones), in f64.
fn doubled_areas(mesh: &Mesh) -> Vec<f64> {
    (0..mesh.triangles.len())
        .map(|t| {
            let [a, b, c] = mesh.triangle_positions(t).map(|p| p.as_dvec3());
            let area2 = (b - a).cross(c - a).length();
            if area2.is_finite() {
                area2
            } else {
                0.0
            }
        })
        .collect()
}

/// `count` points drawn independently, each on a triangle chosen with probability proportional to
/// its area, then uniformly within it (the square-root map of two uniforms to barycentrics).
/// Degenerate and non-finite triangles are never chosen. Fails when the mesh has no area.
pub fn sample_surface(mesh: &Mesh, count: usize, seed: u64) -> Result<Vec<SurfaceSample>> {
    let areas = doubled_areas(mesh);
    if !areas.iter().any(|&a| a > 0.0) {
        bail!("cannot sample the surface of a mesh with no area ({} triangles, all degenerate or none)", mesh.triangles.len());
    }
    let pick = WeightedIndex::new(&areas)?;
    let mut rng = Pcg32::seed_from_u64(seed);
    Ok((0..count)
        .map(|_| {
            let t = pick.sample(&mut rng);
            let (r1, r2): (f64, f64) = (rng.random(), rng.random());
            let s = r1.sqrt();
            let [a, b, c]: [DVec3; 3] = mesh.triangle_positions(t).map(|p| p.as_dvec3());
            let position = (a * (1.0 - s) + b * (s * (1.0 - r2)) + c * (s * r2)).as_vec3();
            SurfaceSample { position, triangle: t as u32 }
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two triangles in the z = 0 plane with areas 1 and 3 (and a degenerate third).
    fn two_triangles() -> Mesh {
        let p = |x: f32, y: f32| Vec3::new(x, y, 0.0);
        Mesh {
            positions: vec![p(0.0, 0.0), p(2.0, 0.0), p(0.0, 1.0), p(10.0, 0.0), p(13.0, 0.0), p(10.0, 2.0)],
            triangles: vec![[0, 1, 2], [3, 4, 5], [0, 1, 1]],
            ..Default::default()
        }
    }

    #[test]
    fn samples_follow_area_and_lie_on_their_triangle() {
        let mesh = two_triangles();
        let n = 40_000;
        let samples = sample_surface(&mesh, n, 7).unwrap();
        assert_eq!(samples.len(), n);
        let on_second = samples.iter().filter(|s| s.triangle == 1).count() as f64 / n as f64;
        // Expected share 3/4; binomial standard deviation sqrt(p(1 − p)/n) ≈ 0.0022, allow 5σ.
        assert!((on_second - 0.75).abs() < 0.011, "share on the larger triangle {on_second}");
        assert!(samples.iter().all(|s| s.triangle != 2), "a degenerate triangle was sampled");
        // Each point is inside its triangle: the barycentric coordinates are in [0, 1].
        for s in &samples {
            let [a, b, c] = mesh.triangle_positions(s.triangle as usize);
            let (e1, e2, d) = ((b - a).truncate(), (c - a).truncate(), (s.position - a).truncate());
            let det = e1.perp_dot(e2);
            let (u, v) = (d.perp_dot(e2) / det, e1.perp_dot(d) / det);
            assert!(s.position.z == 0.0 && u >= -1e-5 && v >= -1e-5 && u + v <= 1.0 + 1e-5, "{s:?} ({u}, {v})");
        }
        // Uniform within the triangle: the mean is the centroid (2/3, 1/3) of the first one.
        let first: Vec<Vec3> = samples.iter().filter(|s| s.triangle == 0).map(|s| s.position).collect();
        let mean = first.iter().copied().sum::<Vec3>() / first.len() as f32;
        // About 10 000 points: the standard deviation of the mean is ≈ 0.005 (x) and 0.0024 (y); allow 5σ.
        assert!((mean - Vec3::new(2.0 / 3.0, 1.0 / 3.0, 0.0)).length() < 0.025, "mean {mean}");
    }

    #[test]
    fn same_seed_same_points_and_no_area_is_an_error() {
        let mesh = two_triangles();
        assert_eq!(sample_surface(&mesh, 100, 3).unwrap(), sample_surface(&mesh, 100, 3).unwrap());
        assert_ne!(sample_surface(&mesh, 100, 3).unwrap(), sample_surface(&mesh, 100, 4).unwrap());
        let mut flat = two_triangles();
        flat.triangles = vec![[0, 1, 1]];
        let err = sample_surface(&flat, 10, 0).unwrap_err().to_string();
        assert!(err.contains("no area"), "{err}");
        assert!(sample_surface(&Mesh::default(), 10, 0).is_err());
    }
}

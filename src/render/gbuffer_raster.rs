//! The G-buffer by projection: the same per-pixel closest hits as [`GBuffer::trace`], found without
//! a BVH, for a mesh that moves every step (the geometry pass).
//!
//! A BVH over a moving mesh must be rebuilt before every step, and its traversal spends most of a
//! primary ray's time finding the few triangles the ray could meet. For primary rays the camera
//! already knows them: a triangle can only be hit through the pixel centres inside its projection.
//! So each triangle is projected, and the pixel centres inside its screen bounds (widened by
//! [`BOUNDS_SLACK`]) are tested with the ray tracer's own ray/triangle test
//! (`geometry::bvh::intersect_triangle`, Möller–Trumbore on the pixel's `Camera::ray_dir`); the
//! nearest hit per pixel wins. Because the test and the ray are the tracer's, the result is the
//! tracer's hit for hit, up to which of two triangles that meet a ray at exactly the same t is kept
//! (here the later in triangle order, there the later in traversal order). A triangle with a vertex on or behind
//! the camera's plane has no finite projection; it is tested at every pixel of the image, which stays
//! exact and only costs time when the camera is inside the mesh.
//!
//! Work is split into horizontal bands of rows, one task each, and a band tests only the triangles
//! whose bounds reach it, so no two tasks write the same pixel.

use glam::Vec3;
use rayon::prelude::*;

use crate::geometry::bvh::intersect_triangle;
use crate::geometry::Mesh;
use crate::render::gbuffer::{surfel_at, GBuffer};
use crate::render::ray_count::{self, RayCount};
use crate::scene::camera::Camera;

/// Widening of a triangle's projected bounds, in pixels. The projection and the pixel's ray are
/// computed in f32 along different paths, so a pixel centre exactly on a projected edge could fall
/// a rounding error outside the bounds; a thousandth of a pixel is far above that error (about
/// 1e-5 px at 512² and unit-scale scenes) and far below the pixel pitch, so it adds no tests in practice.
const BOUNDS_SLACK: f32 = 1e-3;

/// Rows per band: small enough that two threads share the bands evenly, large enough that a
/// triangle rarely spans two.
const BAND_ROWS: usize = 16;

/// A triangle's pixel-centre bounds (inclusive), or all pixels for one that does not project.
#[derive(Clone, Copy)]
struct PixelBounds {
    triangle: u32,
    x0: usize,
    x1: usize,
    y0: usize,
    y1: usize,
}

/// The pixel-centre bounds of the triangle whose vertices sit at pixel coordinates `xy` and
/// planar depths `depth`, or `None` when no pixel centre can be inside it.
fn bounds(triangle: u32, xy: [(f32, f32); 3], depth: [f32; 3], width: usize, height: usize) -> Option<PixelBounds> {
    if !depth.iter().all(|&d| d > 0.0) {
        // On or behind the camera's plane (or not finite): no projection to bound it by.
        if depth.iter().any(|d| d.is_nan()) {
            return None;
        }
        return Some(PixelBounds { triangle, x0: 0, x1: width - 1, y0: 0, y1: height - 1 });
    }
    let (lo_x, hi_x) = (xy.iter().map(|p| p.0).fold(f32::INFINITY, f32::min), xy.iter().map(|p| p.0).fold(f32::NEG_INFINITY, f32::max));
    let (lo_y, hi_y) = (xy.iter().map(|p| p.1).fold(f32::INFINITY, f32::min), xy.iter().map(|p| p.1).fold(f32::NEG_INFINITY, f32::max));
    if !(lo_x.is_finite() && hi_x.is_finite() && lo_y.is_finite() && hi_y.is_finite()) {
        return None;
    }
    // Pixel i's centre is at i + 0.5: the centres inside [lo, hi] are ceil(lo − 0.5) ..= floor(hi − 0.5).
    let first = |lo: f32| (lo - 0.5 - BOUNDS_SLACK).ceil().max(0.0);
    let last = |hi: f32, n: usize| (hi - 0.5 + BOUNDS_SLACK).floor().min(n as f32 - 1.0);
    let (x0, x1, y0, y1) = (first(lo_x), last(hi_x, width), first(lo_y), last(hi_y, height));
    if x0 > x1 || y0 > y1 {
        return None;
    }
    Some(PixelBounds { triangle, x0: x0 as usize, x1: x1 as usize, y0: y0 as usize, y1: y1 as usize })
}

impl GBuffer {
    /// The G-buffer [`GBuffer::trace`] would give for `mesh` seen by `camera`, found by projecting
    /// the triangles instead of traversing a BVH (module comment). Counts one primary ray per pixel.
    pub fn rasterize(mesh: &Mesh, camera: &Camera) -> GBuffer {
        let (width, height) = (camera.width, camera.height);
        let origin = camera.origin();
        let forward = camera.forward();
        let mut surfels = vec![None; width * height];
        if width > 0 && height > 0 {
            let projector = camera.projector();
            let projected: Vec<((f32, f32), f32)> = mesh
                .positions
                .par_iter()
                .map(|&p| {
                    let (xy, depth) = projector.project(p);
                    ((xy.x, xy.y), depth)
                })
                .collect();
            let boxes: Vec<PixelBounds> = mesh
                .triangles
                .par_iter()
                .enumerate()
                .filter_map(|(t, tri)| {
                    let c = tri.map(|i| projected[i as usize]);
                    bounds(t as u32, c.map(|v| v.0), c.map(|v| v.1), width, height)
                })
                .collect();
            // Each band's triangles, in triangle order: the result does not depend on the threads.
            let mut in_band: Vec<Vec<u32>> = vec![Vec::new(); height.div_ceil(BAND_ROWS)];
            for (i, b) in boxes.iter().enumerate() {
                for list in &mut in_band[b.y0 / BAND_ROWS..=b.y1 / BAND_ROWS] {
                    list.push(i as u32);
                }
            }
            surfels.par_chunks_mut(BAND_ROWS * width).zip(in_band.par_iter()).enumerate().for_each(|(band, (rows, list))| {
                let (top, bottom) = (band * BAND_ROWS, (band * BAND_ROWS + rows.len() / width).saturating_sub(1));
                let mut best: Vec<Option<(u32, f32, glam::Vec2)>> = vec![None; rows.len()];
                let mut dirs: Vec<Option<Vec3>> = vec![None; rows.len()];
                for b in list.iter().map(|&i| &boxes[i as usize]) {
                    let p = mesh.triangles[b.triangle as usize].map(|i| mesh.positions[i as usize]);
                    for y in b.y0.max(top)..=b.y1.min(bottom) {
                        for x in b.x0..=b.x1 {
                            let k = (y - top) * width + x;
                            let dir = *dirs[k].get_or_insert_with(|| camera.ray_dir(x as f32 + 0.5, y as f32 + 0.5));
                            let tmax = best[k].map_or(f32::INFINITY, |h| h.1);
                            if let Some((t, bary)) = intersect_triangle(p, origin, dir, 0.0, tmax) {
                                best[k] = Some((b.triangle, t, bary));
                            }
                        }
                    }
                }
                for (k, out) in rows.iter_mut().enumerate() {
                    if let (Some((tri, _, bary)), Some(dir)) = (best[k], dirs[k]) {
                        *out = Some(surfel_at(mesh, tri, bary, dir, origin, forward));
                    }
                }
            });
        }
        ray_count::record(RayCount { primary: (width * height) as u64, ..RayCount::ZERO });
        GBuffer { width, height, origin, surfels }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::bvh::Bvh;
    use crate::geometry::icosphere::icosphere;
    use crate::rng::Sampler;

    /// Every pixel: the same triangle as the tracer, or a different one at the same distance (a
    /// shared edge or vertex, where either is right); the same depth within 1e-5 relative.
    fn assert_same_hits(mesh: &Mesh, camera: &Camera) -> usize {
        let traced = GBuffer::trace(mesh, &Bvh::build(mesh), camera);
        let raster = GBuffer::rasterize(mesh, camera);
        let mut covered = 0;
        for (i, (a, b)) in traced.surfels.iter().zip(&raster.surfels).enumerate() {
            match (a, b) {
                (None, None) => {}
                (Some(a), Some(b)) => {
                    covered += 1;
                    let tol = 1e-5 * a.depth.abs().max(1e-3);
                    assert!((a.depth - b.depth).abs() <= tol, "pixel {i}: depth {} traced, {} rasterised", a.depth, b.depth);
                    if a.triangle == b.triangle {
                        assert!((a.bary - b.bary).abs().max_element() < 1e-5, "pixel {i}: barycentrics {} / {}", a.bary, b.bary);
                    }
                }
                _ => panic!("pixel {i}: traced {:?}, rasterised {:?}", a.map(|s| s.triangle), b.map(|s| s.triangle)),
            }
        }
        covered
    }

    #[test]
    fn rasterised_hits_are_the_traced_ones() {
        // Spheres from outside at several sizes (sub-pixel to many-pixel triangles), random poses.
        let mut rng = Sampler::new(7, 1);
        for (level, radius) in [(1, 0.9f32), (3, 0.7), (5, 1.2)] {
            let mesh = icosphere(Vec3::new(0.1, -0.2, 0.05), radius, level);
            for _ in 0..3 {
                let dir = Vec3::new(rng.next_f32() - 0.5, rng.next_f32() - 0.5, rng.next_f32() - 0.5).normalize_or(Vec3::Y);
                let camera = Camera::look_at(dir * 3.5, Vec3::ZERO, Vec3::Z, 0.7, 61, 47);
                assert!(assert_same_hits(&mesh, &camera) > 200);
            }
        }
    }

    #[test]
    fn hard_cases_stay_exact() {
        // A camera inside the sphere (every triangle straddles or sits behind the camera's plane
        // for some views), a grazing view of a flat square, a mesh with a degenerate and a
        // non-finite triangle, and a view along a shared edge through pixel centres.
        let sphere = icosphere(Vec3::ZERO, 1.0, 3);
        let inside = Camera::look_at(Vec3::new(0.2, 0.1, 0.0), Vec3::new(1.0, 0.3, 0.2), Vec3::Z, 1.2, 40, 30);
        assert_eq!(assert_same_hits(&sphere, &inside), 40 * 30, "inside a closed sphere every pixel sees it");

        let corners = vec![Vec3::new(-1.0, -1.0, 0.0), Vec3::new(1.0, -1.0, 0.0), Vec3::new(1.0, 1.0, 0.0), Vec3::new(-1.0, 1.0, 0.0)];
        let mut square = Mesh { normals: vec![Vec3::Z; 4], uvs: vec![glam::Vec2::ZERO; 4], positions: corners, triangles: vec![[0, 1, 2], [0, 2, 3]], ..Mesh::default() };
        let grazing = Camera::look_at(Vec3::new(0.0, -3.0, 0.05), Vec3::ZERO, Vec3::Z, 0.8, 64, 64);
        assert_same_hits(&square, &grazing);
        // The square's diagonal through pixel centres: a camera straight above, odd image size.
        let above = Camera::look_at(Vec3::new(0.0, 0.0, 3.0), Vec3::ZERO, Vec3::Y, 0.9, 33, 33);
        assert!(assert_same_hits(&square, &above) > 300);

        // A tilted triangle over part of the square (the depth test decides), one of zero area
        // and one with a non-finite vertex (neither may ever be hit).
        square.positions.extend([Vec3::new(0.5, 0.5, 0.5), Vec3::new(f32::NAN, 0.0, 0.0)]);
        square.normals.extend([Vec3::Z; 2]);
        square.uvs.extend([glam::Vec2::ZERO; 2]);
        square.triangles.extend([[0, 2, 4], [0, 0, 1], [1, 5, 2]]);
        assert!(assert_same_hits(&square, &above) > 300);
    }
}

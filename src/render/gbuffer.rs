//! The G-buffer: what primary rays see per pixel. With geometry fixed it is traced once per view.

use glam::{Vec2, Vec3};

/// One pixel's visible surface point.
#[derive(Clone, Copy, Debug)]
pub struct Surfel {
    pub position: Vec3,
    /// Interpolated shading normal, flipped to face the camera (two-sided shading).
    pub normal: Vec3,
    /// Geometric (face) normal, flipped to face the camera.
    pub geo_normal: Vec3,
    pub uv: Vec2,
    /// Index into the mesh's triangle list (not the BVH's primitive order).
    pub triangle: u32,
    /// Barycentrics (b1, b2) of the hit; b0 = 1 − b1 − b2.
    pub bary: Vec2,
    /// Planar depth along the camera's viewing axis.
    pub depth: f32,
}

/// Per-pixel surfels of one view, row-major, row 0 at the top; `None` where the ray missed.
#[derive(Clone, Debug)]
pub struct GBuffer {
    pub width: usize,
    pub height: usize,
    /// Camera position: the outgoing direction of pixel p is `(origin - position).normalize()`.
    pub origin: Vec3,
    pub surfels: Vec<Option<Surfel>>,
}

use rayon::prelude::*;

use crate::geometry::bvh::{Bvh, Hit};
use crate::geometry::Mesh;
use crate::image::Image;
use crate::material::{MaterialField, SurfaceParams};
use crate::render::ray_count::{self, RayCount};
use crate::scene::camera::Camera;

impl GBuffer {
    /// Trace one primary ray per pixel through the pixel centre (supersample by tracing
    /// `camera.resized(W·s, H·s)`), rows in parallel.
    ///
    /// Two-sided convention (as Cycles and the NeRFactor GT normals): when the ray sees a
    /// triangle's back face, both the geometric and the interpolated shading normal are negated.
    /// The shading normal is flipped with the face, not on its own, so it stays continuous across
    /// a smooth surface even where it tilts away from the viewer near silhouettes.
    pub fn trace(mesh: &Mesh, bvh: &Bvh, camera: &Camera) -> GBuffer {
        let (width, height) = (camera.width, camera.height);
        let origin = camera.origin();
        let forward = camera.forward();
        let mut surfels = vec![None; width * height];
        surfels.par_chunks_mut(width.max(1)).enumerate().for_each(|(y, row)| {
            for (x, out) in row.iter_mut().enumerate() {
                let dir = camera.ray_dir(x as f32 + 0.5, y as f32 + 0.5);
                *out = bvh.closest_hit(origin, dir, 0.0, f32::INFINITY).map(|hit| {
                    surfel_at(mesh, hit.triangle, hit.bary, dir, origin, forward)
                });
            }
        });
        ray_count::record(RayCount { primary: (width * height) as u64, ..RayCount::ZERO });
        GBuffer { width, height, origin, surfels }
    }

    /// The rays [`GBuffer::trace`] traced for this buffer: one primary ray per pixel.
    pub fn rays(&self) -> RayCount {
        RayCount { primary: (self.width * self.height) as u64, ..RayCount::ZERO }
    }

    /// Per pixel: did the primary ray hit geometry.
    pub fn mask(&self) -> Vec<bool> {
        self.surfels.iter().map(Option::is_some).collect()
    }

    /// One channel: 1 where the ray hit, 0 elsewhere (average a supersampled one for coverage).
    pub fn coverage_image(&self) -> Image {
        let data = self.surfels.iter().map(|s| if s.is_some() { 1.0 } else { 0.0 }).collect();
        Image { width: self.width, height: self.height, channels: 1, data }
    }

    /// One channel: planar depth along the view axis, 0 on the background (like NeRFactor-layout
    /// `depth.exr`).
    pub fn depth_image(&self) -> Image {
        let data = self.surfels.iter().map(|s| s.map_or(0.0, |s| s.depth)).collect();
        Image { width: self.width, height: self.height, channels: 1, data }
    }

    /// Three channels: world-space shading normal in [−1, 1] (not encoded), 0 on the background.
    pub fn normal_image(&self) -> Image {
        let mut img = Image::new(self.width, self.height, 3);
        for (i, s) in self.surfels.iter().enumerate() {
            if let Some(s) = s {
                img.set_rgb(i, s.normal);
            }
        }
        img
    }

    /// The BRDF inputs of every hit pixel, looked up in `materials` (a mesh's own part materials,
    /// or learned atlas textures).
    pub fn material_params(&self, materials: &dyn MaterialField) -> Vec<Option<SurfaceParams>> {
        self.surfels.par_iter().map(|s| s.map(|s| s.material(materials))).collect()
    }

    /// Replaces every surfel's shading normal by the one `materials` gives it (a normal map).
    pub fn apply_material_normals(&mut self, materials: &dyn MaterialField) {
        self.surfels.par_iter_mut().for_each(|s| {
            if let Some(x) = s.as_mut() {
                *x = x.with_material_normal(materials);
            }
        });
    }
}

impl Surfel {
    /// The surface point a ray from `origin` along `dir` hit (primary or secondary), with the
    /// G-buffer's two-sided rule; `depth` is the hit distance along the ray.
    pub fn from_hit(mesh: &Mesh, hit: &Hit, origin: Vec3, dir: Vec3) -> Surfel {
        surfel_at(mesh, hit.triangle, hit.bary, dir, origin, dir)
    }

    pub fn material(&self, materials: &dyn MaterialField) -> SurfaceParams {
        materials.at(self.triangle, self.uv)
    }

    /// Barycentrics (b0, b1, b2) of the hit.
    pub fn bary3(&self) -> Vec3 {
        Vec3::new(1.0 - self.bary.x - self.bary.y, self.bary.x, self.bary.y)
    }

    /// This surfel with the shading normal `materials` gives it (a normal map's, or its own).
    pub fn with_material_normal(mut self, materials: &dyn MaterialField) -> Surfel {
        self.normal = materials.shading_normal(self.triangle, self.bary3(), self.uv, self.normal);
        self
    }
}

/// The surfel at barycentrics `bary` of triangle `tri`, seen along `dir` from `origin`.
pub(crate) fn surfel_at(mesh: &Mesh, tri: u32, bary: glam::Vec2, dir: Vec3, origin: Vec3, forward: Vec3) -> Surfel {
    let [i0, i1, i2] = mesh.triangles[tri as usize].map(|i| i as usize);
    let w = Vec3::new(1.0 - bary.x - bary.y, bary.x, bary.y);
    let interp3 = |a: &[Vec3]| w.x * a[i0] + w.y * a[i1] + w.z * a[i2];
    let position = interp3(&mesh.positions);
    let (p0, p1, p2) = (mesh.positions[i0], mesh.positions[i1], mesh.positions[i2]);
    // The BVH never returns zero-area triangles, so the face normal is well defined.
    let mut geo_normal = (p1 - p0).cross(p2 - p0).normalize_or(Vec3::Z);
    // Normals that cancel out (opposite vertex normals) fall back to the face normal.
    let mut normal = interp3(&mesh.normals).normalize_or(geo_normal);
    if geo_normal.dot(dir) > 0.0 {
        geo_normal = -geo_normal;
        normal = -normal;
    }
    let uv = w.x * mesh.uvs[i0] + w.y * mesh.uvs[i1] + w.z * mesh.uvs[i2];
    let depth = (position - origin).dot(forward);
    Surfel { position, normal, geo_normal, uv, triangle: tri, bary, depth }
}

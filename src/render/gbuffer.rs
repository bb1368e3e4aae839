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

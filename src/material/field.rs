//! The material at any surface point, whatever stores it: a mesh's per-part materials at its own
//! UVs (ground truth) or textures on a UV atlas (learned). Primary rays (G-buffer pixels) and
//! secondary rays (interreflection) look materials up through the same trait.

use glam::{Vec2, Vec3};

use crate::geometry::Mesh;
use crate::material::texture_maps::MaterialTextures;
use crate::material::SurfaceParams;

pub trait MaterialField: Sync {
    /// The BRDF inputs on triangle `triangle` (index into the mesh's list) at surface UV `uv`.
    fn at(&self, triangle: u32, uv: Vec2) -> SurfaceParams;

    /// The shading normal at barycentrics `bary` (b0, b1, b2) of `triangle`, atlas UV `uv`, where
    /// the mesh's own (two-sided) shading normal is `normal`: `normal` unless the material
    /// perturbs it (a normal map).
    fn shading_normal(&self, _triangle: u32, _bary: Vec3, _uv: Vec2, normal: Vec3) -> Vec3 {
        normal
    }
}

/// A mesh's own part materials.
impl MaterialField for Mesh {
    fn at(&self, triangle: u32, uv: Vec2) -> SurfaceParams {
        self.triangle_material(triangle as usize).eval(uv)
    }
}

/// Atlas textures (the UV is the atlas UV; the triangle matters only for a normal map's frame).
impl MaterialField for MaterialTextures {
    fn at(&self, _triangle: u32, uv: Vec2) -> SurfaceParams {
        self.eval(uv)
    }

    fn shading_normal(&self, triangle: u32, bary: Vec3, uv: Vec2, normal: Vec3) -> Vec3 {
        match &self.normal {
            Some(map) => map.shading_normal(triangle, bary, uv, normal),
            None => normal,
        }
    }
}

//! The material at any surface point, whatever stores it: a mesh's per-part materials at its own
//! UVs (ground truth) or textures on a UV atlas (learned). Primary rays (G-buffer pixels) and
//! secondary rays (interreflection) look materials up through the same trait.

use glam::Vec2;

use crate::geometry::Mesh;
use crate::material::texture_maps::MaterialTextures;
use crate::material::SurfaceParams;

pub trait MaterialField: Sync {
    /// The BRDF inputs on triangle `triangle` (index into the mesh's list) at surface UV `uv`.
    fn at(&self, triangle: u32, uv: Vec2) -> SurfaceParams;
}

/// A mesh's own part materials.
impl MaterialField for Mesh {
    fn at(&self, triangle: u32, uv: Vec2) -> SurfaceParams {
        self.triangle_material(triangle as usize).eval(uv)
    }
}

/// Atlas textures (the UV is the atlas UV; the triangle does not matter).
impl MaterialField for MaterialTextures {
    fn at(&self, _triangle: u32, uv: Vec2) -> SurfaceParams {
        self.eval(uv)
    }
}

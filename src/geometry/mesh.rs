//! A triangle mesh with per-vertex normals and UVs, split into named parts that carry materials.

use glam::{Vec2, Vec3};

use crate::material::PartMaterial;

#[derive(Clone, Debug)]
pub struct Part {
    pub name: String,
    /// Index into `Mesh::materials`.
    pub material: usize,
    /// False when the source file had no texture coordinates for this part (its `uvs` are zero).
    pub has_uv: bool,
}

#[derive(Clone, Debug, Default)]
pub struct Mesh {
    pub positions: Vec<Vec3>,
    /// Per-vertex shading normals, unit length, same length as `positions`.
    pub normals: Vec<Vec3>,
    /// Per-vertex texture coordinates (OBJ convention, v = 0 at the bottom), same length as `positions`.
    pub uvs: Vec<Vec2>,
    pub triangles: Vec<[u32; 3]>,
    /// Part index of each triangle.
    pub triangle_part: Vec<u32>,
    pub parts: Vec<Part>,
    pub materials: Vec<PartMaterial>,
}

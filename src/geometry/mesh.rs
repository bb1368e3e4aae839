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

impl Mesh {
    /// Append another mesh's vertices, triangles, parts and materials (indices shifted).
    pub fn append(&mut self, other: Mesh) {
        let vertex_offset = self.positions.len() as u32;
        let part_offset = self.parts.len() as u32;
        let material_offset = self.materials.len();
        self.positions.extend(other.positions);
        self.normals.extend(other.normals);
        self.uvs.extend(other.uvs);
        self.triangles.extend(other.triangles.iter().map(|t| t.map(|i| i + vertex_offset)));
        self.triangle_part.extend(other.triangle_part.iter().map(|p| p + part_offset));
        self.parts.extend(other.parts.into_iter().map(|p| Part { material: p.material + material_offset, ..p }));
        self.materials.extend(other.materials);
    }

    /// A one-part mesh with this mesh's parts and materials on new geometry (every triangle in part
    /// 0, no UVs, normals from the triangles): what a remesh or a re-extraction of a one-part mesh gives.
    pub fn with_geometry(&self, positions: Vec<Vec3>, triangles: Vec<[u32; 3]>) -> Mesh {
        let n = positions.len();
        let mut mesh = Mesh {
            positions,
            normals: vec![Vec3::Z; n],
            uvs: vec![Vec2::ZERO; n],
            triangle_part: vec![0; triangles.len()],
            triangles,
            parts: self.parts.clone(),
            materials: self.materials.clone(),
        };
        mesh.recompute_normals();
        mesh
    }

    /// Axis-aligned bounds (min, max) of all vertex positions; `None` for an empty mesh.
    pub fn bounds(&self) -> Option<(Vec3, Vec3)> {
        let first = *self.positions.first()?;
        Some(self.positions.iter().fold((first, first), |(lo, hi), p| (lo.min(*p), hi.max(*p))))
    }

    /// The three corner positions of triangle `t`.
    pub fn triangle_positions(&self, t: usize) -> [Vec3; 3] {
        let [a, b, c] = self.triangles[t];
        [self.positions[a as usize], self.positions[b as usize], self.positions[c as usize]]
    }

    /// Unnormalised face normal (cross product of the edges; its length is twice the area).
    pub fn face_normal_scaled(&self, t: usize) -> Vec3 {
        let [p0, p1, p2] = self.triangle_positions(t);
        (p1 - p0).cross(p2 - p0)
    }

    /// Area-weighted vertex normals over the given triangles: each face adds its cross product
    /// (|cross| = 2·area), so large faces dominate and slivers barely count. Vertices that no
    /// non-degenerate face touches get +z so that normals stay unit length and finite.
    pub fn area_weighted_normals(positions: &[Vec3], triangles: &[[u32; 3]]) -> Vec<Vec3> {
        let mut acc = vec![Vec3::ZERO; positions.len()];
        for &[a, b, c] in triangles {
            let (p0, p1, p2) = (positions[a as usize], positions[b as usize], positions[c as usize]);
            let n = (p1 - p0).cross(p2 - p0);
            if !n.is_finite() {
                continue;
            }
            for i in [a, b, c] {
                acc[i as usize] += n;
            }
        }
        acc.into_iter().map(|n| n.try_normalize().unwrap_or(Vec3::Z)).collect()
    }

    /// Recompute all vertex normals from the faces (area-weighted).
    pub fn recompute_normals(&mut self) {
        self.normals = Mesh::area_weighted_normals(&self.positions, &self.triangles);
    }

    /// Number of triangles of each part.
    pub fn part_triangle_counts(&self) -> Vec<usize> {
        let mut counts = vec![0; self.parts.len()];
        for &p in &self.triangle_part {
            counts[p as usize] += 1;
        }
        counts
    }

    /// The material of triangle `t` (through its part).
    pub fn triangle_material(&self, t: usize) -> &PartMaterial {
        &self.materials[self.parts[self.triangle_part[t] as usize].material]
    }

    /// Check the invariants other modules rely on (equal attribute lengths, indices in range,
    /// part and material indices valid). Returns a description of the first violation.
    pub fn validate(&self) -> Result<(), String> {
        let n = self.positions.len();
        if self.normals.len() != n || self.uvs.len() != n {
            return Err(format!(
                "attribute lengths differ: {} positions, {} normals, {} uvs",
                n,
                self.normals.len(),
                self.uvs.len()
            ));
        }
        if self.triangle_part.len() != self.triangles.len() {
            return Err(format!("{} triangles but {} triangle parts", self.triangles.len(), self.triangle_part.len()));
        }
        if let Some((t, tri)) = self.triangles.iter().enumerate().find(|(_, tri)| tri.iter().any(|&i| i as usize >= n)) {
            return Err(format!("triangle {t} {tri:?} indexes past {n} vertices"));
        }
        if let Some(p) = self.triangle_part.iter().find(|&&p| p as usize >= self.parts.len()) {
            return Err(format!("part index {p} out of range ({} parts)", self.parts.len()));
        }
        if let Some(part) = self.parts.iter().find(|p| p.material >= self.materials.len()) {
            return Err(format!("part {} uses material {} of {}", part.name, part.material, self.materials.len()));
        }
        Ok(())
    }
}

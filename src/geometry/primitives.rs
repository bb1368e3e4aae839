//! Procedural shapes (ellipsoids, capped cylinders) assembled into a multi-part Mesh: used by the
//! embedded default scene and by tests that need geometry without files.

use glam::{Quat, Vec2, Vec3};

use crate::geometry::{Mesh, Part};
use crate::material::PartMaterial;

#[derive(Default)]
pub struct MeshBuilder {
    mesh: Mesh,
}

impl MeshBuilder {
    pub fn new() -> Self {
        Self::default()
    }

    /// A new part with its own material; returns its index for the `add_*` calls.
    pub fn part(&mut self, material: PartMaterial) -> u32 {
        let name = material.name.clone();
        self.mesh.materials.push(material);
        self.mesh.parts.push(Part { name, material: self.mesh.materials.len() - 1, has_uv: true });
        (self.mesh.parts.len() - 1) as u32
    }

    fn vertex(&mut self, p: Vec3, n: Vec3, uv: Vec2) -> u32 {
        self.mesh.positions.push(p);
        self.mesh.normals.push(n.normalize());
        self.mesh.uvs.push(uv);
        (self.mesh.positions.len() - 1) as u32
    }

    fn triangle(&mut self, part: u32, a: u32, b: u32, c: u32) {
        self.mesh.triangles.push([a, b, c]);
        self.mesh.triangle_part.push(part);
    }

    /// An ellipsoid with semi-axes `radii` (before `rotation`), UVs u = azimuth, v = polar angle.
    pub fn ellipsoid(&mut self, part: u32, center: Vec3, radii: Vec3, rotation: Quat, segments: u32, rings: u32) {
        let base = self.mesh.positions.len() as u32;
        for r in 0..=rings {
            let theta = std::f32::consts::PI * r as f32 / rings as f32;
            for s in 0..=segments {
                let phi = 2.0 * std::f32::consts::PI * s as f32 / segments as f32;
                let unit = Vec3::new(theta.sin() * phi.cos(), theta.sin() * phi.sin(), theta.cos());
                let p = center + rotation * (unit * radii);
                // The normal of a scaled sphere is the unit normal scaled by the inverse radii.
                let n = rotation * (unit / radii);
                let uv = Vec2::new(s as f32 / segments as f32, 1.0 - r as f32 / rings as f32);
                self.vertex(p, n, uv);
            }
        }
        let row = segments + 1;
        for r in 0..rings {
            for s in 0..segments {
                let (a, b) = (base + r * row + s, base + r * row + s + 1);
                let (c, d) = (a + row, b + row);
                if r != 0 {
                    self.triangle(part, a, c, b);
                }
                if r != rings - 1 {
                    self.triangle(part, b, c, d);
                }
            }
        }
    }

    /// A closed cylinder along z from `z0` to `z1`, flat caps with their own vertices (sharp rims).
    pub fn cylinder(&mut self, part: u32, center_xy: Vec2, radius: f32, z0: f32, z1: f32, segments: u32) {
        let ring = |k: u32| {
            let phi = 2.0 * std::f32::consts::PI * k as f32 / segments as f32;
            Vec2::new(phi.cos(), phi.sin())
        };
        // Side.
        let base = self.mesh.positions.len() as u32;
        for k in 0..=segments {
            let d = ring(k);
            let u = k as f32 / segments as f32;
            for (z, v) in [(z0, 0.0), (z1, 0.25)] {
                let p = (center_xy + radius * d).extend(z);
                self.vertex(p, d.extend(0.0), Vec2::new(u, v));
            }
        }
        for k in 0..segments {
            let (a, b, c, d) = (base + 2 * k, base + 2 * k + 1, base + 2 * k + 2, base + 2 * k + 3);
            self.triangle(part, a, c, b);
            self.triangle(part, b, c, d);
        }
        // Caps: a centre vertex and a ring, UVs mapped into the upper part of the texture.
        for (z, up) in [(z1, 1.0f32), (z0, -1.0)] {
            let n = Vec3::Z * up;
            let centre = self.vertex(center_xy.extend(z), n, Vec2::new(0.5, 0.625));
            let first = self.mesh.positions.len() as u32;
            for k in 0..segments {
                let d = ring(k);
                self.vertex((center_xy + radius * d).extend(z), n, Vec2::new(0.5 + 0.5 * d.x, 0.625 + 0.375 * d.y));
            }
            for k in 0..segments {
                let (a, b) = (first + k, first + (k + 1) % segments);
                if up > 0.0 {
                    self.triangle(part, centre, a, b);
                } else {
                    self.triangle(part, centre, b, a);
                }
            }
        }
    }

    pub fn build(self) -> Mesh {
        self.mesh
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::material::{BaseColor, Scalar};

    fn material() -> PartMaterial {
        PartMaterial { name: "m".into(), base_color: BaseColor::Constant(Vec3::ONE), roughness: Scalar::Constant(0.5), metallic: Scalar::Constant(0.0) }
    }

    /// Signed volume by the divergence theorem: positive for outward-wound closed meshes.
    fn volume(m: &Mesh) -> f32 {
        m.triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|i| m.positions[i as usize]);
                a.dot(b.cross(c)) / 6.0
            })
            .sum()
    }

    #[test]
    fn ellipsoid_volume_and_normals() {
        let mut b = MeshBuilder::new();
        let p = b.part(material());
        let radii = Vec3::new(0.5, 1.0, 0.25);
        b.ellipsoid(p, Vec3::new(0.3, -0.2, 0.1), radii, Quat::from_rotation_z(0.4), 96, 48);
        let m = b.build();
        let exact = 4.0 / 3.0 * std::f32::consts::PI * radii.x * radii.y * radii.z;
        assert!((volume(&m) - exact).abs() / exact < 0.01, "{} vs {exact}", volume(&m));
        // Vertex normals agree with the face normals around them (outward, smooth surface).
        for t in m.triangles.iter().step_by(37) {
            let [a, b2, c] = t.map(|i| m.positions[i as usize]);
            let face = (b2 - a).cross(c - a).normalize();
            assert!(face.dot(m.normals[t[0] as usize]) > 0.8);
        }
    }

    #[test]
    fn cylinder_is_closed_and_outward() {
        let mut b = MeshBuilder::new();
        let p = b.part(material());
        b.cylinder(p, Vec2::new(0.1, 0.2), 0.5, -0.1, 0.3, 128);
        let m = b.build();
        let exact = std::f32::consts::PI * 0.25 * 0.4;
        assert!((volume(&m) - exact).abs() / exact < 0.01);
    }
}

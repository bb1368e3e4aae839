//! Tangent frames of a mesh's UV layout, one per triangle corner, by MikkTSpace (the `mikktspace`
//! crate). A tangent-space normal map means something only in a frame, and MikkTSpace is the frame
//! Blender, glTF viewers and baking tools rebuild from positions, normals and UVs alone: a map
//! learned in it shades the same when the exported mesh is opened elsewhere.
//!
//! Each corner gets (T, s): T the unit tangent along +u, s = ±1 the handedness, so the bitangent
//! (along +v, the OBJ convention's up) is s·(N × T). A point's frame interpolates its triangle's
//! corner tangents by barycentrics; the shading normal N comes from the G-buffer.

use anyhow::{bail, Result};
use glam::{Vec3, Vec4};

use super::Mesh;

struct Corners<'a> {
    mesh: &'a Mesh,
    out: Vec<[Vec4; 3]>,
}

impl mikktspace::Geometry for Corners<'_> {
    fn num_faces(&self) -> usize {
        self.mesh.triangles.len()
    }
    fn num_vertices_of_face(&self, _face: usize) -> usize {
        3
    }
    fn position(&self, face: usize, vert: usize) -> [f32; 3] {
        self.mesh.positions[self.mesh.triangles[face][vert] as usize].to_array()
    }
    fn normal(&self, face: usize, vert: usize) -> [f32; 3] {
        self.mesh.normals[self.mesh.triangles[face][vert] as usize].to_array()
    }
    fn tex_coord(&self, face: usize, vert: usize) -> [f32; 2] {
        self.mesh.uvs[self.mesh.triangles[face][vert] as usize].to_array()
    }
    fn set_tangent_encoded(&mut self, tangent: [f32; 4], face: usize, vert: usize) {
        self.out[face][vert] = Vec4::from_array(tangent);
    }
}

/// MikkTSpace tangents of every triangle corner of `mesh` (needs its normals and UVs). Corners the
/// algorithm leaves without a frame (degenerate UVs) get one built around the vertex normal, so
/// every frame is finite and its tangent is unit length and orthogonal to that normal.
pub fn corner_tangents(mesh: &Mesh) -> Result<Vec<[Vec4; 3]>> {
    let n = mesh.positions.len();
    if mesh.normals.len() != n || mesh.uvs.len() != n {
        bail!("tangent frames need a normal and a UV per vertex ({} positions, {} normals, {} UVs)", n, mesh.normals.len(), mesh.uvs.len());
    }
    let mut corners = Corners { mesh, out: vec![[Vec4::ZERO; 3]; mesh.triangles.len()] };
    if !mikktspace::generate_tangents(&mut corners) {
        bail!("MikkTSpace could not build tangent frames for a mesh of {} triangles", mesh.triangles.len());
    }
    let mut out = corners.out;
    for (t, tri) in mesh.triangles.iter().enumerate() {
        for (k, &v) in tri.iter().enumerate() {
            let normal = mesh.normals[v as usize];
            let tangent = out[t][k].truncate();
            let sign = if out[t][k].w < 0.0 { -1.0 } else { 1.0 };
            let fixed = (tangent - normal * normal.dot(tangent)).try_normalize().unwrap_or_else(|| normal.any_orthonormal_vector());
            out[t][k] = fixed.extend(sign);
        }
    }
    Ok(out)
}

/// The frame at barycentrics `bary` = (b0, b1, b2) of a triangle with corner frames `corners`:
/// the tangents interpolated (not renormalised, as MikkTSpace's reference shader does) and the
/// handedness of the first corner (MikkTSpace gives all corners of a face the same one).
pub fn interpolate(corners: &[Vec4; 3], bary: Vec3) -> (Vec3, f32) {
    let t = corners[0].truncate() * bary.x + corners[1].truncate() * bary.y + corners[2].truncate() * bary.z;
    (t, corners[0].w)
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec2;

    fn quad(flip_u: bool) -> Mesh {
        // A unit square in the xy plane facing +z, u along +x (or −x), v along +y.
        let u = |x: f32| if flip_u { 1.0 - x } else { x };
        Mesh {
            positions: vec![Vec3::new(0.0, 0.0, 0.0), Vec3::new(1.0, 0.0, 0.0), Vec3::new(1.0, 1.0, 0.0), Vec3::new(0.0, 1.0, 0.0)],
            normals: vec![Vec3::Z; 4],
            uvs: vec![Vec2::new(u(0.0), 0.0), Vec2::new(u(1.0), 0.0), Vec2::new(u(1.0), 1.0), Vec2::new(u(0.0), 1.0)],
            triangles: vec![[0, 1, 2], [0, 2, 3]],
            triangle_part: vec![0, 0],
            ..Default::default()
        }
    }

    #[test]
    fn tangent_follows_u_and_the_bitangent_follows_v() -> Result<()> {
        for flip in [false, true] {
            let frames = corner_tangents(&quad(flip))?;
            for tri in &frames {
                for c in tri {
                    let (t, s) = (c.truncate(), c.w);
                    let expect_t = if flip { -Vec3::X } else { Vec3::X };
                    assert!((t - expect_t).length() < 1e-5, "flip {flip}: tangent {t}");
                    // The bitangent s·(N × T) must point along +v, which is +y either way.
                    let b = s * Vec3::Z.cross(t);
                    assert!((b - Vec3::Y).length() < 1e-5, "flip {flip}: bitangent {b} (sign {s})");
                }
            }
        }
        Ok(())
    }

    #[test]
    fn degenerate_uvs_still_give_unit_orthogonal_frames() -> Result<()> {
        let mut m = quad(false);
        m.uvs = vec![Vec2::ZERO; 4];
        for tri in corner_tangents(&m)? {
            for c in tri {
                assert!(c.is_finite());
                assert!((c.truncate().length() - 1.0).abs() < 1e-5);
                assert!(c.truncate().dot(Vec3::Z).abs() < 1e-5);
            }
        }
        Ok(())
    }

    #[test]
    fn missing_uvs_are_an_error() {
        let mut m = quad(false);
        m.uvs.pop();
        assert!(corner_tangents(&m).unwrap_err().to_string().contains("UV"));
    }
}

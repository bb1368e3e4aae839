//! Exact point-to-surface queries on a triangle mesh: the closest point on any triangle (interior,
//! edge or corner), its distance and the triangle it lies on. parry3d answers them with its own BVH
//! searched best-first, so a query costs a few triangle tests instead of one per triangle. The
//! geometry metrics measure every distance this way, never to the nearest of a set of samples.

use anyhow::{bail, Result};
use glam::Vec3;
use parry3d::query::PointQueryWithLocation;
use parry3d::shape::TriMesh;

use super::Mesh;

/// The closest surface point to a query point.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Closest {
    pub point: Vec3,
    pub distance: f32,
    /// Index into the mesh's triangle list. A point nearest to an edge or corner shared by several
    /// triangles gets one of them.
    pub triangle: u32,
}

/// A mesh prepared for closest-point queries.
pub struct SurfaceQuery {
    trimesh: TriMesh,
    /// Mesh triangle index of each triangle kept in `trimesh`.
    triangle_ids: Vec<u32>,
}

impl SurfaceQuery {
    /// Degenerate (zero-area) and non-finite triangles are left out: they carry no surface area and
    /// no normal. Fails when nothing is left.
    pub fn new(mesh: &Mesh) -> Result<SurfaceQuery> {
        let mut indices = Vec::with_capacity(mesh.triangles.len());
        let mut triangle_ids = Vec::with_capacity(mesh.triangles.len());
        for (t, tri) in mesh.triangles.iter().enumerate() {
            let [a, b, c] = mesh.triangle_positions(t);
            let area2 = (b - a).cross(c - a).length_squared();
            if area2 > 0.0 && area2.is_finite() && a.is_finite() && b.is_finite() && c.is_finite() {
                indices.push(*tri);
                triangle_ids.push(t as u32);
            }
        }
        if indices.is_empty() {
            bail!("the mesh has no surface to measure distances to ({} triangles, all degenerate or none)", mesh.triangles.len());
        }
        let vertices = mesh.positions.iter().map(|p| parry3d::math::Vector::from_array(p.to_array())).collect();
        let trimesh = TriMesh::new(vertices, indices)?;
        Ok(SurfaceQuery { trimesh, triangle_ids })
    }

    /// The closest point of the surface to `p` (None only for a non-finite `p`).
    pub fn closest(&self, p: Vec3) -> Option<Closest> {
        if !p.is_finite() {
            return None;
        }
        let q = parry3d::math::Vector::from_array(p.to_array());
        let (proj, (k, _)) = self.trimesh.project_local_point_and_get_location_with_max_dist(q, false, f32::MAX)?;
        let point = Vec3::from_array(proj.point.to_array());
        Some(Closest { point, distance: point.distance(p), triangle: self.triangle_ids[k as usize] })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The unit square [0, 1]² at z = 0 as two triangles, plus a degenerate one far away.
    fn square() -> Mesh {
        Mesh {
            positions: vec![Vec3::ZERO, Vec3::X, Vec3::new(1.0, 1.0, 0.0), Vec3::Y, Vec3::new(-5.0, 0.0, 0.0)],
            triangles: vec![[0, 1, 2], [0, 2, 3], [4, 4, 0]],
            ..Default::default()
        }
    }

    #[test]
    fn closest_points_on_face_edge_and_corner() {
        let q = SurfaceQuery::new(&square()).unwrap();
        // Above the interior of each triangle: straight down.
        let c = q.closest(Vec3::new(0.75, 0.25, 2.0)).unwrap();
        assert!((c.distance - 2.0).abs() < 1e-6 && c.triangle == 0 && (c.point - Vec3::new(0.75, 0.25, 0.0)).length() < 1e-6, "{c:?}");
        let c = q.closest(Vec3::new(0.25, 0.75, -0.5)).unwrap();
        assert!((c.distance - 0.5).abs() < 1e-6 && c.triangle == 1, "{c:?}");
        // Beside the edge x = 1: the foot is on the edge, distance √(1² + 1²).
        let c = q.closest(Vec3::new(2.0, 0.3, 1.0)).unwrap();
        assert!((c.distance - 2f32.sqrt()).abs() < 1e-6 && (c.point - Vec3::new(1.0, 0.3, 0.0)).length() < 1e-6, "{c:?}");
        // Past the corner (1, 1, 0): distance √3.
        let c = q.closest(Vec3::new(2.0, 2.0, 1.0)).unwrap();
        assert!((c.distance - 3f32.sqrt()).abs() < 1e-6 && (c.point - Vec3::ONE.with_z(0.0)).length() < 1e-6, "{c:?}");
        // The degenerate triangle toward x = −5 is not part of the surface: (−3, 0, 0) is 3 away.
        let c = q.closest(Vec3::new(-3.0, 0.0, 0.0)).unwrap();
        assert!((c.distance - 3.0).abs() < 1e-6, "{c:?}");
        assert!(q.closest(Vec3::NAN).is_none());
    }

    #[test]
    fn a_mesh_without_area_is_an_error() {
        let mut m = square();
        m.triangles = vec![[4, 4, 0]];
        let err = SurfaceQuery::new(&m).err().expect("no area must fail").to_string();
        assert!(err.contains("no surface"), "{err}");
        assert!(SurfaceQuery::new(&Mesh::default()).is_err());
    }
}

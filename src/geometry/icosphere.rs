//! A welded, closed sphere mesh made by subdividing an icosahedron: near-equilateral triangles of
//! nearly one size everywhere and no seams or poles (unlike a UV sphere, whose duplicated seam
//! vertices and pole fans would tear or sliver under an optimiser that moves vertices). The
//! geometry pass's tests start from it.

use std::collections::HashMap;

use glam::{Vec2, Vec3};

use crate::geometry::{Mesh, Part};
use crate::material::{BaseColor, PartMaterial, Scalar};

/// A sphere of `radius` around `center`, the icosahedron's 20 faces each split into 4ⁿ for
/// `subdivisions` = n (n = 3: 642 vertices, 1280 triangles). Outward-facing counter-clockwise
/// triangles, exact sphere normals, zero UVs, one grey part.
pub fn icosphere(center: Vec3, radius: f32, subdivisions: u32) -> Mesh {
    let t = (1.0 + 5f32.sqrt()) / 2.0;
    let mut dirs: Vec<Vec3> = [
        [-1.0, t, 0.0],
        [1.0, t, 0.0],
        [-1.0, -t, 0.0],
        [1.0, -t, 0.0],
        [0.0, -1.0, t],
        [0.0, 1.0, t],
        [0.0, -1.0, -t],
        [0.0, 1.0, -t],
        [t, 0.0, -1.0],
        [t, 0.0, 1.0],
        [-t, 0.0, -1.0],
        [-t, 0.0, 1.0],
    ]
    .iter()
    .map(|v| Vec3::from_array(*v).normalize())
    .collect();
    let mut tris: Vec<[u32; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..subdivisions {
        let mut mid: HashMap<(u32, u32), u32> = HashMap::new();
        let mut midpoint = |a: u32, b: u32, dirs: &mut Vec<Vec3>| {
            *mid.entry((a.min(b), a.max(b))).or_insert_with(|| {
                dirs.push((dirs[a as usize] + dirs[b as usize]).normalize());
                (dirs.len() - 1) as u32
            })
        };
        let mut next = Vec::with_capacity(tris.len() * 4);
        for [a, b, c] in tris {
            let (ab, bc, ca) = (midpoint(a, b, &mut dirs), midpoint(b, c, &mut dirs), midpoint(c, a, &mut dirs));
            next.extend([[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]);
        }
        tris = next;
    }
    let n = dirs.len();
    Mesh {
        positions: dirs.iter().map(|d| center + radius * *d).collect(),
        normals: dirs,
        uvs: vec![Vec2::ZERO; n],
        triangle_part: vec![0; tris.len()],
        triangles: tris,
        parts: vec![Part { name: "sphere".into(), material: 0, has_uv: false }],
        materials: vec![PartMaterial { name: "grey".into(), base_color: BaseColor::Constant(Vec3::splat(0.5)), roughness: Scalar::Constant(0.6), metallic: Scalar::Constant(0.0) }],
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::HashMap;

    #[test]
    fn closed_outward_and_on_the_sphere() {
        let m = icosphere(Vec3::new(1.0, 2.0, 3.0), 0.5, 2);
        assert_eq!((m.positions.len(), m.triangles.len()), (162, 320));
        m.validate().unwrap();
        // Closed and manifold: every undirected edge in exactly two triangles, once per direction.
        let mut edges: HashMap<(u32, u32), usize> = HashMap::new();
        for t in &m.triangles {
            for e in 0..3 {
                *edges.entry((t[e], t[(e + 1) % 3])).or_default() += 1;
            }
        }
        assert!(edges.iter().all(|(&(a, b), &k)| k == 1 && edges.get(&(b, a)) == Some(&1)));
        // Euler characteristic of a sphere.
        assert_eq!(m.positions.len() as i64 - edges.len() as i64 / 2 + m.triangles.len() as i64, 2);
        for (t, _) in m.triangles.iter().enumerate() {
            let [p0, ..] = m.triangle_positions(t);
            assert!(m.face_normal_scaled(t).dot(p0 - Vec3::new(1.0, 2.0, 3.0)) > 0.0, "triangle {t} faces inward");
        }
        assert!(m.positions.iter().all(|p| ((*p - Vec3::new(1.0, 2.0, 3.0)).length() - 0.5).abs() < 1e-5));
    }
}

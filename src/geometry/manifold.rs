//! Topology checks for a closed surface: every edge shared by exactly two triangles that use it in
//! opposite directions (closed, manifold at the edges, consistently oriented), no vertex whose
//! triangle fan splits into several pieces (manifold at the vertices), no degenerate triangle, and
//! the Euler characteristic V − E + F. Meshes made or changed by the program (the visual hull, its
//! remesh) are checked with these before anything traces or optimises them.

use std::collections::HashMap;

use crate::geometry::Mesh;

/// Counts of a closed, consistently oriented 2-manifold triangle mesh.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ClosedManifold {
    pub vertices: usize,
    pub edges: usize,
    pub faces: usize,
    /// V − E + F: 2 for a sphere-like surface, 2 − 2g for genus g, 2c for c sphere-like pieces.
    pub euler: i64,
}

/// Checks that `mesh` is a closed, consistently oriented 2-manifold with no unused vertex and no
/// zero-area triangle; returns its counts, or a description of the first defect found.
pub fn check_closed_manifold(mesh: &Mesh) -> Result<ClosedManifold, String> {
    let n = mesh.positions.len();
    // Directed edge → how many triangles use it in that direction.
    let mut directed: HashMap<(u32, u32), u32> = HashMap::with_capacity(3 * mesh.triangles.len());
    let mut used = vec![false; n];
    for (t, tri) in mesh.triangles.iter().enumerate() {
        if tri.iter().any(|&i| i as usize >= n) {
            return Err(format!("triangle {t} {tri:?} indexes past {n} vertices"));
        }
        if tri[0] == tri[1] || tri[1] == tri[2] || tri[0] == tri[2] {
            return Err(format!("triangle {t} {tri:?} repeats a vertex"));
        }
        let area2 = mesh.face_normal_scaled(t).length();
        if !area2.is_finite() || area2 <= 0.0 {
            return Err(format!("triangle {t} {tri:?} has zero or non-finite area"));
        }
        for k in 0..3 {
            used[tri[k] as usize] = true;
            *directed.entry((tri[k], tri[(k + 1) % 3])).or_insert(0) += 1;
        }
    }
    if let Some(v) = used.iter().position(|&u| !u) {
        return Err(format!("vertex {v} belongs to no triangle"));
    }
    for (&(a, b), &count) in &directed {
        if count > 1 {
            return Err(format!("edge {a}→{b} is used {count} times in the same direction (non-manifold or inconsistently oriented)"));
        }
        if !directed.contains_key(&(b, a)) {
            return Err(format!("edge {a}→{b} has no opposite half: the surface is open there or inconsistently oriented"));
        }
    }
    // Manifold vertices: the triangles around a vertex form a single fan. With every edge having
    // exactly one twin, following "next outgoing edge" around the vertex must visit all of them.
    let mut outgoing: Vec<Vec<u32>> = vec![Vec::new(); n];
    let mut next_around: HashMap<(u32, u32), u32> = HashMap::with_capacity(3 * mesh.triangles.len());
    for tri in &mesh.triangles {
        for k in 0..3 {
            let (a, b, c) = (tri[k], tri[(k + 1) % 3], tri[(k + 2) % 3]);
            outgoing[a as usize].push(b);
            // Turning around `a`: triangle (a, b, c) ends with edge c→a, whose twin a→c is the next
            // outgoing edge of `a`, in the neighbouring triangle.
            next_around.insert((a, b), c);
        }
    }
    for (v, out) in outgoing.iter().enumerate() {
        let start = out[0];
        let mut current = start;
        let mut steps = 0;
        loop {
            current = next_around[&(v as u32, current)];
            steps += 1;
            if current == start || steps > out.len() {
                break;
            }
        }
        if steps != out.len() {
            return Err(format!("vertex {v} joins {} triangles that form more than one fan (non-manifold vertex)", out.len()));
        }
    }
    let (vertices, edges, faces) = (n, directed.len() / 2, mesh.triangles.len());
    Ok(ClosedManifold { vertices, edges, faces, euler: vertices as i64 - edges as i64 + faces as i64 })
}

/// Flips triangles so that every edge shared by two triangles is used in opposite directions (a
/// breadth-first walk over edge neighbours from one triangle of each connected piece); returns how
/// many were flipped. Fails, naming the edge, when an edge has more than two triangles or when the
/// surface cannot be oriented.
pub fn orient_consistently(triangles: &mut [[u32; 3]]) -> Result<usize, String> {
    let key = |a: u32, b: u32| (a.min(b), a.max(b));
    let mut by_edge: HashMap<(u32, u32), Vec<usize>> = HashMap::with_capacity(3 * triangles.len() / 2);
    for (t, tri) in triangles.iter().enumerate() {
        for k in 0..3 {
            by_edge.entry(key(tri[k], tri[(k + 1) % 3])).or_default().push(t);
        }
    }
    if let Some((e, ts)) = by_edge.iter().find(|(_, ts)| ts.len() > 2) {
        return Err(format!("edge {}–{} is shared by {} triangles (non-manifold)", e.0, e.1, ts.len()));
    }
    // Whether triangle `t` runs along a→b (true) or b→a.
    let runs = |tri: &[u32; 3], a: u32, b: u32| (0..3).any(|k| tri[k] == a && tri[(k + 1) % 3] == b);
    let mut done = vec![false; triangles.len()];
    let mut flipped = 0;
    let mut queue = std::collections::VecDeque::new();
    for seed in 0..triangles.len() {
        if done[seed] {
            continue;
        }
        done[seed] = true;
        queue.push_back(seed);
        while let Some(t) = queue.pop_front() {
            let tri = triangles[t];
            for k in 0..3 {
                let (a, b) = (tri[k], tri[(k + 1) % 3]);
                for &u in &by_edge[&key(a, b)] {
                    if u == t {
                        continue;
                    }
                    let agrees = runs(&triangles[u], b, a);
                    if done[u] {
                        if !agrees {
                            return Err(format!("the surface cannot be oriented (at edge {a}–{b}; a Möbius-like piece)"));
                        }
                        continue;
                    }
                    if !agrees {
                        triangles[u].swap(1, 2);
                        flipped += 1;
                    }
                    done[u] = true;
                    queue.push_back(u);
                }
            }
        }
    }
    Ok(flipped)
}

/// Gives each extra fan of a pinched vertex (one whose triangles form several fans, joined only at
/// that point) its own copy of the vertex, so that the surface is manifold at its vertices; sheets
/// that touch along an edge (an edge with four triangles) are parted the same way. Returns how many
/// vertices were added.
pub fn split_pinched_vertices(positions: &mut Vec<glam::Vec3>, triangles: &mut [[u32; 3]]) -> usize {
    // Corners (3·triangle + k) around the same vertex join when their triangles share an edge there.
    let mut parent: Vec<usize> = (0..3 * triangles.len()).collect();
    fn root(parent: &mut [usize], mut i: usize) -> usize {
        while parent[i] != i {
            parent[i] = parent[parent[i]];
            i = parent[i];
        }
        i
    }
    let mut by_edge: HashMap<(u32, u32), Vec<usize>> = HashMap::with_capacity(3 * triangles.len() / 2);
    for (t, tri) in triangles.iter().enumerate() {
        for k in 0..3 {
            let (a, b) = (tri[k], tri[(k + 1) % 3]);
            by_edge.entry((a.min(b), a.max(b))).or_default().push(t);
        }
    }
    let corner_of = |t: usize, v: u32, tris: &[[u32; 3]]| 3 * t + tris[t].iter().position(|&x| x == v).expect("vertex of triangle");
    for (&(a, b), ts) in &by_edge {
        // An edge with more than two triangles joins nothing: where two sheets touch along an edge,
        // each sheet's triangles around the edge's end points still join through the sheet's other
        // edges, so each end point splits into one copy per sheet and the edge into one per sheet.
        if ts.len() > 2 {
            continue;
        }
        for pair in ts.windows(2) {
            for v in [a, b] {
                let (c0, c1) = (corner_of(pair[0], v, triangles), corner_of(pair[1], v, triangles));
                let (r0, r1) = (root(&mut parent, c0), root(&mut parent, c1));
                parent[r1] = r0;
            }
        }
    }
    // The first fan met keeps the vertex; later fans get copies.
    let mut fan_vertex: HashMap<usize, u32> = HashMap::new();
    let mut has_fan = vec![false; positions.len()];
    let before = positions.len();
    for (t, tri) in triangles.iter_mut().enumerate() {
        for (k, corner) in tri.iter_mut().enumerate() {
            let v = *corner;
            let r = root(&mut parent, 3 * t + k);
            let id = *fan_vertex.entry(r).or_insert_with(|| {
                if has_fan[v as usize] {
                    positions.push(positions[v as usize]);
                    (positions.len() - 1) as u32
                } else {
                    has_fan[v as usize] = true;
                    v
                }
            });
            *corner = id;
        }
    }
    positions.len() - before
}

/// Signed volume enclosed by a closed mesh (divergence theorem): positive when its triangles face outward.
pub fn signed_volume(mesh: &Mesh) -> f64 {
    mesh.triangles
        .iter()
        .map(|t| {
            let [a, b, c] = t.map(|i| mesh.positions[i as usize].as_dvec3());
            a.dot(b.cross(c)) / 6.0
        })
        .sum()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::primitives::MeshBuilder;
    use crate::material::{BaseColor, PartMaterial, Scalar};
    use glam::Vec3;

    fn tetrahedron() -> Mesh {
        let positions = vec![Vec3::ZERO, Vec3::X, Vec3::Y, Vec3::Z];
        let triangles = vec![[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]];
        Mesh { normals: vec![Vec3::Z; 4], uvs: vec![glam::Vec2::ZERO; 4], triangle_part: vec![0; 4], positions, triangles, ..Default::default() }
    }

    #[test]
    fn tetrahedron_is_a_closed_outward_sphere() {
        let m = tetrahedron();
        let c = check_closed_manifold(&m).unwrap();
        assert_eq!((c.vertices, c.edges, c.faces, c.euler), (4, 6, 4, 2));
        assert!((signed_volume(&m) - 1.0 / 6.0).abs() < 1e-9);
    }

    #[test]
    fn orienting_repairs_flipped_triangles() {
        let mut m = tetrahedron();
        m.triangles[1].swap(0, 1);
        m.triangles[3].swap(1, 2);
        assert!(check_closed_manifold(&m).is_err());
        assert_eq!(orient_consistently(&mut m.triangles).unwrap(), 2);
        check_closed_manifold(&m).unwrap();
        // All four agree with each other; the walk starts from triangle 0, which was outward.
        assert!(signed_volume(&m) > 0.0);
    }

    /// Two tetrahedra sharing one vertex.
    fn pinched_pair() -> Mesh {
        let mut pinched = tetrahedron();
        let mut other = tetrahedron();
        for p in &mut other.positions {
            *p = -*p;
        }
        pinched.positions.extend(&other.positions[1..]);
        pinched.normals.extend(&other.normals[1..]);
        pinched.uvs.extend(&other.uvs[1..]);
        for t in &other.triangles {
            pinched.triangles.push(t.map(|i| if i == 0 { 0 } else { i + 3 }));
            pinched.triangle_part.push(0);
        }
        pinched
    }

    #[test]
    fn pinched_vertices_are_split_into_one_per_fan() {
        let mut m = pinched_pair();
        assert!(check_closed_manifold(&m).is_err());
        assert_eq!(split_pinched_vertices(&mut m.positions, &mut m.triangles), 1);
        m.normals.push(Vec3::Z);
        m.uvs.push(glam::Vec2::ZERO);
        let c = check_closed_manifold(&m).unwrap();
        // Two separate tetrahedra: 8 vertices, 12 edges, 8 faces, Euler 2 + 2.
        assert_eq!((c.vertices, c.edges, c.faces, c.euler), (8, 12, 8, 4));
        // A manifold mesh is left alone.
        let mut t = tetrahedron();
        assert_eq!(split_pinched_vertices(&mut t.positions, &mut t.triangles), 0);
    }

    /// Two tetrahedra sharing the edge 0–X (the second is the first turned 180° about the x axis).
    #[test]
    fn sheets_touching_along_an_edge_are_parted() {
        let mut m = tetrahedron();
        let other = tetrahedron();
        m.positions.extend(other.positions[2..].iter().map(|p| Vec3::new(p.x, -p.y, -p.z)));
        m.normals.extend(&other.normals[2..]);
        m.uvs.extend(&other.uvs[2..]);
        for t in &other.triangles {
            m.triangles.push(t.map(|i| if i < 2 { i } else { i + 2 }));
            m.triangle_part.push(0);
        }
        assert!(check_closed_manifold(&m).unwrap_err().contains("used 2 times in the same direction"));
        assert_eq!(split_pinched_vertices(&mut m.positions, &mut m.triangles), 2);
        m.normals.extend([Vec3::Z; 2]);
        m.uvs.extend([glam::Vec2::ZERO; 2]);
        let c = check_closed_manifold(&m).unwrap();
        assert_eq!((c.vertices, c.edges, c.faces, c.euler), (8, 12, 8, 4));
        assert!((signed_volume(&m) - 2.0 / 6.0).abs() < 1e-9);
    }

    #[test]
    fn defects_are_named() {
        let mut open = tetrahedron();
        open.triangles.pop();
        assert!(check_closed_manifold(&open).unwrap_err().contains("no opposite half"));
        let mut flipped = tetrahedron();
        flipped.triangles[0] = [0, 1, 2];
        assert!(check_closed_manifold(&flipped).is_err());
        // Two tetrahedra sharing only vertex 0: every edge is fine but vertex 0 has two fans.
        let pinched = pinched_pair();
        assert!(check_closed_manifold(&pinched).unwrap_err().contains("more than one fan"));
    }

    #[test]
    fn uv_sphere_with_a_split_seam_is_rejected() {
        // The UV sphere repeats its seam and pole vertices, so it is open as built: a real-world
        // mesh that the check must reject.
        let mut b = MeshBuilder::new();
        let p = b.part(PartMaterial { name: "m".into(), base_color: BaseColor::Constant(Vec3::ONE), roughness: Scalar::Constant(0.5), metallic: Scalar::Constant(0.0) });
        b.ellipsoid(p, Vec3::ZERO, Vec3::ONE, glam::Quat::IDENTITY, 16, 8);
        assert!(check_closed_manifold(&b.build()).is_err());
    }
}

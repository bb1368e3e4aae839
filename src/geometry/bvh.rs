//! Ray queries against a mesh through an 8-wide BVH built by obvhs.
//!
//! Two layouts of the same kind of tree ([`Layout`]):
//! - **`Float8`, the default**: obvhs' binary BVH collapsed to 8-wide nodes of float boxes, leaves
//!   of triangles tested four at a time ([`super::bvh8`]). On the hotdog it traces incoherent rays
//!   about twice as fast as the compressed layout (docs/performance.md, *A float layout*).
//! - **`Cwbvh`**: obvhs' compressed wide BVH and its traversal, with an AVX2 (or AVX-512) node
//!   test where the CPU has it ([`super::bvh_wide`]) or obvhs' SSE test. It stays as the
//!   reference the tests hold the default to, and for meshes too large for the float layout's
//!   leaf references.
//!
//! obvhs reports leaf primitives as indices into its own `primitive_indices`; both layouts store
//! the triangles already permuted into leaf order (so the hot loop reads memory linearly)
//! together with their index in the mesh's triangle list, which is what [`Hit::triangle`] returns.
//! `closest_hit_using` / `any_hit_using` pick a node test explicitly (benchmarks, and the tests
//! comparing them); on the float layout `NodeTest::Obvhs` selects its scalar node test.

use std::time::Duration;

use glam::{UVec2, Vec2, Vec3, Vec3A};
use obvhs::cwbvh::builder::build_cwbvh_from_tris;
use obvhs::cwbvh::node::CwBvhNode;
use obvhs::cwbvh::CwBvh;
use obvhs::ray::Ray;
use obvhs::triangle::Triangle;
use obvhs::BvhBuildParams;

use super::bvh8::{self, Bvh8, PreparedRay, NO_TRIANGLE};
use super::bvh_wide::{self, NodeTest};
use super::Mesh;

/// A ray/triangle intersection.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    /// Index into the mesh's triangle list.
    pub triangle: u32,
    /// Distance along the ray direction (in units of |dir|).
    pub t: f32,
    /// Barycentrics (b1, b2) of the hit; b0 = 1 − b1 − b2.
    pub bary: Vec2,
}

/// A triangle in the form the intersection test wants: one vertex and two edges, 9 floats with no
/// padding (36 bytes, against 48 as three 16-byte vectors), stored in the leaves' order so that a
/// node's leaf triangles are one contiguous walk of at most 24 × 36 bytes.
#[derive(Clone, Copy, Debug)]
#[repr(C)]
struct PackedTriangle {
    v0: Vec3,
    e1: Vec3,
    e2: Vec3,
}

/// Möller–Trumbore ray/triangle test for the triangle (p0, p1, p2). Returns (t, b1, b2) for a hit
/// with t in [tmin, tmax]. Zero-area (or non-finite) triangles never hit: their determinant is 0
/// or the barycentric test fails, so no NaN can escape.
#[inline(always)]
fn intersect_packed(tri: &PackedTriangle, origin: Vec3A, dir: Vec3A, tmin: f32, tmax: f32) -> Option<(f32, f32, f32)> {
    let (v0, e1, e2) = (Vec3A::from(tri.v0), Vec3A::from(tri.e1), Vec3A::from(tri.e2));
    let p = dir.cross(e2);
    let det = e1.dot(p);
    // `!(det != 0)` also rejects NaN.
    if det == 0.0 || det.is_nan() {
        return None;
    }
    let inv_det = 1.0 / det;
    let s = origin - v0;
    let b1 = s.dot(p) * inv_det;
    if !(0.0..=1.0).contains(&b1) {
        return None;
    }
    let q = s.cross(e1);
    let b2 = dir.dot(q) * inv_det;
    if !(b2 >= 0.0 && b1 + b2 <= 1.0) {
        return None;
    }
    let t = e2.dot(q) * inv_det;
    if t >= tmin && t <= tmax && t.is_finite() {
        Some((t, b1, b2))
    } else {
        None
    }
}

/// The same test on three points, for brute-force references and one-off queries.
pub fn intersect_triangle(p: [Vec3; 3], origin: Vec3, dir: Vec3, tmin: f32, tmax: f32) -> Option<(f32, Vec2)> {
    let (a, b, c) = (Vec3A::from(p[0]), Vec3A::from(p[1]), Vec3A::from(p[2]));
    let tri = PackedTriangle { v0: a.into(), e1: (b - a).into(), e2: (c - a).into() };
    intersect_packed(&tri, origin.into(), dir.into(), tmin, tmax).map(|(t, b1, b2)| (t, Vec2::new(b1, b2)))
}

/// obvhs picks a node's near slab by `dir < 0` but inverts ±0 by its sign, so a −0.0 component
/// (e.g. from negating +z) makes every box test miss. Adding +0.0 turns −0.0 into +0.0.
#[inline(always)]
fn positive_zeros(dir: Vec3) -> Vec3A {
    Vec3A::from(dir) + Vec3A::ZERO
}

/// A BVH over a mesh's triangles. Degenerate (zero-area or non-finite) triangles are left out:
/// a ray can never hit them, and leaving them out keeps NaN bounds away from the builder.
pub struct Bvh {
    tree: Option<Tree>,
    /// Mesh triangle index of each leaf slot: each entry of the CWBVH's triangle list, or each
    /// block lane of the float layout ([`NO_TRIANGLE`] where a lane is unused).
    triangle_ids: Vec<u32>,
    /// The node test queries use ([`NodeTest::detect`] at build time).
    node_test: NodeTest,
}

/// How the tree's nodes are stored and traversed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Layout {
    /// obvhs' compressed wide BVH and its traversal, with the node tests of [`NodeTest`].
    Cwbvh,
    /// [`Bvh8`]: obvhs' binary tree collapsed to 8-wide nodes of float boxes, nearest child first.
    Float8,
}

enum Tree {
    /// The compressed tree and its triangles in obvhs' primitive order.
    Cwbvh { cwbvh: CwBvh, triangles: Vec<PackedTriangle> },
    /// The float tree, which holds its triangles in its leaves' blocks.
    Float8(Bvh8),
}

/// Closest-hit traversal with the node test `$test(node, &ray, oct_inv4)`: (primitive slot, t, b1, b2).
macro_rules! closest_traversal {
    ($tris:expr, $bvh:expr, $o:expr, $d:expr, $tmin:expr, $tmax:expr, $test:path) => {{
        let mut ray = Ray::new($o, $d, $tmin, $tmax);
        let mut best: Option<(u32, f32, f32, f32)> = None;
        let mut state = $bvh.new_traversal(ray.direction);
        let mut node;
        obvhs::traverse!($bvh, node, state, $test(node, &ray, state.oct_inv4), {
            let k = state.primitive_id as usize;
            if let Some((t, b1, b2)) = intersect_packed(&$tris[k], $o, $d, $tmin, ray.tmax) {
                best = Some((k as u32, t, b1, b2));
                ray.tmax = t; // shrink so farther boxes and triangles are culled
            }
        });
        best
    }};
}

/// Any-hit traversal with the node test `$test`: stops at the first hit on the segment.
macro_rules! any_traversal {
    ($tris:expr, $bvh:expr, $o:expr, $d:expr, $tmin:expr, $tmax:expr, $test:path) => {{
        let ray = Ray::new($o, $d, $tmin, $tmax);
        let mut state = $bvh.new_traversal(ray.direction);
        let mut node;
        // The macro runs the primitive block inside its own inner loop, so a plain `break` would
        // only leave that loop; break out of the labelled block to stop the whole traversal.
        'traversal: {
            obvhs::traverse!($bvh, node, state, $test(node, &ray, state.oct_inv4), {
                if intersect_packed(&$tris[state.primitive_id as usize], $o, $d, $tmin, $tmax).is_some() {
                    break 'traversal true;
                }
            });
            false
        }
    }};
}

impl Bvh {
    /// Build the float layout with obvhs' "medium" preset (PLOC + reinsertion, no spatial splits);
    /// see examples/bench_rays.rs for the preset and layout comparison on the hotdog.
    pub fn build(mesh: &Mesh) -> Bvh {
        Bvh::build_with(mesh, BvhBuildParams::medium_build())
    }

    pub fn build_with(mesh: &Mesh, params: BvhBuildParams) -> Bvh {
        Bvh::build_layout(mesh, params, Layout::Float8)
    }

    /// Build with the given preset and node layout.
    pub fn build_layout(mesh: &Mesh, params: BvhBuildParams, layout: Layout) -> Bvh {
        let mut tris = Vec::with_capacity(mesh.triangles.len());
        let mut ids = Vec::with_capacity(mesh.triangles.len());
        for t in 0..mesh.triangles.len() {
            let [p0, p1, p2] = mesh.triangle_positions(t);
            let area2 = (p1 - p0).cross(p2 - p0).length_squared();
            if area2 > 0.0 && area2.is_finite() && p0.is_finite() && p1.is_finite() && p2.is_finite() {
                tris.push(Triangle { v0: p0.into(), v1: p1.into(), v2: p2.into() });
                ids.push(t as u32);
            }
        }
        // A leaf reference of the float layout holds triangle indices below `bvh8::MAX_TRIANGLES`
        // (134 million); a larger mesh takes the compressed layout.
        let layout = if tris.len() >= bvh8::MAX_TRIANGLES { Layout::Cwbvh } else { layout };
        if tris.is_empty() {
            return Bvh { tree: None, triangle_ids: Vec::new(), node_test: NodeTest::Obvhs };
        }
        match layout {
            Layout::Cwbvh => {
                let cwbvh = build_cwbvh_from_tris(&tris, params, &mut Duration::default());
                let triangles = cwbvh
                    .primitive_indices
                    .iter()
                    .map(|&i| {
                        let t = &tris[i as usize];
                        PackedTriangle { v0: t.v0.into(), e1: (t.v1 - t.v0).into(), e2: (t.v2 - t.v0).into() }
                    })
                    .collect();
                let triangle_ids = cwbvh.primitive_indices.iter().map(|&i| ids[i as usize]).collect();
                Bvh { tree: Some(Tree::Cwbvh { cwbvh, triangles }), triangle_ids, node_test: NodeTest::detect() }
            }
            Layout::Float8 => {
                let bvh8 = Bvh8::build(&tris, params);
                let triangle_ids = bvh8.lane_triangles().iter().map(|&i| if i == NO_TRIANGLE { NO_TRIANGLE } else { ids[i as usize] }).collect();
                Bvh { tree: Some(Tree::Float8(bvh8)), triangle_ids, node_test: NodeTest::detect() }
            }
        }
    }

    /// Bytes of nodes and triangles that traversal reads (the mesh-side index table aside).
    pub fn footprint_bytes(&self) -> usize {
        match &self.tree {
            None => 0,
            Some(Tree::Cwbvh { cwbvh, triangles }) => cwbvh.nodes.len() * std::mem::size_of::<CwBvhNode>() + std::mem::size_of_val(triangles.as_slice()),
            Some(Tree::Float8(bvh8)) => bvh8.footprint().0,
        }
    }

    /// The node layout queries traverse (`None` for an empty tree).
    pub fn layout(&self) -> Option<Layout> {
        match self.tree.as_ref()? {
            Tree::Cwbvh { .. } => Some(Layout::Cwbvh),
            Tree::Float8(_) => Some(Layout::Float8),
        }
    }

    /// The node test queries use.
    pub fn node_test(&self) -> NodeTest {
        self.node_test
    }

    /// Whether queries test nodes 8 children wide (AVX2 or AVX-512) rather than with obvhs' SSE test.
    pub fn uses_wide_node_test(&self) -> bool {
        self.node_test != NodeTest::Obvhs
    }

    /// Number of (non-degenerate) triangles referenced by the leaves.
    pub fn primitive_count(&self) -> usize {
        self.triangle_ids.iter().filter(|&&id| id != NO_TRIANGLE).count()
    }

    /// The nearest hit with t in [tmin, tmax] along `origin + t·dir` (dir need not be unit).
    pub fn closest_hit(&self, origin: Vec3, dir: Vec3, tmin: f32, tmax: f32) -> Option<Hit> {
        self.closest_hit_using(self.node_test, origin, dir, tmin, tmax)
    }

    /// [`Self::closest_hit`] with obvhs' own node test (the reference the wide tests must match).
    pub fn closest_hit_scalar(&self, origin: Vec3, dir: Vec3, tmin: f32, tmax: f32) -> Option<Hit> {
        self.closest_hit_using(NodeTest::Obvhs, origin, dir, tmin, tmax)
    }

    /// Every hit along `origin + t·dir` from `tmin` on, nearest first: each the closest hit beyond
    /// the previous one's t + `step` (so a ray through a shared edge may report it once or twice).
    /// What ray-parity and winding-number counts walk (`inward_surface`, `enclosed_surface`).
    pub fn hits_along(&self, origin: Vec3, dir: Vec3, tmin: f32, step: f32) -> impl Iterator<Item = Hit> + '_ {
        let mut tmin = tmin;
        std::iter::from_fn(move || {
            let hit = self.closest_hit(origin, dir, tmin, f32::INFINITY)?;
            tmin = hit.t + step;
            Some(hit)
        })
    }

    /// Whether anything lies on the segment t in [tmin, tmax] (occlusion; stops at the first hit).
    pub fn any_hit(&self, origin: Vec3, dir: Vec3, tmin: f32, tmax: f32) -> bool {
        self.any_hit_using(self.node_test, origin, dir, tmin, tmax)
    }

    /// [`Self::any_hit`] with obvhs' own node test.
    pub fn any_hit_scalar(&self, origin: Vec3, dir: Vec3, tmin: f32, tmax: f32) -> bool {
        self.any_hit_using(NodeTest::Obvhs, origin, dir, tmin, tmax)
    }

    /// [`Self::closest_hit`] with the given node test (a narrower one where the CPU lacks its instructions).
    pub fn closest_hit_using(&self, test: NodeTest, origin: Vec3, dir: Vec3, tmin: f32, tmax: f32) -> Option<Hit> {
        let tree = self.tree.as_ref()?;
        if !(origin.is_finite() && dir.is_finite()) || dir == Vec3::ZERO {
            return None;
        }
        let (o, d) = (Vec3A::from(origin), positive_zeros(dir));
        let (bvh, tris) = match tree {
            Tree::Cwbvh { cwbvh, triangles } => (cwbvh, triangles.as_slice()),
            Tree::Float8(bvh8) => {
                let hit = bvh8.closest(&PreparedRay::new(o, d), tmin, tmax, test != NodeTest::Obvhs);
                return hit.map(|(k, t, b1, b2)| Hit { triangle: self.triangle_ids[k as usize], t, bary: Vec2::new(b1, b2) });
            }
        };
        let best = match test {
            #[cfg(target_arch = "x86_64")]
            NodeTest::Avx512 if test.supported() => {
                #[target_feature(enable = "avx2,avx512f,avx512vl,avx512bw")]
                fn run(tris: &[PackedTriangle], bvh: &CwBvh, o: Vec3A, d: Vec3A, tmin: f32, tmax: f32) -> Option<(u32, f32, f32, f32)> {
                    closest_traversal!(tris, bvh, o, d, tmin, tmax, bvh_wide::intersect_node_avx512)
                }
                // SAFETY: the CPU has AVX-512 F/VL/BW and AVX2 (checked just above).
                unsafe { run(tris, bvh, o, d, tmin, tmax) }
            }
            #[cfg(target_arch = "x86_64")]
            NodeTest::Avx2 | NodeTest::Avx512 if NodeTest::Avx2.supported() => {
                #[target_feature(enable = "avx2")]
                fn run(tris: &[PackedTriangle], bvh: &CwBvh, o: Vec3A, d: Vec3A, tmin: f32, tmax: f32) -> Option<(u32, f32, f32, f32)> {
                    closest_traversal!(tris, bvh, o, d, tmin, tmax, bvh_wide::intersect_node)
                }
                // SAFETY: the CPU has AVX2 (checked just above).
                unsafe { run(tris, bvh, o, d, tmin, tmax) }
            }
            _ => closest_traversal!(tris, bvh, o, d, tmin, tmax, CwBvhNode::intersect_ray),
        };
        best.map(|(k, t, b1, b2)| Hit { triangle: self.triangle_ids[k as usize], t, bary: Vec2::new(b1, b2) })
    }

    /// [`Self::any_hit`] with the given node test (a narrower one where the CPU lacks its instructions).
    pub fn any_hit_using(&self, test: NodeTest, origin: Vec3, dir: Vec3, tmin: f32, tmax: f32) -> bool {
        let Some(tree) = self.tree.as_ref() else { return false };
        if !(origin.is_finite() && dir.is_finite()) || dir == Vec3::ZERO {
            return false;
        }
        let (o, d) = (Vec3A::from(origin), positive_zeros(dir));
        let (bvh, tris) = match tree {
            Tree::Cwbvh { cwbvh, triangles } => (cwbvh, triangles.as_slice()),
            Tree::Float8(bvh8) => return bvh8.any(&PreparedRay::new(o, d), tmin, tmax, test != NodeTest::Obvhs),
        };
        match test {
            #[cfg(target_arch = "x86_64")]
            NodeTest::Avx512 if test.supported() => {
                #[target_feature(enable = "avx2,avx512f,avx512vl,avx512bw")]
                fn run(tris: &[PackedTriangle], bvh: &CwBvh, o: Vec3A, d: Vec3A, tmin: f32, tmax: f32) -> bool {
                    any_traversal!(tris, bvh, o, d, tmin, tmax, bvh_wide::intersect_node_avx512)
                }
                // SAFETY: the CPU has AVX-512 F/VL/BW and AVX2 (checked just above).
                unsafe { run(tris, bvh, o, d, tmin, tmax) }
            }
            #[cfg(target_arch = "x86_64")]
            NodeTest::Avx2 | NodeTest::Avx512 if NodeTest::Avx2.supported() => {
                #[target_feature(enable = "avx2")]
                fn run(tris: &[PackedTriangle], bvh: &CwBvh, o: Vec3A, d: Vec3A, tmin: f32, tmax: f32) -> bool {
                    any_traversal!(tris, bvh, o, d, tmin, tmax, bvh_wide::intersect_node)
                }
                // SAFETY: the CPU has AVX2 (checked just above).
                unsafe { run(tris, bvh, o, d, tmin, tmax) }
            }
            _ => any_traversal!(tris, bvh, o, d, tmin, tmax, CwBvhNode::intersect_ray),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hit_point_reproduces_barycentrics() {
        let p = [Vec3::new(0.0, 0.0, 0.0), Vec3::new(2.0, 0.0, 0.0), Vec3::new(0.0, 3.0, 0.0)];
        let o = Vec3::new(0.5, 0.75, 5.0);
        let (t, b) = intersect_triangle(p, o, -Vec3::Z, 0.0, f32::INFINITY).expect("test setup");
        assert!((t - 5.0).abs() < 1e-6);
        let x = (1.0 - b.x - b.y) * p[0] + b.x * p[1] + b.y * p[2];
        assert!((x - Vec3::new(0.5, 0.75, 0.0)).length() < 1e-6);
        // Outside the t range and outside the triangle.
        assert!(intersect_triangle(p, o, -Vec3::Z, 0.0, 4.9).is_none());
        assert!(intersect_triangle(p, Vec3::new(1.9, 2.9, 5.0), -Vec3::Z, 0.0, 10.0).is_none());
        // Degenerate triangles never hit.
        let line = [Vec3::ZERO, Vec3::X, 2.0 * Vec3::X];
        assert!(intersect_triangle(line, Vec3::new(0.5, 0.0, 1.0), -Vec3::Z, 0.0, 10.0).is_none());
        let point = [Vec3::ONE; 3];
        assert!(intersect_triangle(point, Vec3::new(1.0, 1.0, 3.0), -Vec3::Z, 0.0, 10.0).is_none());
    }

    #[test]
    fn empty_and_all_degenerate_meshes_never_hit() {
        let bvh = Bvh::build(&Mesh::default());
        assert!(bvh.closest_hit(Vec3::ZERO, Vec3::Z, 0.0, 1e9).is_none());
        let mesh = Mesh { positions: vec![Vec3::ZERO, Vec3::X, 2.0 * Vec3::X], triangles: vec![[0, 1, 2], [0, 0, 0]], ..Mesh::default() };
        let bvh = Bvh::build(&mesh);
        assert_eq!(bvh.primitive_count(), 0);
        assert!(!bvh.any_hit(Vec3::new(0.5, 0.0, 1.0), -Vec3::Z, 0.0, 10.0));
    }
}

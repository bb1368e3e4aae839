//! An 8-wide BVH with plain float boxes, collapsed from obvhs' binary BVH, and its traversal.
//!
//! obvhs builds the tree (PLOC, reinsertion, leaf collapse: the same builder as its CWBVH). Its
//! CWBVH stores each child box as quantised bytes, which suits a GPU's bandwidth; on a CPU every
//! node test first turns the bytes back into floats, and the traversal's stack of (node group,
//! hit mask) entries visits a node's children in an order fixed by the ray's octant, not by their
//! distance. Here each node holds its 8 children's boxes as floats, one row of 8 per plane, so an
//! AVX2 node test is six loads, six subtractions and six multiplications, and the stack holds
//! (child, entry distance) pairs: the closest-hit query visits the nearest child first and skips a
//! popped child that starts beyond the nearest hit found since it was pushed.
//!
//! The box test is conservative: the far distance is scaled up by a few ulps (Ize, "Robust BVH
//! ray traversal", 2013), so that rounding can never cull a box a ray touches; zero direction
//! components (+0 after [`super::bvh`]'s sign fix) give ±inf or NaN distances, and the operand order
//! of every max/min makes a NaN lane count as "inside" on that axis. Hits are decided by the same
//! triangle test as every other query, so they are the triangles brute force finds.

use std::mem::MaybeUninit;
use std::time::Duration;

use glam::Vec3A;
use obvhs::bvh2::builder::build_bvh2_from_tris;
use obvhs::triangle::Triangle;
use obvhs::BvhBuildParams;

/// Children per node.
pub const WIDTH: usize = 8;

/// A child slot that holds nothing; its box is empty (min +inf, max −inf), so no ray enters it.
const EMPTY: u32 = u32::MAX;
/// A child reference with this bit set is a leaf: triangles `first .. first + count`.
const LEAF: u32 = 1 << 31;
/// Bits of a leaf reference that hold `count − 1` (leaves have at most 16 triangles).
const LEAF_COUNT_SHIFT: u32 = 27;
/// Blocks (and so, at most, triangles) a leaf reference can index: 134 million.
pub const MAX_TRIANGLES: usize = 1 << LEAF_COUNT_SHIFT;
/// Blocks a leaf reference can count (4 bits of `count − 1`): 64 triangles. obvhs' leaves hold
/// at most 8 with every preset (`max_prims_per_leaf`), i.e. 2 blocks.
const MAX_LEAF_BLOCKS: usize = 16;

/// Scale on a box's far distance that covers the rounding of the slab test: the distances are
/// (plane − origin) · (1/dir), three roundings each of relative size ε = 2⁻²⁴, so their error is
/// below γ(3) = 3ε/(1 − 3ε) ≈ 1.8e-7 relative; 1 + 2γ(3) covers both the near and the far side
/// (Ize 2013). 1e-6 leaves room for the comparison with a hit distance computed by the triangle
/// test, and costs nothing measurable.
const FAR_SCALE: f32 = 1.0 + 1e-6;

/// One node: the children's references and the boxes of 8 children as rows of floats (x min,
/// x max, y min, y max, z min, z max). 224 bytes, aligned to cache lines; the references come
/// first, so they arrive with the first row rather than after the test on a line of their own.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(64))]
pub struct Node8 {
    child: [u32; WIDTH],
    planes: [[f32; WIDTH]; 6],
}

impl Node8 {
    fn empty() -> Node8 {
        let mut planes = [[f32::INFINITY; WIDTH]; 6];
        for axis in 0..3 {
            planes[2 * axis + 1] = [f32::NEG_INFINITY; WIDTH];
        }
        Node8 { child: [EMPTY; WIDTH], planes }
    }
}

/// Up to four triangles of a leaf as one vertex and two edges each, lane by lane
/// (`[axis][lane]`), tested together. Unused lanes hold zero edges: a zero determinant, never a hit.
#[derive(Clone, Copy, Debug, Default)]
#[repr(C, align(16))]
pub struct TriBlock4 {
    v0: [[f32; 4]; 3],
    e1: [[f32; 4]; 3],
    e2: [[f32; 4]; 3],
}

/// Lanes per [`TriBlock4`].
pub const LANES: usize = 4;
/// The triangle of an unused lane.
pub const NO_TRIANGLE: u32 = u32::MAX;

/// The tree. A leaf references consecutive [`TriBlock4`]s; [`Bvh8::lane_triangles`] says which
/// input triangle each lane holds.
pub struct Bvh8 {
    nodes: Vec<Node8>,
    blocks: Vec<TriBlock4>,
    /// Input triangle index of each block lane (`block * LANES + lane`), or [`NO_TRIANGLE`].
    lanes: Vec<u32>,
    /// Stack entries a query can need: 7 per level below the root, plus one.
    stack_need: usize,
}

/// A ray prepared for the node tests: origin, inverse direction and the row offsets of each
/// axis' near and far planes (the max plane is the near one for a negative direction).
#[derive(Clone, Copy)]
pub struct PreparedRay {
    pub origin: Vec3A,
    pub dir: Vec3A,
    inv: Vec3A,
    near_row: [usize; 3],
    far_row: [usize; 3],
}

impl PreparedRay {
    /// `dir` must have no −0.0 component (the sign picks the near plane).
    pub fn new(origin: Vec3A, dir: Vec3A) -> PreparedRay {
        let inv = dir.recip();
        let rows = |neg: bool, axis: usize| if neg { (2 * axis + 1, 2 * axis) } else { (2 * axis, 2 * axis + 1) };
        let (nx, fx) = rows(dir.x < 0.0, 0);
        let (ny, fy) = rows(dir.y < 0.0, 1);
        let (nz, fz) = rows(dir.z < 0.0, 2);
        PreparedRay { origin, dir, inv, near_row: [nx, ny, nz], far_row: [fx, fy, fz] }
    }
}

/// The nearest hit a query found: block lane, t and barycentrics (b1, b2).
pub type LaneHit = (u32, f32, f32, f32);

impl Bvh8 {
    /// Build obvhs' binary tree over `tris` with `params`, then collapse it: each node takes its
    /// BVH2 node's two children, then repeatedly opens the inner child of largest surface area
    /// until it has 8 children or only leaves. Each leaf's triangles go into blocks of four.
    pub fn build(tris: &[Triangle], params: BvhBuildParams) -> Bvh8 {
        let mut bvh = Bvh8 { nodes: Vec::new(), blocks: Vec::new(), lanes: Vec::new(), stack_need: 1 };
        if tris.is_empty() {
            return bvh;
        }
        let params = BvhBuildParams { max_prims_per_leaf: params.max_prims_per_leaf.min((MAX_LEAF_BLOCKS * LANES) as u32), ..params };
        let bvh2 = build_bvh2_from_tris(tris, params, &mut Duration::default());
        bvh.nodes.push(Node8::empty());
        let mut depth = 1;
        // (BVH2 nodes to place in this node, node index, depth)
        let mut work: Vec<(Vec<u32>, usize, usize)> = Vec::new();
        let root = &bvh2.nodes[0];
        let first_children = if root.prim_count > 0 { vec![0] } else { vec![root.first_index, root.first_index + 1] };
        work.push((first_children, 0, 1));
        while let Some((mut children, at, level)) = work.pop() {
            depth = depth.max(level);
            while children.len() < WIDTH {
                let open = children
                    .iter()
                    .enumerate()
                    .filter(|(_, &c)| bvh2.nodes[c as usize].prim_count == 0)
                    .max_by(|a, b| bvh2.nodes[*a.1 as usize].aabb.half_area().total_cmp(&bvh2.nodes[*b.1 as usize].aabb.half_area()))
                    .map(|(k, _)| k);
                let Some(k) = open else { break };
                let first = bvh2.nodes[children[k] as usize].first_index;
                children[k] = first;
                children.push(first + 1);
            }
            for (slot, &c) in children.iter().enumerate() {
                let n = &bvh2.nodes[c as usize];
                let (lo, hi) = (n.aabb.min, n.aabb.max);
                for axis in 0..3 {
                    bvh.nodes[at].planes[2 * axis][slot] = lo[axis];
                    bvh.nodes[at].planes[2 * axis + 1][slot] = hi[axis];
                }
                bvh.nodes[at].child[slot] = if n.prim_count > 0 {
                    let prims = &bvh2.primitive_indices[n.first_index as usize..(n.first_index + n.prim_count) as usize];
                    bvh.push_leaf(tris, prims)
                } else {
                    let index = bvh.nodes.len();
                    bvh.nodes.push(Node8::empty());
                    work.push((vec![n.first_index, n.first_index + 1], index, level + 1));
                    index as u32
                };
            }
        }
        bvh.stack_need = (WIDTH - 1) * depth + 1;
        bvh
    }

    /// Store a leaf's triangles as blocks; returns the leaf's child reference (`build` caps
    /// leaves at [`MAX_LEAF_BLOCKS`] blocks).
    fn push_leaf(&mut self, tris: &[Triangle], prims: &[u32]) -> u32 {
        let first = self.blocks.len() as u32;
        for chunk in prims.chunks(LANES) {
            let mut block = TriBlock4::default();
            for (lane, &p) in chunk.iter().enumerate() {
                let t = &tris[p as usize];
                let (e1, e2) = (t.v1 - t.v0, t.v2 - t.v0);
                for axis in 0..3 {
                    block.v0[axis][lane] = t.v0[axis];
                    block.e1[axis][lane] = e1[axis];
                    block.e2[axis][lane] = e2[axis];
                }
            }
            self.blocks.push(block);
            self.lanes.extend((0..LANES).map(|lane| chunk.get(lane).copied().unwrap_or(NO_TRIANGLE)));
        }
        let count = self.blocks.len() as u32 - first;
        LEAF | ((count - 1) << LEAF_COUNT_SHIFT) | first
    }

    /// The input triangle of each block lane, or [`NO_TRIANGLE`].
    pub fn lane_triangles(&self) -> &[u32] {
        &self.lanes
    }

    pub fn node_count(&self) -> usize {
        self.nodes.len()
    }

    /// Bytes of nodes and triangle blocks (what traversal reads), and the share of block lanes
    /// that hold a triangle.
    pub fn footprint(&self) -> (usize, f32) {
        let used = self.lanes.iter().filter(|&&l| l != NO_TRIANGLE).count();
        (self.nodes.len() * std::mem::size_of::<Node8>() + self.blocks.len() * std::mem::size_of::<TriBlock4>(), used as f32 / self.lanes.len().max(1) as f32)
    }

    /// The nearest hit with t in [tmin, tmax]. `avx2`: use the AVX2 node test where the CPU has
    /// it (else the scalar one, which gives the same masks).
    pub fn closest(&self, ray: &PreparedRay, tmin: f32, tmax: f32, avx2: bool) -> Option<LaneHit> {
        let mut best = None;
        self.dispatch::<true>(ray, tmin, tmax, avx2, &mut best);
        best
    }

    /// Whether anything lies on the segment t in [tmin, tmax]; stops at the first hit.
    pub fn any(&self, ray: &PreparedRay, tmin: f32, tmax: f32, avx2: bool) -> bool {
        self.dispatch::<false>(ray, tmin, tmax, avx2, &mut None)
    }

    /// [`Self::walk`] compiled for AVX2 where asked for and available, else the portable one.
    #[inline(always)]
    fn dispatch<const CLOSEST: bool>(&self, ray: &PreparedRay, tmin: f32, tmax: f32, avx2: bool, best: &mut Option<LaneHit>) -> bool {
        #[cfg(target_arch = "x86_64")]
        if avx2 && avx2_available() {
            #[target_feature(enable = "avx2")]
            fn run<const CLOSEST: bool>(bvh: &Bvh8, ray: &PreparedRay, tmin: f32, tmax: f32, best: &mut Option<LaneHit>) -> bool {
                bvh.walk::<CLOSEST, true>(ray, tmin, tmax, best)
            }
            // SAFETY: the CPU has AVX2 (checked just above).
            return unsafe { run::<CLOSEST>(self, ray, tmin, tmax, best) };
        }
        let _ = avx2;
        self.walk::<CLOSEST, false>(ray, tmin, tmax, best)
    }

    /// The traversal. `CLOSEST`: visit children nearest first, shrink the far limit to each hit
    /// and keep the nearest in `best`; otherwise stop at the first hit and return true. `AVX2`:
    /// the node test; `true` only from code compiled for AVX2 on a CPU that has it.
    #[inline(always)]
    fn walk<const CLOSEST: bool, const AVX2: bool>(&self, ray: &PreparedRay, tmin: f32, tmax: f32, best: &mut Option<LaneHit>) -> bool {
        if self.nodes.is_empty() {
            return false;
        }
        // The stack lives on the call stack when the tree is shallow enough (27 levels of 8-wide
        // nodes), and is left uninitialised: zeroing its 1.5 kB cost 5–10 % of an incoherent
        // query (`bench_rays`, 2026-12-06).
        const LOCAL: usize = 192;
        let mut local = [const { MaybeUninit::<(u32, f32)>::uninit() }; LOCAL];
        let mut heap = Vec::new();
        let stack: &mut [MaybeUninit<(u32, f32)>] = if self.stack_need <= LOCAL {
            &mut local
        } else {
            heap.resize(self.stack_need, MaybeUninit::uninit());
            &mut heap
        };
        let mut sp = 0usize;
        let mut far_limit = tmax;
        let mut current = 0u32;
        loop {
            // `current` is an inner node entered at a distance below `far_limit`.
            let node = &self.nodes[current as usize];
            let (mask, near) = node_test::<AVX2>(node, ray, tmin, far_limit);
            let mut bits = mask;
            let base = sp;
            while bits != 0 {
                let slot = bits.trailing_zeros() as usize;
                bits &= bits - 1;
                let child = node.child[slot];
                if child & LEAF != 0 {
                    if !CLOSEST || near[slot] <= far_limit {
                        let first = (child & (MAX_TRIANGLES as u32 - 1)) as usize;
                        let count = ((child & !LEAF) >> LEAF_COUNT_SHIFT) as usize + 1;
                        for b in first..first + count {
                            let (hits, t, b1, b2) = block_test(&self.blocks[b], ray, tmin, far_limit);
                            if hits == 0 {
                                continue;
                            }
                            if !CLOSEST {
                                return true;
                            }
                            // The nearest lane (the last of equal ones, as a triangle-by-triangle loop keeps).
                            let mut lane = hits.trailing_zeros() as usize;
                            for l in lane + 1..LANES {
                                if hits & (1 << l) != 0 && t[l] <= t[lane] {
                                    lane = l;
                                }
                            }
                            far_limit = t[lane];
                            *best = Some(((b * LANES + lane) as u32, t[lane], b1[lane], b2[lane]));
                        }
                    }
                } else {
                    stack[sp].write((child, near[slot]));
                    sp += 1;
                }
            }
            if CLOSEST && sp - base > 1 {
                // Nearest on top: insertion sort of the few entries just pushed, farthest first.
                // SAFETY (the reads below): entries below `sp` were written.
                for i in base + 1..sp {
                    let e = unsafe { stack[i].assume_init() };
                    let mut j = i;
                    while j > base && unsafe { stack[j - 1].assume_init() }.1 < e.1 {
                        stack[j] = stack[j - 1];
                        j -= 1;
                    }
                    stack[j].write(e);
                }
            }
            // Next node: the top of the stack that still starts before the nearest hit.
            loop {
                if sp == 0 {
                    return false;
                }
                sp -= 1;
                // SAFETY: entries below the old `sp` were written.
                let (child, entry) = unsafe { stack[sp].assume_init() };
                if !CLOSEST || entry <= far_limit {
                    current = child;
                    break;
                }
            }
        }
    }
}

/// The four triangles of a block against a ray: the hit mask (lane bits) and each lane's t, b1
/// and b2. The arithmetic is `bvh::intersect_triangle`'s Möller–Trumbore test lane by lane, in the
/// same order and with the same fused or unfused steps as glam's `cross` and `dot` on this
/// target, so each lane gives that test's bits.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn block_test(b: &TriBlock4, ray: &PreparedRay, tmin: f32, tmax: f32) -> (u32, [f32; LANES], [f32; LANES], [f32; LANES]) {
    use std::arch::x86_64::*;
    // SAFETY: SSE2 is part of x86_64; the loads read the block's own 16-byte aligned rows.
    unsafe {
        let ld = |row: &[f32; 4]| _mm_load_ps(row.as_ptr());
        // c − a·b, fused where glam fuses it (its `cross`).
        #[inline(always)]
        unsafe fn nms(a: __m128, b: __m128, c: __m128) -> __m128 {
            #[cfg(target_feature = "fma")]
            {
                _mm_fnmadd_ps(a, b, c)
            }
            #[cfg(not(target_feature = "fma"))]
            {
                _mm_sub_ps(c, _mm_mul_ps(a, b))
            }
        }
        // (a × b) as glam computes it: x = a.y·b.z − b.y·a.z, and cyclically.
        let cross = |a: [__m128; 3], b: [__m128; 3]| {
            [
                nms(b[1], a[2], _mm_mul_ps(a[1], b[2])),
                nms(b[2], a[0], _mm_mul_ps(a[2], b[0])),
                nms(b[0], a[1], _mm_mul_ps(a[0], b[1])),
            ]
        };
        // (a.x·b.x + a.y·b.y) + a.z·b.z, glam's `dot` order.
        let dot = |a: [__m128; 3], b: [__m128; 3]| _mm_add_ps(_mm_add_ps(_mm_mul_ps(a[0], b[0]), _mm_mul_ps(a[1], b[1])), _mm_mul_ps(a[2], b[2]));
        let d = [_mm_set1_ps(ray.dir.x), _mm_set1_ps(ray.dir.y), _mm_set1_ps(ray.dir.z)];
        let e1 = [ld(&b.e1[0]), ld(&b.e1[1]), ld(&b.e1[2])];
        let e2 = [ld(&b.e2[0]), ld(&b.e2[1]), ld(&b.e2[2])];
        let p = cross(d, e2);
        let det = dot(e1, p);
        let zero = _mm_setzero_ps();
        let one = _mm_set1_ps(1.0);
        // det ≠ 0 and not NaN.
        let mut ok = _mm_and_ps(_mm_cmpord_ps(det, det), _mm_cmpneq_ps(det, zero));
        let inv = _mm_div_ps(one, det);
        let s = [
            _mm_sub_ps(_mm_set1_ps(ray.origin.x), ld(&b.v0[0])),
            _mm_sub_ps(_mm_set1_ps(ray.origin.y), ld(&b.v0[1])),
            _mm_sub_ps(_mm_set1_ps(ray.origin.z), ld(&b.v0[2])),
        ];
        let b1 = _mm_mul_ps(dot(s, p), inv);
        ok = _mm_and_ps(ok, _mm_and_ps(_mm_cmpge_ps(b1, zero), _mm_cmple_ps(b1, one)));
        let q = cross(s, e1);
        let b2 = _mm_mul_ps(dot(d, q), inv);
        ok = _mm_and_ps(ok, _mm_and_ps(_mm_cmpge_ps(b2, zero), _mm_cmple_ps(_mm_add_ps(b1, b2), one)));
        let t = _mm_mul_ps(dot(e2, q), inv);
        let finite = _mm_cmplt_ps(_mm_andnot_ps(_mm_set1_ps(-0.0), t), _mm_set1_ps(f32::INFINITY));
        ok = _mm_and_ps(ok, _mm_and_ps(finite, _mm_and_ps(_mm_cmpge_ps(t, _mm_set1_ps(tmin)), _mm_cmple_ps(t, _mm_set1_ps(tmax)))));
        let mask = _mm_movemask_ps(ok) as u32;
        let (mut to, mut b1o, mut b2o) = ([0.0; LANES], [0.0; LANES], [0.0; LANES]);
        if mask != 0 {
            _mm_storeu_ps(to.as_mut_ptr(), t);
            _mm_storeu_ps(b1o.as_mut_ptr(), b1);
            _mm_storeu_ps(b2o.as_mut_ptr(), b2);
        }
        (mask, to, b1o, b2o)
    }
}

/// [`block_test`] one lane at a time, off x86_64.
#[cfg(not(target_arch = "x86_64"))]
fn block_test(b: &TriBlock4, ray: &PreparedRay, tmin: f32, tmax: f32) -> (u32, [f32; LANES], [f32; LANES], [f32; LANES]) {
    let (mut mask, mut to, mut b1o, mut b2o) = (0, [0.0; LANES], [0.0; LANES], [0.0; LANES]);
    for lane in 0..LANES {
        let v = |rows: &[[f32; 4]; 3]| Vec3A::new(rows[0][lane], rows[1][lane], rows[2][lane]);
        let (v0, e1, e2) = (v(&b.v0), v(&b.e1), v(&b.e2));
        let p = ray.dir.cross(e2);
        let det = e1.dot(p);
        if det == 0.0 || det.is_nan() {
            continue;
        }
        let inv = 1.0 / det;
        let s = ray.origin - v0;
        let b1 = s.dot(p) * inv;
        let q = s.cross(e1);
        let b2 = ray.dir.dot(q) * inv;
        let t = e2.dot(q) * inv;
        if (0.0..=1.0).contains(&b1) && b2 >= 0.0 && b1 + b2 <= 1.0 && t >= tmin && t <= tmax && t.is_finite() {
            mask |= 1 << lane;
            (to[lane], b1o[lane], b2o[lane]) = (t, b1, b2);
        }
    }
    (mask, to, b1o, b2o)
}

/// The hit mask of a node's 8 children and their entry distances.
#[inline(always)]
fn node_test<const AVX2: bool>(node: &Node8, ray: &PreparedRay, tmin: f32, tmax: f32) -> (u32, [f32; WIDTH]) {
    #[cfg(target_arch = "x86_64")]
    {
        if AVX2 {
            // SAFETY: `walk`'s contract: with AVX2 = true the CPU has AVX2.
            return unsafe { node_test_avx2(node, ray, tmin, tmax) };
        }
    }
    node_test_scalar(node, ray, tmin, tmax)
}

/// Whether the CPU has AVX2 (std caches the detection).
pub fn avx2_available() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// The node test one child at a time, with the AVX2 test's arithmetic and NaN handling.
fn node_test_scalar(node: &Node8, ray: &PreparedRay, tmin: f32, tmax: f32) -> (u32, [f32; WIDTH]) {
    let mut mask = 0;
    let mut near_out = [0.0; WIDTH];
    let (o, inv) = (ray.origin, ray.inv);
    for (c, near_c) in near_out.iter_mut().enumerate() {
        let d = |row: usize, axis: usize| (node.planes[row][c] - o[axis]) * inv[axis];
        // `maxf(a, b)` returns b when either is NaN, as `_mm256_max_ps` does.
        let maxf = |a: f32, b: f32| if a > b { a } else { b };
        let minf = |a: f32, b: f32| if a < b { a } else { b };
        let near = maxf(d(ray.near_row[0], 0), maxf(d(ray.near_row[1], 1), maxf(d(ray.near_row[2], 2), tmin)));
        let far = minf(d(ray.far_row[0], 0), minf(d(ray.far_row[1], 1), minf(d(ray.far_row[2], 2), tmax))) * FAR_SCALE;
        if near <= far {
            mask |= 1 << c;
        }
        *near_c = near;
    }
    (mask, near_out)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn node_test_avx2(node: &Node8, ray: &PreparedRay, tmin: f32, tmax: f32) -> (u32, [f32; WIDTH]) {
    use std::arch::x86_64::*;
    let rows = node.planes.as_ptr() as *const f32;
    macro_rules! dist {
        ($row:expr, $o:expr, $inv:expr) => {{
            // SAFETY: `$row` < 6 and each row holds 8 floats; the node is 64-byte aligned, rows 32.
            let plane = unsafe { _mm256_load_ps(rows.add($row * WIDTH)) };
            _mm256_mul_ps(_mm256_sub_ps(plane, $o), $inv)
        }};
    }
    let (ox, oy, oz) = (_mm256_set1_ps(ray.origin.x), _mm256_set1_ps(ray.origin.y), _mm256_set1_ps(ray.origin.z));
    let (ix, iy, iz) = (_mm256_set1_ps(ray.inv.x), _mm256_set1_ps(ray.inv.y), _mm256_set1_ps(ray.inv.z));
    // NaN (a zero direction component on a plane through the origin) must lose every max/min:
    // `_mm256_max_ps(a, b)` returns b when either is NaN, so the axis terms go first.
    let near = _mm256_max_ps(
        dist!(ray.near_row[0], ox, ix),
        _mm256_max_ps(dist!(ray.near_row[1], oy, iy), _mm256_max_ps(dist!(ray.near_row[2], oz, iz), _mm256_set1_ps(tmin))),
    );
    let far = _mm256_min_ps(
        dist!(ray.far_row[0], ox, ix),
        _mm256_min_ps(dist!(ray.far_row[1], oy, iy), _mm256_min_ps(dist!(ray.far_row[2], oz, iz), _mm256_set1_ps(tmax))),
    );
    let far = _mm256_mul_ps(far, _mm256_set1_ps(FAR_SCALE));
    let mask = _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_LE_OQ>(near, far)) as u32;
    let mut out = [0.0f32; WIDTH];
    // SAFETY: `out` holds 8 floats.
    unsafe { _mm256_storeu_ps(out.as_mut_ptr(), near) };
    (mask, out)
}

/// The box of a node's child slot, for tests.
#[cfg(test)]
fn child_box(node: &Node8, slot: usize) -> (glam::Vec3, glam::Vec3) {
    let p = |r: usize| node.planes[r][slot];
    (glam::Vec3::new(p(0), p(2), p(4)), glam::Vec3::new(p(1), p(3), p(5)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;
    use rand::{Rng, SeedableRng};
    use rand_pcg::Pcg64;

    fn soup(n: usize, seed: u64) -> Vec<Triangle> {
        let mut rng = Pcg64::seed_from_u64(seed);
        (0..n)
            .map(|_| {
                let c = Vec3A::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0));
                let mut r = || Vec3A::new(rng.random_range(-0.1..0.1), rng.random_range(-0.1..0.1), rng.random_range(-0.1..0.1));
                Triangle { v0: c, v1: c + r(), v2: c + r() }
            })
            .collect()
    }

    /// Every triangle sits in exactly one block lane, inside the boxes above it, and each block
    /// lane gives the single-triangle test's answer.
    #[test]
    fn collapse_keeps_every_triangle_once_inside_its_boxes() {
        for n in [1usize, 2, 9, 1000] {
            let tris = soup(n, n as u64);
            let bvh = Bvh8::build(&tris, BvhBuildParams::medium_build());
            let mut seen = vec![0usize; n];
            let mut stack = vec![(0u32, Vec3::splat(f32::NEG_INFINITY), Vec3::splat(f32::INFINITY))];
            while let Some((at, lo, hi)) = stack.pop() {
                let node = &bvh.nodes[at as usize];
                for slot in 0..WIDTH {
                    let c = node.child[slot];
                    if c == EMPTY {
                        continue;
                    }
                    let (clo, chi) = child_box(node, slot);
                    assert!(clo.cmpge(lo).all() && chi.cmple(hi).all(), "child box outside its parent's");
                    if c & LEAF != 0 {
                        let first = (c & (MAX_TRIANGLES as u32 - 1)) as usize;
                        let count = ((c & !LEAF) >> LEAF_COUNT_SHIFT) as usize + 1;
                        for lane in first * LANES..(first + count) * LANES {
                            let id = bvh.lanes[lane];
                            if id == NO_TRIANGLE {
                                continue;
                            }
                            let t = &tris[id as usize];
                            for v in [t.v0, t.v1, t.v2] {
                                assert!(Vec3::from(v).cmpge(clo).all() && Vec3::from(v).cmple(chi).all(), "triangle outside its leaf's box");
                            }
                            seen[id as usize] += 1;
                        }
                    } else {
                        stack.push((c, clo, chi));
                    }
                }
            }
            assert!(seen.iter().all(|&s| s == 1), "n = {n}: triangles seen {seen:?}");
        }
    }

    /// A block's lanes give `intersect_triangle`'s answers bit for bit, hits and misses, on rays
    /// aimed at the triangles, beside them, along their edges and with zero components; unused
    /// lanes never hit.
    #[test]
    fn block_lanes_equal_the_single_triangle_test() {
        let tris = soup(401, 11);
        let mut rng = Pcg64::seed_from_u64(12);
        let mut hits = 0;
        for chunk in tris.chunks(LANES) {
            let mut bvh = Bvh8 { nodes: Vec::new(), blocks: Vec::new(), lanes: Vec::new(), stack_need: 1 };
            let ids: Vec<u32> = (0..chunk.len() as u32).collect();
            bvh.push_leaf(chunk, &ids);
            let block = &bvh.blocks[0];
            for k in 0..40 {
                let target = &chunk[k % chunk.len()];
                let (w1, w2): (f32, f32) = (rng.random_range(-0.2..1.0), rng.random_range(-0.2..1.0));
                let aim = target.v0 + w1 * (target.v1 - target.v0) + w2 * (target.v2 - target.v0);
                let origin = Vec3A::new(rng.random_range(-3.0..3.0), rng.random_range(-3.0..3.0), rng.random_range(-3.0..3.0));
                let mut dir = aim - origin;
                match k % 10 {
                    1 => dir.x = 0.0,
                    2 => dir = target.v1 - target.v0,
                    _ => {}
                }
                let origin = if k % 10 == 2 { target.v0 - 0.5 * dir } else { origin };
                let tmax = if k % 3 == 0 { rng.random_range(0.0..3.0) } else { f32::INFINITY };
                let (mask, t, b1, b2) = block_test(block, &PreparedRay::new(origin, dir), 1e-4, tmax);
                for lane in 0..LANES {
                    let want = chunk.get(lane).and_then(|tri| {
                        crate::geometry::bvh::intersect_triangle([tri.v0.into(), tri.v1.into(), tri.v2.into()], origin.into(), dir.into(), 1e-4, tmax)
                    });
                    match want {
                        None => assert_eq!(mask & (1 << lane), 0, "lane {lane} hit where the single test misses"),
                        Some((wt, wb)) => {
                            hits += 1;
                            assert!(mask & (1 << lane) != 0, "lane {lane} missed where the single test hits");
                            assert_eq!((t[lane].to_bits(), b1[lane].to_bits(), b2[lane].to_bits()), (wt.to_bits(), wb.x.to_bits(), wb.y.to_bits()));
                        }
                    }
                }
            }
        }
        assert!(hits > 1000, "only {hits} hits");
    }

    /// The AVX2 and scalar node tests agree, mask and distances, on random boxes and rays with
    /// zero components, and the test never culls a box whose interior the ray passes through.
    #[test]
    fn node_tests_agree_and_are_conservative() {
        let mut rng = Pcg64::seed_from_u64(3);
        for k in 0..20_000 {
            let mut node = Node8::empty();
            let filled = rng.random_range(1..=WIDTH);
            for slot in 0..filled {
                for axis in 0..3 {
                    let (a, b): (f32, f32) = (rng.random_range(-2.0..2.0), rng.random_range(-2.0..2.0));
                    // Some flat boxes (a triangle lying in an axis plane).
                    let (lo, hi) = if k % 7 == 0 && axis == 2 { (a, a) } else { (a.min(b), a.max(b)) };
                    node.planes[2 * axis][slot] = lo;
                    node.planes[2 * axis + 1][slot] = hi;
                }
                node.child[slot] = slot as u32;
            }
            let mut comp = || match rng.random_range(0..8) {
                0 => 0.0,
                _ => rng.random_range(-1.0f32..1.0),
            };
            let dir = Vec3A::new(comp(), comp(), comp());
            if dir == Vec3A::ZERO {
                continue;
            }
            let origin = Vec3A::new(rng.random_range(-3.0..3.0), rng.random_range(-3.0..3.0), rng.random_range(-3.0..3.0));
            let ray = PreparedRay::new(origin, dir);
            let tmax = if k % 3 == 0 { f32::INFINITY } else { rng.random_range(0.0..6.0) };
            let (mask, near) = node_test_scalar(&node, &ray, 0.0, tmax);
            #[cfg(target_arch = "x86_64")]
            if avx2_available() {
                // SAFETY: AVX2 is available (checked just above).
                let (wide_mask, wide_near) = unsafe { node_test_avx2(&node, &ray, 0.0, tmax) };
                assert_eq!(wide_mask, mask);
                for c in 0..WIDTH {
                    assert!(wide_near[c].to_bits() == near[c].to_bits() || (wide_near[c].is_nan() && near[c].is_nan()));
                }
            }
            // A box the ray meets, by an interval computed in f64, must never be culled.
            for slot in 0..filled {
                let (lo, hi) = child_box(&node, slot);
                let (mut enter, mut leave) = (0.0f64, tmax as f64);
                for axis in 0..3 {
                    let (o, d) = (origin[axis] as f64, dir[axis] as f64);
                    let (l, h) = (lo[axis] as f64, hi[axis] as f64);
                    if d == 0.0 {
                        if o < l || o > h {
                            leave = -1.0;
                        }
                    } else {
                        let (a, b) = ((l - o) / d, (h - o) / d);
                        enter = enter.max(a.min(b));
                        leave = leave.min(a.max(b));
                    }
                }
                if enter <= leave {
                    assert!(mask & (1 << slot) != 0, "box {slot} culled though the ray meets it over [{enter}, {leave}]");
                }
            }
            // Empty slots never hit.
            assert_eq!(mask >> filled, 0);
        }
    }
}

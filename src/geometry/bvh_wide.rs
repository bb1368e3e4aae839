//! The CWBVH node test on 8 children at once (AVX2 or AVX-512), for the compressed layout of
//! [`super::bvh::Bvh`] (the reference layout; the default is [`super::bvh8`]).
//!
//! obvhs tests a compressed wide node's 8 child boxes 4 at a time with SSE, converting each
//! quantised plane byte to f32 one by one. With AVX2 the 8 bytes of a plane row become 8 floats in
//! two instructions (zero-extend, convert) and the slab test runs on all 8 children in one pass.
//! With AVX-512 one 16-byte load takes an axis' min and max rows together (they are adjacent in
//! the node), a byte shuffle puts the near row first for a negative direction, and one 16-lane
//! convert, multiply and add give the near and far distances of all 8 children on that axis. Both
//! gather the hit children's bits into the hit mask with a (masked) variable shift and an OR
//! across lanes instead of a loop over the hit children (3–7 % faster on incoherent rays).
//!
//! The arithmetic is obvhs' own, in the same order (plane · (extent/dir) + (p − origin)/dir by a
//! multiply then an add, no FMA; max/min with the same operand order, so NaN lanes resolve the
//! same way; the same tmin floor), so the hit mask is bit for bit the one `intersect_ray` returns
//! and the traversal visits the same nodes and reports the same hits. [`NodeTest::detect`] picks
//! the test at run time: AVX2 where the CPU has it (the AVX-512 test measured slower, see there),
//! obvhs' SSE test elsewhere.

use glam::Vec3A;
use obvhs::cwbvh::node::CwBvhNode;
use obvhs::ray::Ray;

/// obvhs' node test floors a child's entry distance at this (its `EPSILON`, not exported); the
/// wide test must use the same floor to cull exactly the same boxes.
const NODE_TMIN: f32 = 0.0001;

/// Which node test a traversal uses. All give the same hit masks.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum NodeTest {
    /// obvhs' own test (SSE, 4 children at a time; its scalar loop off x86).
    Obvhs,
    /// [`intersect_node`]: 8 children at once with AVX2.
    Avx2,
    /// [`intersect_node_avx512`]: both planes of an axis in one 16-lane register (AVX-512 F/VL/BW).
    Avx512,
}

impl NodeTest {
    /// The test `Bvh` uses by default: AVX2 where the CPU has it, else obvhs'. Not AVX-512 even
    /// where the CPU has it: on the Xeon (AVX-512) this was measured on, the AVX-512 test traced
    /// incoherent rays about 7 % slower than the AVX2 one (`bench_rays`, docs/performance.md): a
    /// node test is on the traversal's critical path, and the 16-lane version's single chain of
    /// convert, multiply, add, min/max and extract is longer than the AVX2 version's two
    /// independent 8-lane chains.
    pub fn detect() -> NodeTest {
        if NodeTest::Avx2.supported() {
            NodeTest::Avx2
        } else {
            NodeTest::Obvhs
        }
    }

    /// Whether the running CPU can run this test.
    pub fn supported(self) -> bool {
        #[cfg(target_arch = "x86_64")]
        {
            use std::arch::is_x86_feature_detected as has;
            match self {
                NodeTest::Obvhs => true,
                NodeTest::Avx2 => has!("avx2"),
                NodeTest::Avx512 => has!("avx2") && has!("avx512f") && has!("avx512vl") && has!("avx512bw"),
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            self == NodeTest::Obvhs
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            NodeTest::Obvhs => "obvhs SSE",
            NodeTest::Avx2 => "AVX2 8-wide",
            NodeTest::Avx512 => "AVX-512 16-lane",
        }
    }
}

/// The hit mask of `node`'s children for `ray` (the layout of obvhs' `CwBvhNode::intersect_ray`:
/// inner children's traversal bits in the top byte, leaf primitives' bits in the low 24).
///
/// # Safety
/// Call only where [`NodeTest::Avx2`] is supported (the CPU must have AVX2).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
pub fn intersect_node(node: &CwBvhNode, ray: &Ray, oct_inv4: u32) -> u32 {
    use std::arch::x86_64::*;
    let dir_inv = node.compute_extent() * ray.inv_direction;
    let orig = (Vec3A::from(node.p) - ray.origin) * ray.inv_direction;
    // 8 plane bytes → 8 floats.
    macro_rules! planes {
        ($bytes:expr) => {{
            // SAFETY: reads exactly the 8 bytes of the array (an unaligned 64-bit load).
            let b = unsafe { _mm_loadl_epi64($bytes.as_ptr() as *const __m128i) };
            _mm256_cvtepi32_ps(_mm256_cvtepu8_epi32(b))
        }};
    }
    // Near and far distances along one axis: the near plane is the max plane for a negative direction.
    macro_rules! slab {
        ($lo:expr, $hi:expr, $neg:expr, $inv:expr, $orig:expr) => {{
            let (near, far) = if $neg { (&$hi, &$lo) } else { (&$lo, &$hi) };
            let (inv, o) = (_mm256_set1_ps($inv), _mm256_set1_ps($orig));
            (_mm256_add_ps(_mm256_mul_ps(planes!(near), inv), o), _mm256_add_ps(_mm256_mul_ps(planes!(far), inv), o))
        }};
    }
    let d = ray.direction;
    let (tmin_x, tmax_x) = slab!(node.child_min_x, node.child_max_x, d.x < 0.0, dir_inv.x, orig.x);
    let (tmin_y, tmax_y) = slab!(node.child_min_y, node.child_max_y, d.y < 0.0, dir_inv.y, orig.y);
    let (tmin_z, tmax_z) = slab!(node.child_min_z, node.child_max_z, d.z < 0.0, dir_inv.z, orig.z);
    let tmin = _mm256_max_ps(_mm256_max_ps(tmin_x, _mm256_max_ps(tmin_y, tmin_z)), _mm256_set1_ps(NODE_TMIN));
    let tmax = _mm256_min_ps(_mm256_min_ps(tmax_x, _mm256_min_ps(tmax_y, tmax_z)), _mm256_set1_ps(ray.tmax));
    let hits = _mm256_castps_si256(_mm256_cmp_ps::<_CMP_LE_OQ>(tmin, tmax));
    // Each hit child contributes its bits shifted to its index (a masked variable shift, no loop).
    let (child_bits8, bit_index8) = node.get_child_and_index_bits(oct_inv4);
    let bits = _mm256_cvtepu8_epi32(_mm_cvtsi64_si128(child_bits8 as i64));
    let index = _mm256_cvtepu8_epi32(_mm_cvtsi64_si128(bit_index8 as i64));
    or_lanes(_mm256_and_si256(_mm256_sllv_epi32(bits, index), hits))
}

/// [`intersect_node`] with AVX-512: the same hit mask, from half the conversions and arithmetic.
///
/// # Safety
/// Call only where [`NodeTest::Avx512`] is supported.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,avx512f,avx512vl,avx512bw")]
#[inline]
pub fn intersect_node_avx512(node: &CwBvhNode, ray: &Ray, oct_inv4: u32) -> u32 {
    use std::arch::x86_64::*;
    let dir_inv = node.compute_extent() * ray.inv_direction;
    let orig = (Vec3A::from(node.p) - ray.origin) * ray.inv_direction;
    // Swaps the two 8-byte rows of a 16-byte load, so the max plane comes first.
    let swap = _mm_set_epi8(7, 6, 5, 4, 3, 2, 1, 0, 15, 14, 13, 12, 11, 10, 9, 8);
    let identity = _mm_set_epi8(15, 14, 13, 12, 11, 10, 9, 8, 7, 6, 5, 4, 3, 2, 1, 0);
    // Lanes 0..8: near distances of the 8 children on one axis; lanes 8..16: far distances.
    macro_rules! axis {
        ($min_row:expr, $neg:expr, $inv:expr, $orig:expr) => {{
            // SAFETY: the min row and the max row right after it are 16 bytes of the node
            // (`CwBvhNode` is repr(C) with `child_max_*` following `child_min_*`).
            let rows = unsafe { _mm_loadu_si128($min_row.as_ptr() as *const __m128i) };
            let rows = _mm_shuffle_epi8(rows, if $neg { swap } else { identity });
            let planes = _mm512_cvtepi32_ps(_mm512_cvtepu8_epi32(rows));
            _mm512_add_ps(_mm512_mul_ps(planes, _mm512_set1_ps($inv)), _mm512_set1_ps($orig))
        }};
    }
    let d = ray.direction;
    let tx = axis!(node.child_min_x, d.x < 0.0, dir_inv.x, orig.x);
    let ty = axis!(node.child_min_y, d.y < 0.0, dir_inv.y, orig.y);
    let tz = axis!(node.child_min_z, d.z < 0.0, dir_inv.z, orig.z);
    // max over the near halves and min over the far halves, in obvhs' operand order.
    let near = _mm512_castps512_ps256(_mm512_max_ps(tx, _mm512_max_ps(ty, tz)));
    let far = _mm256_castpd_ps(_mm512_extractf64x4_pd::<1>(_mm512_castps_pd(_mm512_min_ps(tx, _mm512_min_ps(ty, tz)))));
    let tmin = _mm256_max_ps(near, _mm256_set1_ps(NODE_TMIN));
    let tmax = _mm256_min_ps(far, _mm256_set1_ps(ray.tmax));
    let hits = _mm256_cmp_ps_mask::<_CMP_LE_OQ>(tmin, tmax);
    let (child_bits8, bit_index8) = node.get_child_and_index_bits(oct_inv4);
    let bits = _mm256_cvtepu8_epi32(_mm_cvtsi64_si128(child_bits8 as i64));
    let index = _mm256_cvtepu8_epi32(_mm_cvtsi64_si128(bit_index8 as i64));
    or_lanes(_mm256_maskz_sllv_epi32(hits, bits, index))
}

/// The OR of a vector's 8 u32 lanes.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
fn or_lanes(v: std::arch::x86_64::__m256i) -> u32 {
    use std::arch::x86_64::*;
    let x = _mm_or_si128(_mm256_castsi256_si128(v), _mm256_extracti128_si256::<1>(v));
    let x = _mm_or_si128(x, _mm_shuffle_epi32::<0b01_00_11_10>(x));
    let x = _mm_or_si128(x, _mm_shuffle_epi32::<0b10_11_00_01>(x));
    _mm_cvtsi128_si32(x) as u32
}

#[cfg(all(test, target_arch = "x86_64"))]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_pcg::Pcg64;

    /// Random nodes (random planes, metadata, exponents) against random rays, including zero and
    /// −0.0 direction components: the masks of the AVX2 and (where the CPU has it) AVX-512 tests
    /// equal obvhs' own test bit for bit.
    #[test]
    fn mask_equals_obvhs_node_test() {
        if !NodeTest::Avx2.supported() {
            eprintln!("no AVX2 on this CPU: the wide node test is never used here");
            return;
        }
        let mut rng = Pcg64::seed_from_u64(7);
        for k in 0..20_000 {
            // The rng draws happen in field order: p, e, imask.
            let mut node = CwBvhNode {
                p: glam::Vec3::new(rng.random_range(-2.0..2.0), rng.random_range(-2.0..2.0), rng.random_range(-2.0..2.0)),
                e: [0u8; 3].map(|_| rng.random_range(115..130)),
                imask: rng.random(),
                ..CwBvhNode::default()
            };
            for c in 0..8 {
                node.child_meta[c] = rng.random();
                for (lo, hi) in [(&mut node.child_min_x, &mut node.child_max_x), (&mut node.child_min_y, &mut node.child_max_y), (&mut node.child_min_z, &mut node.child_max_z)] {
                    let (a, b): (u8, u8) = (rng.random(), rng.random());
                    // Mostly proper boxes, some inverted (empty slots are stored that way).
                    (lo[c], hi[c]) = if k % 5 == 0 { (a, b) } else { (a.min(b), a.max(b)) };
                }
            }
            let mut comp = || match rng.random_range(0..8) {
                0 => 0.0,
                1 => -0.0,
                _ => rng.random_range(-1.0f32..1.0),
            };
            let dir = Vec3A::new(comp(), comp(), comp());
            if dir == Vec3A::ZERO {
                continue;
            }
            let origin = Vec3A::new(rng.random_range(-4.0..4.0), rng.random_range(-4.0..4.0), rng.random_range(-4.0..4.0));
            let tmax = if k % 3 == 0 { f32::INFINITY } else { rng.random_range(0.0..8.0) };
            let ray = Ray::new(origin, dir, 0.0, tmax);
            let oct_inv4: u32 = [0x0101_0101u32, 0x0202_0202, 0x0404_0404].iter().filter(|_| rng.random::<bool>()).sum();
            let want = node.intersect_ray(&ray, oct_inv4);
            // SAFETY: AVX2 is available (checked above).
            let wide = unsafe { intersect_node(&node, &ray, oct_inv4) };
            assert_eq!(wide, want, "AVX2: node {node:?}, ray {ray:?}");
            if NodeTest::Avx512.supported() {
                // SAFETY: AVX-512 F/VL/BW are available (checked just above).
                let wide = unsafe { intersect_node_avx512(&node, &ray, oct_inv4) };
                assert_eq!(wide, want, "AVX-512: node {node:?}, ray {ray:?}");
            }
        }
    }
}

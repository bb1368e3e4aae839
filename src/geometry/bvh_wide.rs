//! The CWBVH node test on 8 children at once (AVX2), for [`super::bvh::Bvh`]'s traversal.
//!
//! obvhs tests a compressed wide node's 8 child boxes 4 at a time with SSE, converting each
//! quantised plane byte to f32 one by one. With AVX2 the 8 bytes of a plane row become 8 floats in
//! two instructions (zero-extend, convert) and the slab test runs on all 8 children in one pass.
//! The arithmetic is obvhs' own, in the same order (plane · (extent/dir) + (p − origin)/dir by a
//! multiply then an add, no FMA; max/min with the same operand order, so NaN lanes resolve the
//! same way; the same tmin floor), so the hit mask is bit for bit the one `intersect_ray` returns
//! and the traversal visits the same nodes and reports the same hits. Detected at run time; on
//! other CPUs `Bvh` keeps obvhs' test.

use glam::Vec3A;
use obvhs::cwbvh::node::CwBvhNode;
use obvhs::ray::Ray;

/// obvhs' node test floors a child's entry distance at this (its `EPSILON`, not exported); the
/// wide test must use the same floor to cull exactly the same boxes.
const NODE_TMIN: f32 = 0.0001;

/// Whether the running CPU has the instructions [`intersect_node`] needs.
pub fn available() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// The hit mask of `node`'s children for `ray` (the layout of obvhs' `CwBvhNode::intersect_ray`:
/// inner children's traversal bits in the top byte, leaf primitives' bits in the low 24).
///
/// # Safety
/// Call only where [`available`] returned true (the CPU must have AVX2).
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
    let mut hits = _mm256_movemask_ps(_mm256_cmp_ps::<_CMP_LE_OQ>(tmin, tmax)) as u32;
    let (child_bits8, bit_index8) = node.get_child_and_index_bits(oct_inv4);
    let mut mask = 0u32;
    while hits != 0 {
        let child = hits.trailing_zeros();
        hits &= hits - 1;
        let byte = |x: u64| ((x >> (8 * child)) as u32) & 0xff;
        mask |= byte(child_bits8) << byte(bit_index8);
    }
    mask
}

#[cfg(all(test, target_arch = "x86_64"))]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_pcg::Pcg64;

    /// Random nodes (random planes, metadata, exponents) against random rays, including zero and
    /// −0.0 direction components: the mask equals obvhs' own test bit for bit.
    #[test]
    fn mask_equals_obvhs_node_test() {
        if !available() {
            eprintln!("no AVX2 on this CPU: the wide node test is never used here");
            return;
        }
        let mut rng = Pcg64::seed_from_u64(7);
        for k in 0..20_000 {
            let mut node = CwBvhNode::default();
            node.p = glam::Vec3::new(rng.random_range(-2.0..2.0), rng.random_range(-2.0..2.0), rng.random_range(-2.0..2.0));
            node.e = [0u8; 3].map(|_| rng.random_range(115..130));
            node.imask = rng.random();
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
            // SAFETY: AVX2 is available (checked above).
            let wide = unsafe { intersect_node(&node, &ray, oct_inv4) };
            assert_eq!(wide, node.intersect_ray(&ray, oct_inv4), "node {node:?}, ray {ray:?}");
        }
    }
}

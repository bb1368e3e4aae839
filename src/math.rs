//! Small numeric helpers shared by the BRDF, the light, the textures and the renderers: a frame
//! around a normal, and a floor that costs no function call.

use glam::Vec3;

/// Orthonormal frame around a unit normal (Duff et al. 2017, branchless).
#[derive(Clone, Copy, Debug)]
pub struct Frame {
    pub s: Vec3,
    pub t: Vec3,
    pub n: Vec3,
}

impl Frame {
    pub fn from_normal(n: Vec3) -> Self {
        let sign = 1.0f32.copysign(n.z);
        let a = -1.0 / (sign + n.z);
        let b = n.x * n.y * a;
        let s = Vec3::new(1.0 + sign * n.x * n.x * a, sign * b, -sign * n.x);
        let t = Vec3::new(b, sign + n.y * n.y * a, -n.y);
        Frame { s, t, n }
    }

    pub fn to_local(&self, v: Vec3) -> Vec3 {
        Vec3::new(v.dot(self.s), v.dot(self.t), v.dot(self.n))
    }

    pub fn to_world(&self, v: Vec3) -> Vec3 {
        self.s * v.x + self.t * v.y + self.n * v.z
    }
}

/// ⌊x⌋, the value of `x.floor()` for every f64 (±0, ±∞ and NaN included), without a call into
/// libm: x86-64's baseline has no rounding instruction (SSE4.1's `roundsd`), so `floor` is a
/// function call on every texture and light lookup, which a Monte Carlo step's profile showed
/// (`floor`, `floorf`: 2 % of the 4-spp step, 2026-12-08). Below 2⁵² the truncating cast is exact
/// and at most one above the floor; from there on every f64 is an integer (or ±∞, NaN), its own floor.
#[inline]
pub fn floor_f64(x: f64) -> f64 {
    const ALL_INTEGERS: f64 = (1u64 << 52) as f64;
    if x.abs() < ALL_INTEGERS && x != 0.0 {
        let t = x as i64 as f64;
        if t > x {
            t - 1.0
        } else {
            t
        }
    } else {
        x
    }
}

/// [`floor_f64`] for f32: exact, since an f32 widens to f64 without rounding and its floor is an
/// f32 again.
#[inline]
pub fn floor_f32(x: f32) -> f32 {
    floor_f64(x as f64) as f32
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_floors_are_libm_floor_bit_for_bit() {
        let mut rng = crate::rng::Sampler::new(11, 0);
        let mut xs: Vec<f64> = vec![0.0, -0.0, 0.5, -0.5, 1.0, -1.0, 2.5, -2.5, 1e-40, -1e-40, f64::INFINITY, f64::NEG_INFINITY, f64::NAN];
        for e in [22, 23, 24, 51, 52, 53, 62, 63, 64, 100] {
            let p = 2f64.powi(e);
            xs.extend([p, -p, p - 0.5, -(p - 0.5), p + 1.0, -(p + 1.0), p - 1.0, -(p - 1.0)]);
        }
        xs.extend((0..50_000).map(|k| (rng.next_f32() as f64 - 0.5) * 2f64.powi(k % 70 - 10)));
        for &x in &xs {
            let (f, g) = (x.floor(), floor_f64(x));
            assert!(f.to_bits() == g.to_bits() || (f.is_nan() && g.is_nan()), "f64 {x:e}: {g:e} against {f:e}");
            let x = x as f32;
            let (f, g) = (x.floor(), floor_f32(x));
            assert!(f.to_bits() == g.to_bits() || (f.is_nan() && g.is_nan()), "f32 {x:e}: {g:e} against {f:e}");
        }
        for bits in (0..u32::MAX).step_by(65_521) {
            let x = f32::from_bits(bits);
            let (f, g) = (x.floor(), floor_f32(x));
            assert!(f.to_bits() == g.to_bits() || (f.is_nan() && g.is_nan()), "f32 bits {bits:#x}: {g:e} against {f:e}");
        }
    }

    #[test]
    fn frame_is_orthonormal_and_round_trips() {
        for n in [Vec3::Z, -Vec3::Z, Vec3::X, Vec3::new(0.3, -0.5, 0.81).normalize(), Vec3::new(1e-7, 0.0, -1.0).normalize()] {
            let f = Frame::from_normal(n);
            assert!((f.s.length() - 1.0).abs() < 1e-5 && (f.t.length() - 1.0).abs() < 1e-5);
            assert!(f.s.dot(f.t).abs() < 1e-5 && f.s.dot(n).abs() < 1e-5 && f.t.dot(n).abs() < 1e-5);
            let v = Vec3::new(0.2, -0.7, 0.4);
            assert!((f.to_world(f.to_local(v)) - v).length() < 1e-5);
        }
    }
}

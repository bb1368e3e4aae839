//! Elementwise functions written for the vectoriser: no branches, no libm calls, so that loops
//! over them compile to whole-register arithmetic inside a pulp dispatch (the UNet's softmax,
//! SiLU after group norm, GELU in the feed-forward).

/// exp(x) for x ≤ 0; below −87 it returns 2⁻¹²⁶ instead of a subnormal.
#[inline(always)]
pub fn exp_nonpositive(x: f32) -> f32 {
    // exp(x) = 2^k · exp(r) with k = round(x / ln 2) and |r| ≤ ln 2 / 2; ln 2 in two parts so
    // that r = x − k ln 2 is exact; a degree-6 polynomial then keeps the error within ~2 ulp.
    const ROUND: f32 = 12_582_912.0; // 1.5 · 2²³: adding it rounds to an integer
    const LN2_HI: f32 = 0.693_145_75;
    const LN2_LO: f32 = 1.428_606_8e-6;
    let x = x.max(-87.0);
    let shifted = x * std::f32::consts::LOG2_E + ROUND;
    let k = shifted - ROUND;
    let r = (x - k * LN2_HI) - k * LN2_LO;
    let p = 1.0 + r * (1.0 + r * (0.5 + r * (1.0 / 6.0 + r * (1.0 / 24.0 + r * (1.0 / 120.0 + r * (1.0 / 720.0))))));
    // 2^k from k's bits in `shifted` (its mantissa holds 2²² + k): integer lanes, where `k as
    // i32` would be a saturating conversion the vectoriser gives up on
    let biased = shifted.to_bits().wrapping_sub(ROUND.to_bits()).wrapping_add(127);
    p * f32::from_bits(biased << 23)
}

/// x · sigmoid(x), from e = exp(−|x|) so that the exp never overflows.
#[inline(always)]
pub fn silu(x: f32) -> f32 {
    let e = exp_nonpositive(-x.abs());
    let sigmoid = if x >= 0.0 { 1.0 / (1.0 + e) } else { e / (1.0 + e) };
    x * sigmoid
}

/// GELU with the exact-erf definition, x · (1 + erf(x/√2)) / 2, through erfc(|x|/√2) by
/// Abramowitz & Stegun 7.1.26 (absolute error ≤ 1.5e-7), so the negative tail keeps its
/// relative accuracy instead of cancelling 1 + erf.
#[inline(always)]
pub fn gelu_erf(x: f32) -> f32 {
    const P: f32 = 0.327_591_1;
    const A: [f32; 5] = [0.254_829_6, -0.284_496_74, 1.421_413_7, -1.453_152, 1.061_405_4];
    let z = x.abs() * std::f32::consts::FRAC_1_SQRT_2;
    let t = 1.0 / (1.0 + P * z);
    let poly = t * (A[0] + t * (A[1] + t * (A[2] + t * (A[3] + t * A[4]))));
    let erfc = poly * exp_nonpositive(-z * z);
    let one_plus_erf = if x >= 0.0 { 2.0 - erfc } else { erfc };
    0.5 * x * one_plus_erf
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Relative error against f64 exp on [−87, 0]; below, a value that is negligible in any sum.
    #[test]
    fn exp_matches_f64_to_a_few_ulp() {
        let mut worst = 0f64;
        for i in 0..=200_000 {
            let x = -87.0 * i as f32 / 200_000.0;
            let want = (x as f64).exp();
            worst = worst.max(((exp_nonpositive(x) as f64 - want) / want).abs());
        }
        assert!(worst < 3e-7, "worst relative error {worst:e}");
        for x in [-87.5f32, -100.0, -1e4, f32::NEG_INFINITY] {
            assert!(exp_nonpositive(x) <= 2e-38, "exp({x}) = {}", exp_nonpositive(x));
        }
    }

    /// Against x / (1 + exp(−x)) in f64, large arguments of both signs included.
    #[test]
    fn silu_matches_f64() {
        for i in -4000..=4000 {
            let x = i as f32 * 0.025;
            let want = x as f64 / (1.0 + (-(x as f64)).exp());
            assert!((silu(x) as f64 - want).abs() <= 1e-6 * want.abs().max(1.0), "silu({x}) = {} vs {want}", silu(x));
        }
        assert!(silu(-200.0).abs() < 1e-30);
        assert_eq!(silu(200.0), 200.0);
    }

    /// Against the f64 erf GELU (candle's), on both tails and around zero.
    #[test]
    fn gelu_matches_f64_erf_gelu() {
        let mut worst = 0f64;
        for i in -10_000..=10_000 {
            let x = i as f32 * 0.001;
            let want = 0.5 * x as f64 * (1.0 + candle_core::cpu::erf::erf_f64(x as f64 * std::f64::consts::FRAC_1_SQRT_2));
            worst = worst.max((gelu_erf(x) as f64 - want).abs() / (x as f64).abs().max(1.0));
        }
        assert!(worst < 5e-7, "worst scaled error {worst:e}");
    }
}

//! The row softmax of the attention kernel, written so the compiler vectorises it: a branch-free
//! exp (exact power-of-two scaling times a degree-6 polynomial, within ~2 ulp), running maxima
//! and sums in 16 lanes, compiled for the best instruction set found at run time (pulp's
//! dispatch: AVX-512 here). With the libm exp one element at a time, the softmax took as long
//! as the attention products around it.

const LANES: usize = 16;

/// exp(x) for x ≤ 0 (softmax arguments); below −87 it returns 2⁻¹²⁶ instead of a subnormal.
#[inline(always)]
fn exp_nonpositive(x: f32) -> f32 {
    // exp(x) = 2^k · exp(r) with k = round(x / ln 2) and |r| ≤ ln 2 / 2; ln 2 in two parts so
    // that r = x − k ln 2 is exact.
    const ROUND: f32 = 12_582_912.0; // 1.5 · 2²³: adding it rounds to an integer
    const LN2_HI: f32 = 0.693_145_75;
    const LN2_LO: f32 = 1.428_606_8e-6;
    let x = x.max(-87.0);
    let k = (x * std::f32::consts::LOG2_E + ROUND) - ROUND;
    let r = (x - k * LN2_HI) - k * LN2_LO;
    let p = 1.0 + r * (1.0 + r * (0.5 + r * (1.0 / 6.0 + r * (1.0 / 24.0 + r * (1.0 / 120.0 + r * (1.0 / 720.0))))));
    p * f32::from_bits(((k as i32 + 127) as u32) << 23)
}

#[inline(always)]
fn row_max(row: &[f32]) -> f32 {
    let mut lanes = [f32::NEG_INFINITY; LANES];
    let chunks = row.chunks_exact(LANES);
    let tail = chunks.remainder();
    for c in chunks {
        for (m, &v) in lanes.iter_mut().zip(c) {
            *m = if v > *m { v } else { *m };
        }
    }
    tail.iter().chain(&lanes).copied().fold(f32::NEG_INFINITY, f32::max)
}

/// row ← exp(row − max row); returns the sum.
#[inline(always)]
fn exp_shifted_sum(row: &mut [f32], max: f32) -> f32 {
    let mut lanes = [0f32; LANES];
    let mut chunks = row.chunks_exact_mut(LANES);
    for c in &mut chunks {
        for (s, v) in lanes.iter_mut().zip(c) {
            *v = exp_nonpositive(*v - max);
            *s += *v;
        }
    }
    let mut sum: f32 = lanes.iter().sum();
    for v in chunks.into_remainder() {
        *v = exp_nonpositive(*v - max);
        sum += *v;
    }
    sum
}

/// Each `cols`-long row of `scores` ← exp(row − max(row)), unnormalised; `inv_sums[r]` ← 1 / Σ.
pub fn exp_rows(scores: &mut [f32], cols: usize, inv_sums: &mut [f32]) {
    pulp::Arch::new().dispatch(ExpRows { scores, cols, inv_sums });
}

struct ExpRows<'a> {
    scores: &'a mut [f32],
    cols: usize,
    inv_sums: &'a mut [f32],
}

impl pulp::WithSimd for ExpRows<'_> {
    type Output = ();

    // Inlined into pulp's target-feature function, so the loops below compile for its ISA.
    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _: S) {
        for (row, inv) in self.scores.chunks_mut(self.cols).zip(self.inv_sums.iter_mut()) {
            let max = row_max(row);
            *inv = 1.0 / exp_shifted_sum(row, max);
        }
    }
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

    /// Rows of lengths with and without a tail: probabilities that sum to one and match f64.
    #[test]
    fn rows_match_f64_softmax() {
        for cols in [1usize, 16, 77, 100] {
            let rows = 3;
            let data: Vec<f32> = (0..rows * cols).map(|i| ((i * 7919) % 1000) as f32 * 0.03 - 15.0).collect();
            let mut scores = data.clone();
            let mut inv = vec![0f32; rows];
            exp_rows(&mut scores, cols, &mut inv);
            for r in 0..rows {
                let row = &data[r * cols..(r + 1) * cols];
                let m = row.iter().copied().fold(f64::NEG_INFINITY, |a, b| a.max(b as f64));
                let z: f64 = row.iter().map(|&v| (v as f64 - m).exp()).sum();
                for c in 0..cols {
                    let want = (row[c] as f64 - m).exp() / z;
                    let got = scores[r * cols + c] as f64 * inv[r] as f64;
                    assert!((got - want).abs() < 1e-6, "cols {cols} ({r}, {c}): {got} vs {want}");
                }
            }
        }
    }
}

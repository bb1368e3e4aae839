//! The softmax of the attention kernel over a block of scores stored key-major ([keys][queries],
//! the layout in which gemm computes q kᵀ fastest): running maxima and sums run across the
//! queries, 16 lanes at a time, with the branch-free exp of [`super::vector_math`], compiled for
//! the best instruction set found at run time (pulp's dispatch: AVX-512 here). With the libm exp
//! one element at a time, the softmax took as long as the attention products around it.
use super::vector_math::exp_nonpositive;

/// For `scores` holding `keys` rows of `queries` values (key-major): each value ←
/// exp(value − max over its query's keys), unnormalised; `inv_sums[i]` ← 1 / Σ for query i.
pub fn exp_key_major(scores: &mut [f32], queries: usize, inv_sums: &mut [f32]) {
    pulp::Arch::new().dispatch(ExpKeyMajor { scores, queries, inv_sums });
}

struct ExpKeyMajor<'a> {
    scores: &'a mut [f32],
    queries: usize,
    inv_sums: &'a mut [f32],
}

impl pulp::WithSimd for ExpKeyMajor<'_> {
    type Output = ();

    // Inlined into pulp's target-feature function, so the loops below compile for its ISA.
    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _: S) {
        let (n, sum) = (self.queries, self.inv_sums);
        let mut maxima = vec![f32::NEG_INFINITY; n];
        for key in self.scores.chunks_exact(n) {
            for (m, &v) in maxima.iter_mut().zip(key) {
                *m = if v > *m { v } else { *m };
            }
        }
        sum.iter_mut().for_each(|s| *s = 0.0);
        for key in self.scores.chunks_exact_mut(n) {
            for ((v, s), &m) in key.iter_mut().zip(sum.iter_mut()).zip(&maxima) {
                *v = exp_nonpositive(*v - m);
                *s += *v;
            }
        }
        sum.iter_mut().for_each(|s| *s = 1.0 / *s);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Blocks with and without a lane tail: probabilities that sum to one and match f64.
    #[test]
    fn key_major_blocks_match_f64_softmax() {
        for (queries, keys) in [(1usize, 5usize), (16, 77), (21, 100), (64, 3)] {
            let data: Vec<f32> = (0..queries * keys).map(|i| ((i * 7919) % 1000) as f32 * 0.03 - 15.0).collect();
            let mut scores = data.clone();
            let mut inv = vec![0f32; queries];
            exp_key_major(&mut scores, queries, &mut inv);
            for q in 0..queries {
                let col: Vec<f64> = (0..keys).map(|k| data[k * queries + q] as f64).collect();
                let m = col.iter().copied().fold(f64::NEG_INFINITY, f64::max);
                let z: f64 = col.iter().map(|&v| (v - m).exp()).sum();
                for (k, &v) in col.iter().enumerate() {
                    let got = scores[k * queries + q] as f64 * inv[q] as f64;
                    assert!((got - (v - m).exp() / z).abs() < 1e-6, "{queries}×{keys} ({q}, {k}): {got}");
                }
            }
        }
    }
}

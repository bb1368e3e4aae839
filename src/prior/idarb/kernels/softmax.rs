//! The softmax of the attention kernel, one chunk of keys at a time (online: running maxima and
//! sums, earlier partial results rescaled), over scores stored key-major ([keys][queries], the
//! layout in which gemm computes q kᵀ fastest). The loops run across the queries, 16 lanes at a
//! time, with the branch-free exp of [`super::vector_math`], compiled for the best instruction
//! set found at run time (pulp's dispatch: AVX-512 here). With the libm exp one element at a
//! time, the softmax took as long as the attention products around it.
use super::vector_math::exp_nonpositive;

/// Running softmax state of a block of queries.
pub struct OnlineSoftmax {
    /// Largest score seen so far, per query.
    pub max: Vec<f32>,
    /// Σ exp(score − max) so far, per query.
    pub sum: Vec<f32>,
    /// exp(previous max − max) of the last chunk: the factor for earlier partial results.
    pub rescale: Vec<f32>,
}

impl OnlineSoftmax {
    pub fn new(queries: usize) -> Self {
        Self { max: vec![f32::NEG_INFINITY; queries], sum: vec![0.0; queries], rescale: vec![0.0; queries] }
    }

    /// Starts over (a new head).
    pub fn reset(&mut self) {
        self.max.fill(f32::NEG_INFINITY);
        self.sum.fill(0.0);
    }

    /// Takes in one chunk of `scores` (key-major, `self.max.len()` queries per key): updates the
    /// maxima, turns the chunk into exp(score − max), adds it to the sums (after rescaling them)
    /// and leaves the rescaling factors in `rescale`.
    pub fn absorb(&mut self, scores: &mut [f32]) {
        pulp::Arch::new().dispatch(Absorb { state: self, scores });
    }
}

struct Absorb<'a> {
    state: &'a mut OnlineSoftmax,
    scores: &'a mut [f32],
}

impl pulp::WithSimd for Absorb<'_> {
    type Output = ();

    // Inlined into pulp's target-feature function, so the loops below compile for its ISA.
    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _: S) {
        let OnlineSoftmax { max, sum, rescale } = self.state;
        let n = max.len();
        // rescale ← old max for now, max ← new max
        rescale.copy_from_slice(max);
        for key in self.scores.chunks_exact(n) {
            for (m, &v) in max.iter_mut().zip(key) {
                *m = if v > *m { v } else { *m };
            }
        }
        for ((r, s), &m) in rescale.iter_mut().zip(sum.iter_mut()).zip(max.iter()) {
            *r = exp_nonpositive(*r - m);
            *s *= *r;
        }
        for key in self.scores.chunks_exact_mut(n) {
            for ((v, s), &m) in key.iter_mut().zip(sum.iter_mut()).zip(max.iter()) {
                *v = exp_nonpositive(*v - m);
                *s += *v;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Chunk by chunk, with and without a lane tail: the rescaled chunk weights divided by the
    /// final sum are the f64 softmax over all keys.
    #[test]
    fn chunked_online_softmax_matches_f64() {
        for (queries, keys, chunk) in [(1usize, 5usize, 5usize), (16, 77, 30), (21, 100, 7), (64, 3, 1)] {
            let data: Vec<f32> = (0..queries * keys).map(|i| ((i * 7919) % 1000) as f32 * 0.03 - 15.0).collect();
            let mut scores = data.clone();
            let mut state = OnlineSoftmax::new(queries);
            state.reset();
            // weights[k][q] as absorbed, times every later chunk's rescaling
            let mut weights = vec![0f64; queries * keys];
            for c0 in (0..keys).step_by(chunk) {
                let c1 = (c0 + chunk).min(keys);
                state.absorb(&mut scores[c0 * queries..c1 * queries]);
                for k in 0..c0 {
                    for q in 0..queries {
                        weights[k * queries + q] *= state.rescale[q] as f64;
                    }
                }
                for i in c0 * queries..c1 * queries {
                    weights[i] = scores[i] as f64;
                }
            }
            for q in 0..queries {
                let col: Vec<f64> = (0..keys).map(|k| data[k * queries + q] as f64).collect();
                let m = col.iter().copied().fold(f64::NEG_INFINITY, f64::max);
                let z: f64 = col.iter().map(|&v| (v - m).exp()).sum();
                for (k, &v) in col.iter().enumerate() {
                    let got = weights[k * queries + q] / state.sum[q] as f64;
                    assert!((got - (v - m).exp() / z).abs() < 1e-6, "{queries}×{keys} by {chunk} ({q}, {k}): {got}");
                }
            }
        }
    }
}

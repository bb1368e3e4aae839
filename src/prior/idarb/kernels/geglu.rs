//! GEGLU's gating, value · gelu_erf(gate), as one parallel, vectorised pass over rows of the
//! projection's output (candle ops would take the two halves as strided views, copy the gate for
//! the GELU and write two fresh tensors, each on one thread, with a libm erf per element).
use super::vector_math::gelu_erf;
use rayon::prelude::*;

/// `h`: rows of 2·n with the value in the first half and the gate in the second (diffusers'
/// chunk order) → `out`: rows of n, with the exact erf GELU (not the tanh approximation).
pub fn geglu_rows(h: &[f32], out: &mut [f32], n: usize) {
    assert_eq!(h.len(), 2 * out.len(), "geglu: {} inputs for {} outputs", h.len(), out.len());
    if n == 0 {
        return;
    }
    let arch = pulp::Arch::new();
    out.par_chunks_mut(n).zip(h.par_chunks(2 * n)).for_each(|(out, row)| arch.dispatch(GateRow { out, row }));
}

/// One token: out ← value · gelu_erf(gate), compiled for the dispatched instruction set.
struct GateRow<'a> {
    out: &'a mut [f32],
    row: &'a [f32],
}

impl pulp::WithSimd for GateRow<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _: S) {
        let (value, gate) = self.row.split_at(self.out.len());
        for ((o, &v), &g) in self.out.iter_mut().zip(value).zip(gate) {
            *o = v * gelu_erf(g);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, Result, Tensor, D};

    /// Against candle's own ops: value · gelu_erf(gate).
    #[test]
    fn matches_candle_gelu_erf_gating() -> Result<()> {
        let h = (Tensor::randn(0f32, 1.0, (6, 10), &Device::Cpu)? * 3.0)?;
        let want = (h.narrow(D::Minus1, 0, 5)? * h.narrow(D::Minus1, 5, 5)?.gelu_erf()?)?.flatten_all()?.to_vec1::<f32>()?;
        let mut got = vec![0f32; 30];
        geglu_rows(&h.flatten_all()?.to_vec1::<f32>()?, &mut got, 5);
        for (g, w) in got.iter().zip(&want) {
            assert!((g - w).abs() < 1e-5, "geglu {g} vs {w}");
        }
        Ok(())
    }
}

//! GEGLU's gating, value · gelu_erf(gate), in one parallel, vectorised pass over the
//! projection's output (candle ops would take the two halves as strided views, copy the gate for
//! the GELU and write two fresh tensors, each on one thread, with a libm erf per element).
use super::cpu_kernel::contiguous_f32;
use super::vector_math::gelu_erf;
use candle_core::{bail, CpuStorage, CustomOp1, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

/// `h`: [..., 2·n] with the value in the first half and the gate in the second (diffusers'
/// chunk order) → [..., n], with the exact erf GELU (not the tanh approximation).
pub fn geglu(h: &Tensor) -> Result<Tensor> {
    h.contiguous()?.apply_op1_no_bwd(&Geglu)
}

struct Geglu;

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

impl CustomOp1 for Geglu {
    fn name(&self) -> &'static str {
        "idarb-geglu"
    }

    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        let h = contiguous_f32(s, l, self.name())?;
        let mut dims = l.dims().to_vec();
        let two_n = dims.last().copied().unwrap_or(0);
        if two_n % 2 != 0 {
            bail!("geglu: last dimension {two_n} is odd");
        }
        let n = two_n / 2;
        let mut out = vec![0f32; h.len() / 2];
        if n > 0 {
            let arch = pulp::Arch::new();
            out.par_chunks_mut(n).zip(h.par_chunks(two_n)).for_each(|(out, row)| arch.dispatch(GateRow { out, row }));
        }
        *dims.last_mut().expect("rank ≥ 1") = n;
        Ok((CpuStorage::F32(out), Shape::from_dims(&dims)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, D};

    /// Against candle's own ops: value · gelu_erf(gate).
    #[test]
    fn matches_candle_gelu_erf_gating() -> Result<()> {
        let h = (Tensor::randn(0f32, 1.0, (2, 3, 10), &Device::Cpu)? * 3.0)?;
        let want = (h.narrow(D::Minus1, 0, 5)? * h.narrow(D::Minus1, 5, 5)?.gelu_erf()?)?;
        let d = (geglu(&h)? - want)?.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?;
        assert!(d < 1e-5, "geglu differs by {d}");
        Ok(())
    }
}

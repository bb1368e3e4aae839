//! diffusers' `FeedForward` with GEGLU (`net.0.proj`: C → 2·4C, value · gelu_erf(gate), `net.2`:
//! 4C → C) plus the block's residual, as one kernel over chunks of tokens: the 8C-wide hidden
//! state and the gated 4C never exist for all tokens at once (at 512² with 4 views they would be
//! 0.5 and 0.25 GiB of fresh memory per block, faulted in page by page), only per chunk in reused
//! buffers.
use crate::optim::tape::contiguous_slice;
use super::kernels::geglu::geglu_rows;
use super::kernels::linear::{linear, Linear};
use super::kernels::scratch::Scratch;
use candle_core::{bail, CpuStorage, CustomOp2, Layout, Result, Shape, Tensor};
use candle_nn::VarBuilder;

/// Tokens per chunk: enough rows for the products to run at full speed.
const TOKENS_PER_CHUNK: usize = 1024;

#[derive(Debug, Clone)]
pub struct FeedForwardGeglu {
    proj: Linear,
    out: Linear,
    dim: usize,
}

impl FeedForwardGeglu {
    pub fn new(vb: VarBuilder, dim: usize) -> Result<Self> {
        let inner = 4 * dim;
        Ok(Self { proj: linear(dim, 2 * inner, vb.pp("net.0.proj"))?, out: linear(inner, dim, vb.pp("net.2"))?, dim })
    }

    /// `residual` + FF(`x`), both [..., C].
    pub fn forward_plus(&self, x: &Tensor, residual: &Tensor) -> Result<Tensor> {
        x.contiguous()?.apply_op2_no_bwd(&residual.contiguous()?, &FeedForwardKernel { ff: self, tokens: TOKENS_PER_CHUNK })
    }
}

struct FeedForwardKernel<'a> {
    ff: &'a FeedForwardGeglu,
    tokens: usize,
}

impl CustomOp2 for FeedForwardKernel<'_> {
    fn name(&self) -> &'static str {
        "idarb-feed-forward"
    }

    fn cpu_fwd(&self, xs: &CpuStorage, xl: &Layout, rs: &CpuStorage, rl: &Layout) -> Result<(CpuStorage, Shape)> {
        let (x, residual) = (contiguous_slice::<f32>(self.name(), xs, xl)?, contiguous_slice::<f32>(self.name(), rs, rl)?);
        let c = self.ff.dim;
        if xl.dims().last() != Some(&c) || rl.shape() != xl.shape() {
            bail!("feed-forward: input {:?}, residual {:?}, {c} channels", xl.shape(), rl.shape());
        }
        let inner = 4 * c;
        let mut out = residual.to_vec();
        for (x, out) in x.chunks(self.tokens * c).zip(out.chunks_mut(self.tokens * c)) {
            let t = x.len() / c;
            let mut hidden = Scratch::take(t * 2 * inner);
            self.ff.proj.product_into(x, hidden.as_mut_slice(), false)?;
            let mut gated = Scratch::take(t * inner);
            geglu_rows(hidden.as_mut_slice(), gated.as_mut_slice(), inner);
            self.ff.out.product_into(gated.as_mut_slice(), out, true)?;
        }
        Ok((CpuStorage::F32(out), xl.shape().clone()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Device, Module, D};
    use candle_nn::VarMap;

    /// Against the unfused formulation in candle ops, with chunks that do not divide the tokens.
    #[test]
    fn matches_unfused_feed_forward() -> Result<()> {
        let dev = Device::Cpu;
        let varmap = VarMap::new();
        let ff = FeedForwardGeglu::new(VarBuilder::from_varmap(&varmap, DType::F32, &dev), 8)?;
        let x = Tensor::randn(0f32, 1.0, (2, 7, 8), &dev)?;
        let r = Tensor::randn(0f32, 1.0, (2, 7, 8), &dev)?;
        let h = ff.proj.forward(&x)?;
        let want = (ff.out.forward(&(h.narrow(D::Minus1, 0, 32)? * h.narrow(D::Minus1, 32, 32)?.gelu_erf()?)?)? + &r)?;
        for tokens in [3, 1024] {
            let got = x.apply_op2_no_bwd(&r, &FeedForwardKernel { ff: &ff, tokens })?;
            let d = (got - &want)?.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?;
            assert!(d < 1e-5, "{tokens} tokens per chunk: feed-forward differs by {d}");
        }
        Ok(())
    }
}

//! Multi-head attention as diffusers' `Attention` (`to_q`, `to_k`, `to_v`, `to_out.0`), with
//! memory-bounded scaled-dot-product attention: queries are processed in chunks so the score
//! matrix never exceeds a fixed budget (4 views at 512² would otherwise need ~15 GiB per layer).
use candle_core::{Module, Result, Tensor};
use candle_nn::{linear, linear_no_bias, Linear, VarBuilder};

/// Upper bound, in bytes, of one chunk of attention scores (f32).
pub const ATTENTION_SCORE_BUDGET_BYTES: usize = 256 << 20;

/// softmax(q kᵀ · scale) v for q [B, Lq, D], k/v [B, Lk, D], computed in query chunks.
pub fn chunked_attention(q: &Tensor, k: &Tensor, v: &Tensor, scale: f64) -> Result<Tensor> {
    chunked_attention_with_budget(q, k, v, scale, ATTENTION_SCORE_BUDGET_BYTES)
}

/// [`chunked_attention`] with an explicit score budget in bytes.
pub fn chunked_attention_with_budget(q: &Tensor, k: &Tensor, v: &Tensor, scale: f64, budget: usize) -> Result<Tensor> {
    let (b, lq, _d) = q.dims3()?;
    let lk = k.dim(1)?;
    let bytes_per_row = b * lk * 4;
    let chunk = (budget / bytes_per_row.max(1)).clamp(1, lq);
    let kt = k.transpose(1, 2)?.contiguous()?;
    let v = v.contiguous()?;
    let mut outs = Vec::with_capacity(lq.div_ceil(chunk));
    let mut start = 0;
    while start < lq {
        let len = chunk.min(lq - start);
        let qc = q.narrow(1, start, len)?.contiguous()?;
        let scores = (qc.matmul(&kt)? * scale)?;
        let probs = candle_nn::ops::softmax_last_dim(&scores)?;
        outs.push(probs.matmul(&v)?);
        start += len;
    }
    if outs.len() == 1 {
        Ok(outs.pop().expect("one chunk"))
    } else {
        Tensor::cat(&outs, 1)
    }
}

/// [B, L, H·D] → [B·H, L, D]; heads are contiguous channel blocks (diffusers `head_to_batch_dim`).
pub fn heads_to_batch(x: &Tensor, heads: usize) -> Result<Tensor> {
    let (b, l, c) = x.dims3()?;
    x.reshape((b, l, heads, c / heads))?.transpose(1, 2)?.contiguous()?.reshape((b * heads, l, c / heads))
}

/// Inverse of [`heads_to_batch`].
pub fn batch_to_heads(x: &Tensor, heads: usize) -> Result<Tensor> {
    let (bh, l, d) = x.dims3()?;
    x.reshape((bh / heads, heads, l, d))?.transpose(1, 2)?.contiguous()?.reshape((bh / heads, l, heads * d))
}

/// diffusers `Attention` without group norm: q from `x`, k and v from `context` (or `x`).
#[derive(Debug, Clone)]
pub struct Attention {
    to_q: Linear,
    to_k: Linear,
    to_v: Linear,
    to_out: Linear,
    heads: usize,
    scale: f64,
}

impl Attention {
    /// `bias` is the projections' bias (false in the UNet, true in the VAE); `to_out.0` always has one.
    pub fn new(vb: VarBuilder, query_dim: usize, context_dim: usize, heads: usize, dim_head: usize, bias: bool) -> Result<Self> {
        let inner = heads * dim_head;
        let proj = |i, o, name: &str| if bias { linear(i, o, vb.pp(name)) } else { linear_no_bias(i, o, vb.pp(name)) };
        Ok(Self {
            to_q: proj(query_dim, inner, "to_q")?,
            to_k: proj(context_dim, inner, "to_k")?,
            to_v: proj(context_dim, inner, "to_v")?,
            to_out: linear(inner, query_dim, vb.pp("to_out.0"))?,
            heads,
            scale: 1.0 / (dim_head as f64).sqrt(),
        })
    }

    /// Projected q, k, v (before the head split), so callers can modify q and k (CaPE).
    pub fn project(&self, x: &Tensor, context: Option<&Tensor>) -> Result<(Tensor, Tensor, Tensor)> {
        let ctx = context.unwrap_or(x);
        Ok((self.to_q.forward(x)?, self.to_k.forward(ctx)?, self.to_v.forward(ctx)?))
    }

    /// Attention over projected q, k, v [B, L, H·D], followed by `to_out.0`.
    pub fn attend(&self, q: &Tensor, k: &Tensor, v: &Tensor) -> Result<Tensor> {
        let h = self.heads;
        let out = chunked_attention(&heads_to_batch(q, h)?, &heads_to_batch(k, h)?, &heads_to_batch(v, h)?, self.scale)?;
        self.to_out.forward(&batch_to_heads(&out, h)?)
    }

    pub fn forward(&self, x: &Tensor, context: Option<&Tensor>) -> Result<Tensor> {
        let (q, k, v) = self.project(x, context)?;
        self.attend(&q, &k, &v)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, DType};

    /// Chunking must not change the result: compare a forced multi-chunk run with one full softmax.
    #[test]
    fn chunked_matches_direct_softmax() -> Result<()> {
        let dev = Device::Cpu;
        let q = Tensor::randn(0f32, 1.0, (2, 37, 8), &dev)?;
        let k = Tensor::randn(0f32, 1.0, (2, 29, 8), &dev)?;
        let v = Tensor::randn(0f32, 1.0, (2, 29, 8), &dev)?;
        let direct = candle_nn::ops::softmax_last_dim(&(q.matmul(&k.t()?)? * 0.3)?)?.matmul(&v)?;
        // A budget of 5 score rows (2 batches × 29 keys × 4 bytes each) forces 8 chunks.
        let chunked = chunked_attention_with_budget(&q, &k, &v, 0.3, 5 * 2 * 29 * 4)?;
        let diff = (direct - chunked)?.abs()?.flatten_all()?.max(0)?.to_dtype(DType::F32)?.to_scalar::<f32>()?;
        assert!(diff < 1e-6, "chunked attention differs by {diff}");
        Ok(())
    }
}

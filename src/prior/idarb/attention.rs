//! Multi-head attention as diffusers' `Attention` (`to_q`, `to_k`, `to_v`, `to_out.0`). The core
//! softmax(q kᵀ · scale) v is one CPU kernel (inference only) that reads each head straight out
//! of the projections' [B, L, H·D] layout and works through blocks of queries with a reused
//! per-thread score buffer: no head permutes, no score tensors (4 views at 512² would need
//! ~15 GiB of them per layer), no fresh pages to fault in.
use super::cpu_kernel::contiguous_f32;
use super::linear::{linear, linear_no_bias, Linear};
use super::matmul::{gemm, MatMut, MatRef};
use super::scratch::Scratch;
use super::softmax::exp_rows;
use candle_core::{bail, CpuStorage, CustomOp3, Layout, Module, Result, Shape, Tensor};
use candle_nn::VarBuilder;
use rayon::prelude::*;

/// Most queries per block: enough rows for the score product to run at full speed, few enough
/// that a block's scores (× keys) stay a few MiB.
const MAX_QUERY_BLOCK: usize = 128;

/// softmax(q kᵀ · scale) v per head for q [B, Lq, H·D] and k, v [B, Lk, H·D]; heads are
/// contiguous channel blocks (diffusers' `head_to_batch_dim`). Returns [B, Lq, H·D].
pub fn attention(q: &Tensor, k: &Tensor, v: &Tensor, heads: usize, scale: f64) -> Result<Tensor> {
    let (b, lq, _) = q.dims3()?;
    let block = MAX_QUERY_BLOCK.min(lq.div_ceil((4 * rayon::current_num_threads()).div_ceil(b)).max(1));
    attention_in_blocks(q, k, v, heads, scale, block)
}

/// [`attention`] with an explicit query block size.
fn attention_in_blocks(q: &Tensor, k: &Tensor, v: &Tensor, heads: usize, scale: f64, block: usize) -> Result<Tensor> {
    let op = AttentionKernel { heads, scale: scale as f32, block };
    q.contiguous()?.apply_op3_no_bwd(&k.contiguous()?, &v.contiguous()?, &op)
}

struct AttentionKernel {
    heads: usize,
    scale: f32,
    block: usize,
}

impl CustomOp3 for AttentionKernel {
    fn name(&self) -> &'static str {
        "idarb-attention"
    }

    fn cpu_fwd(&self, qs: &CpuStorage, ql: &Layout, ks: &CpuStorage, kl: &Layout, vs: &CpuStorage, vl: &Layout) -> Result<(CpuStorage, Shape)> {
        let (q, k, v) = (contiguous_f32(qs, ql, self.name())?, contiguous_f32(ks, kl, self.name())?, contiguous_f32(vs, vl, self.name())?);
        let (b, lq, hd) = ql.shape().dims3()?;
        let (bk, lk, hdk) = kl.shape().dims3()?;
        if bk != b || hdk != hd || vl.shape() != kl.shape() || hd % self.heads != 0 {
            bail!("attention: q {:?}, k {:?}, v {:?} with {} heads", ql.shape(), kl.shape(), vl.shape(), self.heads);
        }
        let d = hd / self.heads;
        let mut out = vec![0f32; b * lq * hd];
        if lq > 0 && hd > 0 {
            out.par_chunks_mut(lq * hd).enumerate().for_each(|(bi, out_b)| {
                let (q, k, v) = (&q[bi * lq * hd..], &k[bi * lk * hd..], &v[bi * lk * hd..]);
                out_b.par_chunks_mut(self.block * hd).enumerate().for_each(|(ci, out_c)| {
                    let rows = out_c.len() / hd;
                    let q = &q[ci * self.block * hd..];
                    let mut scores = Scratch::take(rows * lk);
                    let scores = scores.as_mut_slice();
                    let mut inv_sums = vec![0f32; rows];
                    for h in 0..self.heads {
                        let (qh, kh) = (MatRef::new(&q[h * d..], rows, d, hd, 1), MatRef::new(&k[h * d..], lk, d, hd, 1));
                        gemm(MatMut::new(scores, rows, lk, lk, 1), qh, kh.t(), self.scale, false, false);
                        exp_rows(scores, lk, &mut inv_sums);
                        // unnormalised weights times v, then each output row divided by its sum
                        let probs = MatRef::new(scores, rows, lk, lk, 1);
                        gemm(MatMut::new(&mut out_c[h * d..], rows, d, hd, 1), probs, MatRef::new(&v[h * d..], lk, d, hd, 1), 1.0, false, false);
                        for (r, inv) in inv_sums.iter().enumerate() {
                            out_c[r * hd + h * d..r * hd + (h + 1) * d].iter_mut().for_each(|o| *o *= inv);
                        }
                    }
                });
            });
        }
        Ok((CpuStorage::F32(out), Shape::from_dims(&[b, lq, hd])))
    }
}

/// [B, L, H·D] → [B·H, L, D], the per-head layout of the reference formulation in the tests.
#[cfg(test)]
pub(crate) fn heads_to_batch(x: &Tensor, heads: usize) -> Result<Tensor> {
    let (b, l, c) = x.dims3()?;
    x.reshape((b, l, heads, c / heads))?.transpose(1, 2)?.contiguous()?.reshape((b * heads, l, c / heads))
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
        self.to_out.forward(&attention(q, k, v, self.heads, self.scale)?)
    }

    pub fn forward(&self, x: &Tensor, context: Option<&Tensor>) -> Result<Tensor> {
        let (q, k, v) = self.project(x, context)?;
        self.attend(&q, &k, &v)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Device};

    /// The blocked multi-head kernel against one full softmax per head in candle ops, with
    /// blocks that do not divide the queries.
    #[test]
    fn matches_direct_softmax_per_head() -> Result<()> {
        let dev = Device::Cpu;
        let heads = 3;
        let q = Tensor::randn(0f32, 1.0, (2, 37, heads * 8), &dev)?;
        let k = Tensor::randn(0f32, 1.0, (2, 29, heads * 8), &dev)?;
        let v = Tensor::randn(0f32, 1.0, (2, 29, heads * 8), &dev)?;
        let (qh, kh, vh) = (heads_to_batch(&q, heads)?, heads_to_batch(&k, heads)?, heads_to_batch(&v, heads)?);
        let direct = candle_nn::ops::softmax_last_dim(&(qh.matmul(&kh.t()?)? * 0.3)?)?.matmul(&vh)?;
        let direct = direct.reshape((2, heads, 37, 8))?.transpose(1, 2)?.reshape((2, 37, heads * 8))?;
        for block in [5, 37, 128] {
            let got = attention_in_blocks(&q, &k, &v, heads, 0.3, block)?;
            let diff = (&direct - got)?.abs()?.flatten_all()?.max(0)?.to_dtype(DType::F32)?.to_scalar::<f32>()?;
            assert!(diff < 1e-5, "block {block}: attention differs by {diff}");
        }
        Ok(())
    }
}

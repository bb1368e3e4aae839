//! Multi-head attention as diffusers' `Attention` (`to_q`, `to_k`, `to_v`, `to_out.0`). The core
//! softmax(q kᵀ · scale) v is one CPU kernel (inference only) that reads each head straight out
//! of the projections' [rows, L, H·D] layout, lets a row attend jointly to the keys of several
//! rows where they lie (IDArb's cross-domain and cross-view attention, without regrouping
//! copies), and works through blocks of queries and chunks of keys with an online softmax in a
//! reused per-thread score buffer that stays in cache: no head permutes, no score tensors (4
//! views at 512² would need ~15 GiB of them per layer), no fresh pages to fault in.
use crate::optim::tape::contiguous_slice;
use super::kernels::linear::{linear, linear_no_bias, Linear};
use super::kernels::matmul::{gemm, MatMut, MatRef};
use super::kernels::scratch::Scratch;
use super::kernels::softmax::OnlineSoftmax;
use candle_core::{bail, CpuStorage, CustomOp3, Layout, Module, Result, Shape, Tensor};
use candle_nn::VarBuilder;
use rayon::prelude::*;

/// Most queries per block (measured best among 32–256 on 256² and 512² shapes).
const MAX_QUERY_BLOCK: usize = 256;
/// Queries per block come in multiples of this (the softmax's vector width).
const QUERY_LANES: usize = 16;
/// Size of one chunk of scores, in bytes: about what stays in a core's L2 cache between the
/// score product, the softmax and the weighted sum.
const SCORE_CHUNK_BYTES: usize = 512 << 10;

/// Which rows' keys a query row attends to: rows come in groups of `blocks · stride`, and row r
/// attends to the `blocks` rows of its group that share `r mod stride`, their keys concatenated
/// in order. With rows ordered (object, view, domain): cross-domain attention is
/// `{ blocks: domains, stride: 1 }`, cross-view attention `{ blocks: views, stride: domains }`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct JointRows {
    pub blocks: usize,
    pub stride: usize,
}

impl JointRows {
    /// Each row attends to its own keys only.
    pub const OWN: JointRows = JointRows { blocks: 1, stride: 1 };

    /// The first key row of row `r`'s group and the spacing of its key rows.
    fn first_key_row(&self, r: usize) -> usize {
        let group = self.blocks * self.stride;
        (r / group) * group + r % self.stride
    }
}

/// softmax(q kᵀ · scale) v per head for q [R, Lq, H·D] and k, v [R, Lk, H·D], row r attending to
/// the keys of the rows `joint` names; heads are contiguous channel blocks (diffusers'
/// `head_to_batch_dim`). Returns [R, Lq, H·D].
pub fn attention(q: &Tensor, k: &Tensor, v: &Tensor, heads: usize, scale: f64, joint: JointRows) -> Result<Tensor> {
    let (rows, lq, _) = q.dims3()?;
    // at least four tasks per thread, for balance
    let by_tasks = lq.div_ceil((4 * rayon::current_num_threads()).div_ceil(rows.max(1)));
    let block = by_tasks.next_multiple_of(QUERY_LANES).min(MAX_QUERY_BLOCK);
    let chunk = (SCORE_CHUNK_BYTES / (4 * block)).max(1);
    attention_in_blocks(q, k, v, heads, scale, joint, (block, chunk))
}

/// [`attention`] with explicit (queries per block, keys per chunk).
fn attention_in_blocks(q: &Tensor, k: &Tensor, v: &Tensor, heads: usize, scale: f64, joint: JointRows, (block, chunk): (usize, usize)) -> Result<Tensor> {
    let op = AttentionKernel { heads, scale: scale as f32, joint, block, chunk };
    q.contiguous()?.apply_op3_no_bwd(&k.contiguous()?, &v.contiguous()?, &op)
}

struct AttentionKernel {
    heads: usize,
    scale: f32,
    joint: JointRows,
    /// Queries per block.
    block: usize,
    /// Keys per chunk.
    chunk: usize,
}

impl CustomOp3 for AttentionKernel {
    fn name(&self) -> &'static str {
        "idarb-attention"
    }

    fn cpu_fwd(&self, qs: &CpuStorage, ql: &Layout, ks: &CpuStorage, kl: &Layout, vs: &CpuStorage, vl: &Layout) -> Result<(CpuStorage, Shape)> {
        let (q, k, v) = (contiguous_slice::<f32>(self.name(), qs, ql)?, contiguous_slice::<f32>(self.name(), ks, kl)?, contiguous_slice::<f32>(self.name(), vs, vl)?);
        let (rows, lq, hd) = ql.shape().dims3()?;
        let (krows, lk, khd) = kl.shape().dims3()?;
        let JointRows { blocks, stride } = self.joint;
        if krows != rows || khd != hd || vl.shape() != kl.shape() || hd % self.heads != 0 || blocks * stride == 0 || rows % (blocks * stride) != 0 {
            bail!("attention: q {:?}, k {:?}, v {:?} with {} heads and {:?}", ql.shape(), kl.shape(), vl.shape(), self.heads, self.joint);
        }
        let d = hd / self.heads;
        // key rows one apart are one run of keys, to be chunked as one
        let (runs, run_len, run_step) = if stride == 1 { (1, blocks * lk, 0) } else { (blocks, lk, stride * lk * hd) };
        let chunks: Vec<(usize, usize)> = (0..runs).flat_map(|j| (0..run_len).step_by(self.chunk).map(move |c0| (j * run_step + c0 * hd, self.chunk.min(run_len - c0)))).collect();
        let mut out = vec![0f32; rows * lq * hd];
        if lq > 0 && hd > 0 && run_len > 0 {
            out.par_chunks_mut(lq * hd).enumerate().for_each(|(r, out_r)| {
                let first = self.joint.first_key_row(r) * lk * hd;
                out_r.par_chunks_mut(self.block * hd).enumerate().for_each(|(ci, out_c)| {
                    let n = out_c.len() / hd;
                    let q = &q[(r * lq + ci * self.block) * hd..];
                    // scores key-major, [keys][queries]: gemm's fastest output layout here
                    let mut scores = Scratch::take(n * self.chunk);
                    let scores = scores.as_mut_slice();
                    let mut softmax = OnlineSoftmax::new(n);
                    for h in 0..self.heads {
                        let qh = MatRef::new(&q[h * d..], n, d, hd, 1);
                        softmax.reset();
                        for (i, &(offset, len)) in chunks.iter().enumerate() {
                            let (kh, vh) = (MatRef::new(&k[first + offset + h * d..], len, d, hd, 1), MatRef::new(&v[first + offset + h * d..], len, d, hd, 1));
                            let s = &mut scores[..len * n];
                            gemm(MatMut::new(s, n, len, 1, n), qh, kh.t(), self.scale, false, false);
                            softmax.absorb(s);
                            // unnormalised weights times v, onto the earlier chunks' rescaled sum
                            if i > 0 {
                                for (row, f) in out_c.chunks_mut(hd).zip(&softmax.rescale) {
                                    row[h * d..(h + 1) * d].iter_mut().for_each(|o| *o *= f);
                                }
                            }
                            gemm(MatMut::new(&mut out_c[h * d..], n, d, hd, 1), MatRef::new(s, n, len, 1, n), vh, 1.0, i > 0, false);
                        }
                        for (row, sum) in out_c.chunks_mut(hd).zip(&softmax.sum) {
                            row[h * d..(h + 1) * d].iter_mut().for_each(|o| *o /= sum);
                        }
                    }
                });
            });
        }
        Ok((CpuStorage::F32(out), Shape::from_dims(&[rows, lq, hd])))
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

    /// `residual` + `to_out.0`(attention over projected q, k, v [R, L, H·D], rows joined by `joint`).
    pub fn attend_plus(&self, q: &Tensor, k: &Tensor, v: &Tensor, joint: JointRows, residual: &Tensor) -> Result<Tensor> {
        self.to_out.forward_plus(&attention(q, k, v, self.heads, self.scale, joint)?, residual)
    }

    /// `residual` + attention of `x` over `context` (or itself), rows joined by `joint`.
    pub fn forward_plus(&self, x: &Tensor, context: Option<&Tensor>, joint: JointRows, residual: &Tensor) -> Result<Tensor> {
        let (q, k, v) = self.project(x, context)?;
        self.attend_plus(&q, &k, &v, joint, residual)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Device};

    /// The reference: one full softmax per head in candle ops, over the keys of `key_rows`.
    fn direct(q: &Tensor, k: &Tensor, v: &Tensor, heads: usize, scale: f64, key_rows: &[usize]) -> Result<Tensor> {
        let pick = |t: &Tensor| -> Result<Tensor> {
            let parts = key_rows.iter().map(|&r| t.narrow(0, r, 1)).collect::<Result<Vec<_>>>()?;
            Tensor::cat(&parts, 1)
        };
        let (kr, vr) = (pick(k)?, pick(v)?);
        let (qh, kh, vh) = (heads_to_batch(q, heads)?, heads_to_batch(&kr, heads)?, heads_to_batch(&vr, heads)?);
        let out = candle_nn::ops::softmax_last_dim(&(qh.matmul(&kh.t()?)? * scale)?)?.matmul(&vh)?;
        let (_, lq, d) = out.dims3()?;
        out.reshape((1, heads, lq, d))?.transpose(1, 2)?.reshape((1, lq, heads * d))
    }

    /// The blocked multi-head kernel against the reference, for own-row, cross-domain-like
    /// (adjacent rows) and cross-view-like (strided rows) joins.
    #[test]
    fn matches_direct_softmax_per_head() -> Result<()> {
        let dev = Device::Cpu;
        let (heads, rows) = (3, 6);
        let q = Tensor::randn(0f32, 1.0, (rows, 37, heads * 8), &dev)?;
        let k = Tensor::randn(0f32, 1.0, (rows, 29, heads * 8), &dev)?;
        let v = Tensor::randn(0f32, 1.0, (rows, 29, heads * 8), &dev)?;
        for joint in [JointRows::OWN, JointRows { blocks: 3, stride: 1 }, JointRows { blocks: 2, stride: 3 }] {
            // query blocks and key chunks that do and do not divide the queries and keys
            for blocking in [(5, 7), (37, 29), (128, 1000), (16, 1)] {
                let got = attention_in_blocks(&q, &k, &v, heads, 0.3, joint, blocking)?;
                for r in 0..rows {
                    let first = joint.first_key_row(r);
                    let key_rows: Vec<usize> = (0..joint.blocks).map(|j| first + j * joint.stride).collect();
                    let want = direct(&q.narrow(0, r, 1)?, &k, &v, heads, 0.3, &key_rows)?;
                    let diff = (want - got.narrow(0, r, 1)?)?.abs()?.flatten_all()?.max(0)?.to_dtype(DType::F32)?.to_scalar::<f32>()?;
                    assert!(diff < 1e-5, "{joint:?} blocks {blocking:?} row {r}: attention differs by {diff}");
                }
            }
        }
        Ok(())
    }
}

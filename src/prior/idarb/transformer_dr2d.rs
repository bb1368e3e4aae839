//! `TransformerDR2DModel`: the SD spatial transformer with IDArb's `BasicDRTransformerBlock`.
//!
//! Batch layout everywhere is (object, view, domain) with the domain fastest: row `3·v + d`.
//! Per block: `attn1` is cross-domain attention (the domain images of one view attend jointly over
//! 3·L tokens), `attn_mv` cross-view attention (the N views of one domain attend jointly over N·L
//! tokens, CaPE on q and k), `attn2` text cross-attention, then a GEGLU feed-forward with erf GELU.
use super::attention::{Attention, JointRows};
use super::cape::apply_cape;
use super::feed_forward::FeedForwardGeglu;
use super::kernels::linear::{linear, Linear};
use candle_core::{Module, Result, Tensor};
use super::kernels::group_norm::{group_norm, GroupNorm};
use candle_nn::{layer_norm, LayerNorm, VarBuilder};

/// LayerNorm eps of `norm1`, `norm_mv`, `norm2`, `norm3` (torch default).
const LAYER_NORM_EPS: f64 = 1e-5;
/// GroupNorm eps of the transformer's input norm (diffusers `Transformer2DModel`).
const TRANSFORMER_GROUP_NORM_EPS: f64 = 1e-6;

/// Joint-attention context: how the batch rows group into views and domains, and the poses.
#[derive(Debug, Clone)]
pub struct MultiViewContext<'a> {
    pub num_views: usize,
    pub num_domains: usize,
    /// [objects, views, 4] CaPE angles.
    pub pose: &'a Tensor,
}

/// IDArb `BasicDRTransformerBlock` (with `attn1_cd` and `attn_mid_cv` on, as released).
#[derive(Debug, Clone)]
pub struct BasicDRTransformerBlock {
    norm1: LayerNorm,
    attn1: Attention,
    norm_mv: LayerNorm,
    attn_mv: Attention,
    norm2: LayerNorm,
    attn2: Attention,
    norm3: LayerNorm,
    ff: FeedForwardGeglu,
}

impl BasicDRTransformerBlock {
    pub fn new(vb: VarBuilder, dim: usize, heads: usize, dim_head: usize, context_dim: usize) -> Result<Self> {
        Ok(Self {
            norm1: layer_norm(dim, LAYER_NORM_EPS, vb.pp("norm1"))?,
            attn1: Attention::new(vb.pp("attn1"), dim, dim, heads, dim_head, false)?,
            norm_mv: layer_norm(dim, LAYER_NORM_EPS, vb.pp("norm_mv"))?,
            attn_mv: Attention::new(vb.pp("attn_mv"), dim, dim, heads, dim_head, false)?,
            norm2: layer_norm(dim, LAYER_NORM_EPS, vb.pp("norm2"))?,
            attn2: Attention::new(vb.pp("attn2"), dim, context_dim, heads, dim_head, false)?,
            norm3: layer_norm(dim, LAYER_NORM_EPS, vb.pp("norm3"))?,
            ff: FeedForwardGeglu::new(vb.pp("ff"), dim)?,
        })
    }

    /// `x`: [B·N·3, L, C] with rows (object, view, domain); `context`: [B·N·3, 77, C_text].
    /// Each residual add happens inside the output projection before it.
    pub fn forward(&self, x: &Tensor, context: &Tensor, mv: &MultiViewContext) -> Result<Tensor> {
        let (nd, nv) = (mv.num_domains, mv.num_views);
        // attn1, cross-domain: the domain rows of one view attend jointly over their 3·L tokens
        let x = self.attn1.forward_plus(&self.norm1.forward(x)?, None, JointRows { blocks: nd, stride: 1 }, x)?;
        // attn_mv, cross-view: one domain's rows of all N views jointly, CaPE on q and k
        let (q, k, v) = self.attn_mv.project(&self.norm_mv.forward(&x)?, None)?;
        let (q, k) = (apply_cape(&q, mv.pose, nd)?, apply_cape(&k, mv.pose, nd)?);
        let x = self.attn_mv.attend_plus(&q, &k, &v, JointRows { blocks: nv, stride: nd }, &x)?;
        // attn2, text cross-attention
        let x = self.attn2.forward_plus(&self.norm2.forward(&x)?, Some(context), JointRows::OWN, &x)?;
        self.ff.forward_plus(&self.norm3.forward(&x)?, &x)
    }
}

/// `TransformerDR2DModel` with linear projections and one transformer block.
#[derive(Debug, Clone)]
pub struct TransformerDR2DModel {
    norm: GroupNorm,
    proj_in: Linear,
    blocks: Vec<BasicDRTransformerBlock>,
    proj_out: Linear,
}

impl TransformerDR2DModel {
    pub fn new(vb: VarBuilder, channels: usize, heads: usize, context_dim: usize, groups: usize) -> Result<Self> {
        let dim_head = channels / heads;
        Ok(Self {
            norm: group_norm(groups, channels, TRANSFORMER_GROUP_NORM_EPS, vb.pp("norm"))?,
            proj_in: linear(channels, channels, vb.pp("proj_in"))?,
            blocks: vec![BasicDRTransformerBlock::new(vb.pp("transformer_blocks.0"), channels, heads, dim_head, context_dim)?],
            proj_out: linear(channels, channels, vb.pp("proj_out"))?,
        })
    }

    /// `x`: [B·N·3, C, H, W].
    pub fn forward(&self, x: &Tensor, context: &Tensor, mv: &MultiViewContext) -> Result<Tensor> {
        let (b, c, h, w) = x.dims4()?;
        let residual = x;
        let t = self.norm.forward(x)?.permute((0, 2, 3, 1))?.reshape((b, h * w, c))?;
        let mut t = self.proj_in.forward(&t)?;
        for block in &self.blocks {
            t = block.forward(&t, context, mv)?;
        }
        let t = self.proj_out.forward(&t)?.reshape((b, h, w, c))?.permute((0, 3, 1, 2))?;
        t + residual
    }
}

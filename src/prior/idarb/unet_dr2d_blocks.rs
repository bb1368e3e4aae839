//! The UNet's down, mid and up blocks (`CrossAttnDownBlockDR2D`, `DownBlock2D`,
//! `UNetMidBlockDR2DCrossAttn`, `UpBlock2D`, `CrossAttnUpBlockDR2D`): SD-2.1 structure with
//! [`TransformerDR2DModel`] as the attention.
use super::resnet::{Downsample2D, ResnetBlock2D, Upsample2D};
use super::transformer_dr2d::{MultiViewContext, TransformerDR2DModel};
use candle_core::{Result, Tensor};
use candle_nn::VarBuilder;

/// Shared per-UNet sizes every block needs.
#[derive(Debug, Clone, Copy)]
pub struct BlockSettings {
    pub temb_channels: usize,
    pub groups: usize,
    pub resnet_eps: f64,
    pub context_dim: usize,
}

/// A down block: `layers` × (resnet [+ transformer]) then an optional stride-2 downsampler.
#[derive(Debug, Clone)]
pub struct DownBlock {
    resnets: Vec<ResnetBlock2D>,
    attentions: Vec<TransformerDR2DModel>,
    downsampler: Option<Downsample2D>,
}

impl DownBlock {
    /// `heads` is Some for `CrossAttnDownBlockDR2D`, None for `DownBlock2D`.
    pub fn new(vb: VarBuilder, i: usize, o: usize, layers: usize, heads: Option<usize>, add_downsample: bool, s: BlockSettings) -> Result<Self> {
        let mut resnets = Vec::new();
        let mut attentions = Vec::new();
        for j in 0..layers {
            let cin = if j == 0 { i } else { o };
            resnets.push(ResnetBlock2D::new(vb.pp(format!("resnets.{j}")), cin, o, Some(s.temb_channels), s.groups, s.resnet_eps)?);
            if let Some(h) = heads {
                attentions.push(TransformerDR2DModel::new(vb.pp(format!("attentions.{j}")), o, h, s.context_dim, s.groups)?);
            }
        }
        let downsampler = if add_downsample { Some(Downsample2D::new(vb.pp("downsamplers.0"), o, false)?) } else { None };
        Ok(Self { resnets, attentions, downsampler })
    }

    /// Returns the output and the skip states it contributes (one per layer, plus the downsampled).
    pub fn forward(&self, x: &Tensor, temb: &Tensor, ctx: &Tensor, mv: &MultiViewContext) -> Result<(Tensor, Vec<Tensor>)> {
        let mut h = x.clone();
        let mut skips = Vec::new();
        for (j, resnet) in self.resnets.iter().enumerate() {
            h = resnet.forward(&h, Some(temb))?;
            if let Some(attn) = self.attentions.get(j) {
                h = attn.forward(&h, ctx, mv)?;
            }
            skips.push(h.clone());
        }
        if let Some(d) = &self.downsampler {
            h = d.forward(&h)?;
            skips.push(h.clone());
        }
        Ok((h, skips))
    }
}

/// `UNetMidBlockDR2DCrossAttn`: resnet, transformer, resnet.
#[derive(Debug, Clone)]
pub struct MidBlock {
    resnet0: ResnetBlock2D,
    attention: TransformerDR2DModel,
    resnet1: ResnetBlock2D,
}

impl MidBlock {
    pub fn new(vb: VarBuilder, c: usize, heads: usize, s: BlockSettings) -> Result<Self> {
        Ok(Self {
            resnet0: ResnetBlock2D::new(vb.pp("resnets.0"), c, c, Some(s.temb_channels), s.groups, s.resnet_eps)?,
            attention: TransformerDR2DModel::new(vb.pp("attentions.0"), c, heads, s.context_dim, s.groups)?,
            resnet1: ResnetBlock2D::new(vb.pp("resnets.1"), c, c, Some(s.temb_channels), s.groups, s.resnet_eps)?,
        })
    }

    pub fn forward(&self, x: &Tensor, temb: &Tensor, ctx: &Tensor, mv: &MultiViewContext) -> Result<Tensor> {
        let h = self.resnet0.forward(x, Some(temb))?;
        let h = self.attention.forward(&h, ctx, mv)?;
        self.resnet1.forward(&h, Some(temb))
    }
}

/// An up block: `layers` × (concat skip, resnet [+ transformer]) then an optional upsampler.
#[derive(Debug, Clone)]
pub struct UpBlock {
    resnets: Vec<ResnetBlock2D>,
    attentions: Vec<TransformerDR2DModel>,
    upsampler: Option<Upsample2D>,
}

impl UpBlock {
    /// `prev` = channels coming from below, `o` = this block's channels, `skip_in` = channels of the
    /// down block's input (the last skip of this block comes from there).
    #[allow(clippy::too_many_arguments)]
    pub fn new(vb: VarBuilder, skip_in: usize, o: usize, prev: usize, layers: usize, heads: Option<usize>, add_upsample: bool, s: BlockSettings) -> Result<Self> {
        let mut resnets = Vec::new();
        let mut attentions = Vec::new();
        for j in 0..layers {
            let skip = if j == layers - 1 { skip_in } else { o };
            let cin = if j == 0 { prev } else { o };
            resnets.push(ResnetBlock2D::new(vb.pp(format!("resnets.{j}")), cin + skip, o, Some(s.temb_channels), s.groups, s.resnet_eps)?);
            if let Some(h) = heads {
                attentions.push(TransformerDR2DModel::new(vb.pp(format!("attentions.{j}")), o, h, s.context_dim, s.groups)?);
            }
        }
        let upsampler = if add_upsample { Some(Upsample2D::new(vb.pp("upsamplers.0"), o)?) } else { None };
        Ok(Self { resnets, attentions, upsampler })
    }

    /// Consumes skips from the end of `skips`; `upsample_size` is the next skip's size.
    pub fn forward(&self, x: &Tensor, skips: &mut Vec<Tensor>, temb: &Tensor, ctx: &Tensor, mv: &MultiViewContext) -> Result<Tensor> {
        let mut h = x.clone();
        for (j, resnet) in self.resnets.iter().enumerate() {
            let skip = skips.pop().ok_or_else(|| candle_core::Error::Msg("UNet: ran out of skip connections".into()))?;
            h = Tensor::cat(&[&h, &skip], 1)?;
            h = resnet.forward(&h, Some(temb))?;
            if let Some(attn) = self.attentions.get(j) {
                h = attn.forward(&h, ctx, mv)?;
            }
        }
        if let Some(u) = &self.upsampler {
            let size = skips.last().map(|s| (s.dim(2).unwrap_or(0), s.dim(3).unwrap_or(0)));
            h = u.forward(&h, size)?;
        }
        Ok(h)
    }
}

//! diffusers `AutoencoderKL` with the SD layout: encoder (to the latent mean × scaling factor) and
//! decoder. Accepts both attention naming schemes (`to_q`… since diffusers 0.14, `query`… before).
use super::attention::{attention, JointRows};
use super::resnet::{Downsample2D, ResnetBlock2D, Upsample2D};
use anyhow::Context;
use candle_core::{Module, Result, Tensor};
use super::kernels::conv::{conv2d, Conv2d};
use super::kernels::group_norm::{group_norm, GroupNorm};
use super::kernels::linear::{linear, Linear};
use candle_nn::{Conv2dConfig, VarBuilder};
use serde_json::Value;
use std::path::Path;

/// Every VAE GroupNorm uses this eps.
const VAE_NORM_EPS: f64 = 1e-6;

#[derive(Debug, Clone, PartialEq)]
pub struct AutoencoderKLConfig {
    pub in_channels: usize,
    pub out_channels: usize,
    pub latent_channels: usize,
    pub block_out_channels: Vec<usize>,
    pub layers_per_block: usize,
    pub norm_num_groups: usize,
    pub scaling_factor: f64,
}

impl AutoencoderKLConfig {
    /// SD 2.1 VAE.
    pub fn sd21() -> Self {
        Self { in_channels: 3, out_channels: 3, latent_channels: 4, block_out_channels: vec![128, 256, 512, 512], layers_per_block: 2, norm_num_groups: 32, scaling_factor: 0.18215 }
    }

    pub fn from_json_file(path: &Path) -> anyhow::Result<Self> {
        let text = std::fs::read_to_string(path).with_context(|| format!("reading VAE config {}", path.display()))?;
        let v: Value = serde_json::from_str(&text).with_context(|| format!("parsing VAE config {}", path.display()))?;
        let u = |k: &str, d: usize| v.get(k).and_then(Value::as_u64).map(|x| x as usize).unwrap_or(d);
        let block_out_channels = v.get("block_out_channels").and_then(Value::as_array)
            .with_context(|| format!("{}: missing `block_out_channels`", path.display()))?
            .iter().map(|x| x.as_u64().map(|x| x as usize).context("bad channel count")).collect::<anyhow::Result<_>>()?;
        for k in ["use_quant_conv", "use_post_quant_conv", "mid_block_add_attention"] {
            if v.get(k).and_then(Value::as_bool) == Some(false) {
                anyhow::bail!("{}: `{k}: false` is not supported (SD VAE layout expected)", path.display());
            }
        }
        Ok(Self {
            in_channels: u("in_channels", 3),
            out_channels: u("out_channels", 3),
            latent_channels: u("latent_channels", 4),
            block_out_channels,
            layers_per_block: u("layers_per_block", 2),
            norm_num_groups: u("norm_num_groups", 32),
            scaling_factor: v.get("scaling_factor").and_then(Value::as_f64).unwrap_or(0.18215),
        })
    }
}

/// Single-head spatial self-attention with group norm and residual (the VAE mid-block attention).
#[derive(Debug, Clone)]
struct VaeAttention {
    group_norm: GroupNorm,
    to_q: Linear,
    to_k: Linear,
    to_v: Linear,
    to_out: Linear,
}

impl VaeAttention {
    fn new(vb: VarBuilder, c: usize, groups: usize) -> Result<Self> {
        // Checkpoints saved before diffusers 0.14 name the projections query/key/value/proj_attn.
        let legacy = !vb.contains_tensor("to_q.weight") && vb.contains_tensor("query.weight");
        let (q, k, v, o) = if legacy { ("query", "key", "value", "proj_attn") } else { ("to_q", "to_k", "to_v", "to_out.0") };
        Ok(Self {
            group_norm: group_norm(groups, c, VAE_NORM_EPS, vb.pp("group_norm"))?,
            to_q: linear(c, c, vb.pp(q))?,
            to_k: linear(c, c, vb.pp(k))?,
            to_v: linear(c, c, vb.pp(v))?,
            to_out: linear(c, c, vb.pp(o))?,
        })
    }

    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let (b, c, h, w) = x.dims4()?;
        let t = self.group_norm.forward(x)?.reshape((b, c, h * w))?.transpose(1, 2)?.contiguous()?;
        let (q, k, v) = (self.to_q.forward(&t)?, self.to_k.forward(&t)?, self.to_v.forward(&t)?);
        let a = self.to_out.forward(&attention(&q, &k, &v, 1, 1.0 / (c as f64).sqrt(), JointRows::OWN)?)?;
        let a = a.transpose(1, 2)?.reshape((b, c, h, w))?;
        a + x
    }
}

#[derive(Debug, Clone)]
struct VaeMidBlock {
    resnet0: ResnetBlock2D,
    attention: VaeAttention,
    resnet1: ResnetBlock2D,
}

impl VaeMidBlock {
    fn new(vb: VarBuilder, c: usize, groups: usize) -> Result<Self> {
        Ok(Self {
            resnet0: ResnetBlock2D::new(vb.pp("resnets.0"), c, c, None, groups, VAE_NORM_EPS)?,
            attention: VaeAttention::new(vb.pp("attentions.0"), c, groups)?,
            resnet1: ResnetBlock2D::new(vb.pp("resnets.1"), c, c, None, groups, VAE_NORM_EPS)?,
        })
    }

    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let h = self.resnet0.forward(x, None)?;
        let h = self.attention.forward(&h)?;
        self.resnet1.forward(&h, None)
    }
}

fn conv3(vb: VarBuilder, i: usize, o: usize) -> Result<Conv2d> {
    conv2d(i, o, 3, Conv2dConfig { padding: 1, ..Default::default() }, vb)
}

#[derive(Debug, Clone)]
pub struct Encoder {
    conv_in: Conv2d,
    down: Vec<(Vec<ResnetBlock2D>, Option<Downsample2D>)>,
    mid: VaeMidBlock,
    conv_norm_out: GroupNorm,
    conv_out: Conv2d,
}

impl Encoder {
    fn new(vb: VarBuilder, c: &AutoencoderKLConfig) -> Result<Self> {
        let ch = &c.block_out_channels;
        let g = c.norm_num_groups;
        let mut down = Vec::new();
        for i in 0..ch.len() {
            let vbi = vb.pp(format!("down_blocks.{i}"));
            let cin = if i == 0 { ch[0] } else { ch[i - 1] };
            let resnets = (0..c.layers_per_block)
                .map(|j| ResnetBlock2D::new(vbi.pp(format!("resnets.{j}")), if j == 0 { cin } else { ch[i] }, ch[i], None, g, VAE_NORM_EPS))
                .collect::<Result<Vec<_>>>()?;
            let ds = if i + 1 < ch.len() { Some(Downsample2D::new(vbi.pp("downsamplers.0"), ch[i], true)?) } else { None };
            down.push((resnets, ds));
        }
        let last = ch[ch.len() - 1];
        Ok(Self {
            conv_in: conv3(vb.pp("conv_in"), c.in_channels, ch[0])?,
            down,
            mid: VaeMidBlock::new(vb.pp("mid_block"), last, g)?,
            conv_norm_out: group_norm(g, last, VAE_NORM_EPS, vb.pp("conv_norm_out"))?,
            conv_out: conv3(vb.pp("conv_out"), last, 2 * c.latent_channels)?,
        })
    }

    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let mut h = self.conv_in.forward(x)?;
        for (resnets, ds) in &self.down {
            for r in resnets {
                h = r.forward(&h, None)?;
            }
            if let Some(d) = ds {
                h = d.forward(&h)?;
            }
        }
        let h = self.mid.forward(&h)?;
        self.conv_out.forward(&self.conv_norm_out.forward_silu(&h)?)
    }
}

#[derive(Debug, Clone)]
pub struct Decoder {
    conv_in: Conv2d,
    mid: VaeMidBlock,
    up: Vec<(Vec<ResnetBlock2D>, Option<Upsample2D>)>,
    conv_norm_out: GroupNorm,
    conv_out: Conv2d,
}

impl Decoder {
    fn new(vb: VarBuilder, c: &AutoencoderKLConfig) -> Result<Self> {
        let rch: Vec<usize> = c.block_out_channels.iter().rev().copied().collect();
        let g = c.norm_num_groups;
        let mut up = Vec::new();
        for i in 0..rch.len() {
            let vbi = vb.pp(format!("up_blocks.{i}"));
            let cin = if i == 0 { rch[0] } else { rch[i - 1] };
            let resnets = (0..=c.layers_per_block)
                .map(|j| ResnetBlock2D::new(vbi.pp(format!("resnets.{j}")), if j == 0 { cin } else { rch[i] }, rch[i], None, g, VAE_NORM_EPS))
                .collect::<Result<Vec<_>>>()?;
            let us = if i + 1 < rch.len() { Some(Upsample2D::new(vbi.pp("upsamplers.0"), rch[i])?) } else { None };
            up.push((resnets, us));
        }
        let first = c.block_out_channels[0];
        Ok(Self {
            conv_in: conv3(vb.pp("conv_in"), c.latent_channels, rch[0])?,
            mid: VaeMidBlock::new(vb.pp("mid_block"), rch[0], g)?,
            up,
            conv_norm_out: group_norm(g, first, VAE_NORM_EPS, vb.pp("conv_norm_out"))?,
            conv_out: conv3(vb.pp("conv_out"), first, c.out_channels)?,
        })
    }

    fn forward(&self, z: &Tensor) -> Result<Tensor> {
        let h = self.conv_in.forward(z)?;
        let mut h = self.mid.forward(&h)?;
        for (resnets, us) in &self.up {
            for r in resnets {
                h = r.forward(&h, None)?;
            }
            if let Some(u) = us {
                h = u.forward(&h, None)?;
            }
        }
        self.conv_out.forward(&self.conv_norm_out.forward_silu(&h)?)
    }
}

#[derive(Debug, Clone)]
pub struct AutoencoderKL {
    pub config: AutoencoderKLConfig,
    encoder: Encoder,
    decoder: Decoder,
    quant_conv: Conv2d,
    post_quant_conv: Conv2d,
}

impl AutoencoderKL {
    pub fn new(vb: VarBuilder, config: AutoencoderKLConfig) -> Result<Self> {
        let l = config.latent_channels;
        Ok(Self {
            encoder: Encoder::new(vb.pp("encoder"), &config)?,
            decoder: Decoder::new(vb.pp("decoder"), &config)?,
            quant_conv: conv2d(2 * l, 2 * l, 1, Default::default(), vb.pp("quant_conv"))?,
            post_quant_conv: conv2d(l, l, 1, Default::default(), vb.pp("post_quant_conv"))?,
            config,
        })
    }

    /// Images in [−1, 1] [B, 3, H, W] → scaled latent mean [B, 4, H/8, W/8]
    /// (`latent_dist.mode() · scaling_factor`).
    pub fn encode_scaled_mean(&self, x: &Tensor) -> Result<Tensor> {
        let moments = self.quant_conv.forward(&self.encoder.forward(x)?)?;
        moments.narrow(1, 0, self.config.latent_channels)? * self.config.scaling_factor
    }

    /// Scaled latents → images in [−1, 1] (unclamped): `decode(z / scaling_factor)`.
    pub fn decode_scaled(&self, z: &Tensor) -> Result<Tensor> {
        let z = (z / self.config.scaling_factor)?;
        self.decoder.forward(&self.post_quant_conv.forward(&z)?)
    }
}

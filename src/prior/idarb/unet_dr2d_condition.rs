//! `UNetDR2DConditionModel`: the SD-2.1-base UNet with 8 input channels (noisy latent, then image
//! latent) and IDArb's multi-domain, multi-view transformer blocks.
use super::transformer_dr2d::MultiViewContext;
use super::unet_dr2d_blocks::{BlockSettings, DownBlock, MidBlock, UpBlock};
use anyhow::{bail, Context};
use candle_core::{Module, Result, Tensor};
use super::kernels::conv::{conv2d, Conv2d};
use super::kernels::group_norm::{group_norm, GroupNorm};
use super::kernels::linear::{linear, Linear};
use candle_nn::{Conv2dConfig, VarBuilder};
use serde_json::Value;
use std::path::Path;

/// The config values the port uses, read from diffusers' `unet/config.json`.
#[derive(Debug, Clone, PartialEq)]
pub struct UNetDR2DConfig {
    pub in_channels: usize,
    pub out_channels: usize,
    pub block_out_channels: Vec<usize>,
    /// Number of heads per down block (diffusers calls this `attention_head_dim`).
    pub heads: Vec<usize>,
    pub layers_per_block: usize,
    pub cross_attention_dim: usize,
    pub norm_num_groups: usize,
    pub norm_eps: f64,
    pub num_domains: usize,
    pub flip_sin_to_cos: bool,
    pub freq_shift: f64,
    /// Whether each down block has attention (`CrossAttnDownBlockDR2D`) or not (`DownBlock2D`).
    pub down_has_attention: Vec<bool>,
    pub up_has_attention: Vec<bool>,
}

impl UNetDR2DConfig {
    /// The released full-size model (SD-2.1-base + IDArb overrides).
    pub fn full() -> Self {
        Self {
            in_channels: 8,
            out_channels: 4,
            block_out_channels: vec![320, 640, 1280, 1280],
            heads: vec![5, 10, 20, 20],
            layers_per_block: 2,
            cross_attention_dim: 1024,
            norm_num_groups: 32,
            norm_eps: 1e-5,
            num_domains: 3,
            flip_sin_to_cos: true,
            freq_shift: 0.0,
            down_has_attention: vec![true, true, true, false],
            up_has_attention: vec![false, true, true, true],
        }
    }

    pub fn from_json_file(path: &Path) -> anyhow::Result<Self> {
        let text = std::fs::read_to_string(path).with_context(|| format!("reading UNet config {}", path.display()))?;
        let v: Value = serde_json::from_str(&text).with_context(|| format!("parsing UNet config {}", path.display()))?;
        Self::from_json(&v).with_context(|| format!("in UNet config {}", path.display()))
    }

    pub fn from_json(v: &Value) -> anyhow::Result<Self> {
        let usize_of = |k: &str| v.get(k).and_then(Value::as_u64).map(|x| x as usize).with_context(|| format!("missing integer `{k}`"));
        let list_of = |k: &str| -> anyhow::Result<Vec<usize>> {
            v.get(k).and_then(Value::as_array).with_context(|| format!("missing list `{k}`"))?
                .iter().map(|x| x.as_u64().map(|x| x as usize).with_context(|| format!("`{k}` has a non-integer"))).collect()
        };
        let names = |k: &str| -> anyhow::Result<Vec<String>> {
            v.get(k).and_then(Value::as_array).with_context(|| format!("missing list `{k}`"))?
                .iter().map(|x| x.as_str().map(str::to_owned).with_context(|| format!("`{k}` has a non-string"))).collect()
        };
        let block_out_channels = list_of("block_out_channels")?;
        let nb = block_out_channels.len();
        // `num_attention_heads` wins when set; otherwise `attention_head_dim` holds head counts.
        let heads_value = match v.get("num_attention_heads") {
            Some(h) if !h.is_null() => h.clone(),
            _ => v.get("attention_head_dim").cloned().context("missing `attention_head_dim`")?,
        };
        let heads = match &heads_value {
            Value::Number(n) => vec![n.as_u64().context("bad head count")? as usize; nb],
            Value::Array(a) => a.iter().map(|x| x.as_u64().map(|x| x as usize).context("bad head count")).collect::<anyhow::Result<_>>()?,
            _ => bail!("`attention_head_dim` must be an integer or a list"),
        };
        if v.get("use_linear_projection").and_then(Value::as_bool) != Some(true) {
            bail!("only `use_linear_projection: true` is supported (SD 2.x)");
        }
        for k in ["attn1_cd", "attn_mid_cv"] {
            if v.get(k).and_then(Value::as_bool) != Some(true) {
                bail!("`{k}` must be true (the released IDArb model)");
            }
        }
        if let Some(t) = v.get("transformer_layers_per_block").and_then(Value::as_u64) {
            if t != 1 {
                bail!("`transformer_layers_per_block` must be 1");
            }
        }
        let down = names("down_block_types")?;
        let up = names("up_block_types")?;
        let down_has_attention = down.iter().map(|n| match n.as_str() {
            "CrossAttnDownBlockDR2D" => Ok(true),
            "DownBlock2D" => Ok(false),
            o => bail!("unsupported down block `{o}`"),
        }).collect::<anyhow::Result<Vec<_>>>()?;
        let up_has_attention = up.iter().map(|n| match n.as_str() {
            "CrossAttnUpBlockDR2D" => Ok(true),
            "UpBlock2D" => Ok(false),
            o => bail!("unsupported up block `{o}`"),
        }).collect::<anyhow::Result<Vec<_>>>()?;
        if heads.len() != nb || down_has_attention.len() != nb || up_has_attention.len() != nb {
            bail!("block lists have different lengths");
        }
        Ok(Self {
            in_channels: usize_of("in_channels")?,
            out_channels: usize_of("out_channels")?,
            block_out_channels,
            heads,
            layers_per_block: usize_of("layers_per_block")?,
            cross_attention_dim: usize_of("cross_attention_dim")?,
            norm_num_groups: usize_of("norm_num_groups")?,
            norm_eps: v.get("norm_eps").and_then(Value::as_f64).unwrap_or(1e-5),
            num_domains: usize_of("num_domains")?,
            flip_sin_to_cos: v.get("flip_sin_to_cos").and_then(Value::as_bool).unwrap_or(true),
            freq_shift: v.get("freq_shift").and_then(Value::as_f64).unwrap_or(0.0),
            down_has_attention,
            up_has_attention,
        })
    }
}

/// Sinusoidal timestep features as diffusers `Timesteps` (always float32): half = dim/2,
/// freq_k = exp(−ln(10000)·k/(half − shift)), features [sin, cos] or [cos, sin] when flipped.
pub fn timestep_features(t: f32, dim: usize, flip_sin_to_cos: bool, freq_shift: f64) -> Vec<f32> {
    let half = dim / 2;
    let mut sin = Vec::with_capacity(half);
    let mut cos = Vec::with_capacity(half);
    for k in 0..half {
        let exponent = -(10000f32.ln()) * k as f32 / (half as f32 - freq_shift as f32);
        let arg = t * exponent.exp();
        sin.push(arg.sin());
        cos.push(arg.cos());
    }
    if flip_sin_to_cos { [cos, sin].concat() } else { [sin, cos].concat() }
}

#[derive(Debug, Clone)]
pub struct UNetDR2DConditionModel {
    pub config: UNetDR2DConfig,
    conv_in: Conv2d,
    time_linear_1: Linear,
    time_linear_2: Linear,
    down_blocks: Vec<DownBlock>,
    mid_block: MidBlock,
    up_blocks: Vec<UpBlock>,
    conv_norm_out: GroupNorm,
    conv_out: Conv2d,
}

impl UNetDR2DConditionModel {
    pub fn new(vb: VarBuilder, config: UNetDR2DConfig) -> Result<Self> {
        let ch = &config.block_out_channels;
        let nb = ch.len();
        let temb = 4 * ch[0];
        let s = BlockSettings { temb_channels: temb, groups: config.norm_num_groups, resnet_eps: config.norm_eps, context_dim: config.cross_attention_dim };
        let pad1 = Conv2dConfig { padding: 1, ..Default::default() };
        let conv_in = conv2d(config.in_channels, ch[0], 3, pad1, vb.pp("conv_in"))?;
        let time_linear_1 = linear(ch[0], temb, vb.pp("time_embedding.linear_1"))?;
        let time_linear_2 = linear(temb, temb, vb.pp("time_embedding.linear_2"))?;
        let mut down_blocks = Vec::new();
        for i in 0..nb {
            let cin = if i == 0 { ch[0] } else { ch[i - 1] };
            let heads = config.down_has_attention[i].then_some(config.heads[i]);
            down_blocks.push(DownBlock::new(vb.pp(format!("down_blocks.{i}")), cin, ch[i], config.layers_per_block, heads, i + 1 < nb, s)?);
        }
        let mid_block = MidBlock::new(vb.pp("mid_block"), ch[nb - 1], config.heads[nb - 1], s)?;
        let rch: Vec<usize> = ch.iter().rev().copied().collect();
        let rheads: Vec<usize> = config.heads.iter().rev().copied().collect();
        let mut up_blocks = Vec::new();
        for i in 0..nb {
            let prev = if i == 0 { rch[0] } else { rch[i - 1] };
            let skip_in = rch[(i + 1).min(nb - 1)];
            let heads = config.up_has_attention[i].then_some(rheads[i]);
            up_blocks.push(UpBlock::new(vb.pp(format!("up_blocks.{i}")), skip_in, rch[i], prev, config.layers_per_block + 1, heads, i + 1 < nb, s)?);
        }
        let conv_norm_out = group_norm(config.norm_num_groups, ch[0], config.norm_eps, vb.pp("conv_norm_out"))?;
        let conv_out = conv2d(ch[0], config.out_channels, 3, pad1, vb.pp("conv_out"))?;
        Ok(Self { config, conv_in, time_linear_1, time_linear_2, down_blocks, mid_block, up_blocks, conv_norm_out, conv_out })
    }

    /// v-prediction for `sample` [B·N·D, 8, h, w] at integer timestep `t` (the same for every row),
    /// with text context [B·N·D, 77, C_text] and CaPE poses [B, N, 4].
    pub fn forward(&self, sample: &Tensor, t: f32, context: &Tensor, pose: &Tensor, num_views: usize) -> Result<Tensor> {
        let c = &self.config;
        let rows = sample.dim(0)?;
        let dtype = sample.dtype();
        let feats = timestep_features(t, c.block_out_channels[0], c.flip_sin_to_cos, c.freq_shift);
        let feats = Tensor::from_vec(feats, (1, c.block_out_channels[0]), sample.device())?.to_dtype(dtype)?;
        let emb = self.time_linear_2.forward(&self.time_linear_1.forward(&feats)?.silu()?)?;
        let emb = emb.broadcast_as((rows, emb.dim(1)?))?.contiguous()?;
        let mv = MultiViewContext { num_views, num_domains: c.num_domains, pose };

        let mut h = self.conv_in.forward(sample)?;
        let mut skips = vec![h.clone()];
        for block in &self.down_blocks {
            let (out, s) = block.forward(&h, &emb, context, &mv)?;
            h = out;
            skips.extend(s);
        }
        h = self.mid_block.forward(&h, &emb, context, &mv)?;
        for block in &self.up_blocks {
            h = block.forward(&h, &mut skips, &emb, context, &mv)?;
        }
        let h = self.conv_norm_out.forward_silu(&h)?;
        self.conv_out.forward(&h)?.to_dtype(dtype)
    }

    /// Floating-point operations of one forward at latent size h×w for `rows` images, counting
    /// 2 per multiply-add of the convolutions, linears and attention products (the bulk of the work).
    pub fn forward_flops(&self, rows: usize, h: usize, w: usize, num_views: usize) -> f64 {
        unet_forward_flops(&self.config, rows, h, w, num_views)
    }
}

/// See [`UNetDR2DConditionModel::forward_flops`]; needs only the config.
pub fn unet_forward_flops(c: &UNetDR2DConfig, rows: usize, h: usize, w: usize, num_views: usize) -> f64 {
    let r = rows as f64;
    let conv = |cin: usize, cout: usize, k: usize, pixels: usize| 2.0 * r * (cin * cout * k * k * pixels) as f64;
    let transformer = |ch: usize, pixels: usize| {
        let l = pixels as f64;
        let cf = ch as f64;
        let lin = 2.0 * r * l * cf * cf;
        // proj_in/out 2, attn1/mv: q,k,v,out 4 each, attn2: q,out 2 (+ k,v on 77 tokens), ff 8+4
        let linears = lin * (2.0 + 8.0 + 2.0 + 12.0) + 2.0 * 2.0 * r * 77.0 * c.cross_attention_dim as f64 * cf;
        // score + weighted sum: 4·L·keys·C per row; keys = 3L (attn1), N·L (attn_mv), 77 (attn2)
        let attn = 4.0 * r * l * cf * (c.num_domains as f64 * l + num_views as f64 * l + 77.0);
        linears + attn
    };
    let ch = &c.block_out_channels;
    let nb = ch.len();
    let mut flops = conv(c.in_channels, ch[0], 3, h * w);
    let (mut hh, mut ww) = (h, w);
    let mut skip_ch = vec![ch[0]];
    let mut prev = ch[0];
    for (i, &o) in ch.iter().enumerate() {
        for j in 0..c.layers_per_block {
            let cin = if j == 0 { prev } else { o };
            flops += conv(cin, o, 3, hh * ww) + conv(o, o, 3, hh * ww);
            if c.down_has_attention[i] {
                flops += transformer(o, hh * ww);
            }
            skip_ch.push(o);
        }
        prev = o;
        if i + 1 < nb {
            hh = hh.div_ceil(2);
            ww = ww.div_ceil(2);
            flops += conv(o, o, 3, hh * ww);
            skip_ch.push(o);
        }
    }
    flops += 2.0 * conv(prev, prev, 3, hh * ww) * 2.0 + transformer(prev, hh * ww);
    for i in 0..nb {
        let o = ch[nb - 1 - i];
        for _ in 0..=c.layers_per_block {
            let cin = prev + skip_ch.pop().unwrap_or(0);
            flops += conv(cin, o, 3, hh * ww) + conv(o, o, 3, hh * ww);
            if c.up_has_attention[i] {
                flops += transformer(o, hh * ww);
            }
            prev = o;
        }
        if i + 1 < nb {
            hh *= 2;
            ww *= 2;
            flops += conv(o, o, 3, hh * ww);
        }
    }
    flops + conv(ch[0], c.out_channels, 3, h * w)
}


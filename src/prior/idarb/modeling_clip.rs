//! transformers' `CLIPTextModel` for inference: the text tower IDArb conditions on (SD-2.1's
//! OpenCLIP ViT-H/14 text encoder in diffusers' `text_encoder/` layout). Token + position
//! embeddings, pre-LayerNorm transformer layers with causal self-attention, the final LayerNorm;
//! the output is `last_hidden_state` [B, L, hidden]. Struct, field and weight names follow the
//! official module one-to-one (`text_model.encoder.layers.{i}.self_attn.q_proj`, …).
use super::kernels::linear::{linear, Linear};
use anyhow::{bail, Context};
use candle_core::{DType, Module, Result, Tensor};
use candle_nn::{embedding, layer_norm, Embedding, LayerNorm, VarBuilder};
use serde::Deserialize;
use std::path::Path;

/// The `hidden_act` values of CLIP text configs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
pub enum HiddenAct {
    /// Exact (erf) GELU: SD-2.x's OpenCLIP towers.
    #[serde(rename = "gelu")]
    Gelu,
    /// x·σ(1.702x): OpenAI's CLIP towers (SD-1.x).
    #[serde(rename = "quick_gelu")]
    QuickGelu,
}

/// The fields of `text_encoder/config.json` the forward pass uses.
#[derive(Debug, Clone, Deserialize)]
pub struct CLIPTextConfig {
    pub vocab_size: usize,
    pub hidden_size: usize,
    pub intermediate_size: usize,
    pub num_hidden_layers: usize,
    pub num_attention_heads: usize,
    pub max_position_embeddings: usize,
    pub hidden_act: HiddenAct,
    pub layer_norm_eps: f64,
    /// Present in saved configs; checked to name a wrong model.
    #[serde(default)]
    pub architectures: Option<Vec<String>>,
}

impl CLIPTextConfig {
    /// Read and check a saved config; the error names the file and the field.
    pub fn from_json_file(path: &Path) -> anyhow::Result<Self> {
        let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        let cfg: Self = serde_json::from_str(&text).with_context(|| format!("{}: not a CLIPTextModel config", path.display()))?;
        if let Some(arch) = &cfg.architectures {
            if !arch.iter().any(|a| a.starts_with("CLIPTextModel")) {
                bail!("{}: architectures {arch:?}, expected a CLIPTextModel", path.display());
            }
        }
        if cfg.num_attention_heads == 0 || !cfg.hidden_size.is_multiple_of(cfg.num_attention_heads) {
            bail!("{}: hidden_size {} is not a multiple of num_attention_heads {}", path.display(), cfg.hidden_size, cfg.num_attention_heads);
        }
        Ok(cfg)
    }
}

#[derive(Debug, Clone)]
pub struct CLIPTextEmbeddings {
    token_embedding: Embedding,
    position_embedding: Embedding,
}

impl CLIPTextEmbeddings {
    pub fn new(vb: VarBuilder, c: &CLIPTextConfig) -> Result<Self> {
        Ok(Self {
            token_embedding: embedding(c.vocab_size, c.hidden_size, vb.pp("token_embedding"))?,
            position_embedding: embedding(c.max_position_embeddings, c.hidden_size, vb.pp("position_embedding"))?,
        })
    }

    /// ids [B, L] (u32) → [B, L, hidden], positions 0…L−1.
    pub fn forward(&self, input_ids: &Tensor) -> Result<Tensor> {
        let l = input_ids.dim(1)?;
        let positions = Tensor::arange(0u32, l as u32, input_ids.device())?;
        self.token_embedding.forward(input_ids)?.broadcast_add(&self.position_embedding.forward(&positions)?)
    }
}

#[derive(Debug, Clone)]
pub struct CLIPAttention {
    q_proj: Linear,
    k_proj: Linear,
    v_proj: Linear,
    out_proj: Linear,
    num_heads: usize,
    head_dim: usize,
}

impl CLIPAttention {
    pub fn new(vb: VarBuilder, c: &CLIPTextConfig) -> Result<Self> {
        let d = c.hidden_size;
        Ok(Self {
            q_proj: linear(d, d, vb.pp("q_proj"))?,
            k_proj: linear(d, d, vb.pp("k_proj"))?,
            v_proj: linear(d, d, vb.pp("v_proj"))?,
            out_proj: linear(d, d, vb.pp("out_proj"))?,
            num_heads: c.num_attention_heads,
            head_dim: d / c.num_attention_heads,
        })
    }

    /// `residual` + attention(x) with the additive `causal_mask` [L, L].
    pub fn forward_plus(&self, x: &Tensor, causal_mask: &Tensor, residual: &Tensor) -> Result<Tensor> {
        let (b, l, _) = x.dims3()?;
        let heads = |t: Tensor| t.reshape((b, l, self.num_heads, self.head_dim))?.transpose(1, 2)?.contiguous();
        let scale = (self.head_dim as f64).powf(-0.5);
        let q = heads(self.q_proj.forward(x)?.affine(scale, 0.0)?)?;
        let k = heads(self.k_proj.forward(x)?)?;
        let v = heads(self.v_proj.forward(x)?)?;
        let scores = q.matmul(&k.t()?)?.broadcast_add(causal_mask)?;
        let probs = candle_nn::ops::softmax_last_dim(&scores)?;
        let out = probs.matmul(&v)?.transpose(1, 2)?.contiguous()?.reshape((b, l, self.num_heads * self.head_dim))?;
        self.out_proj.forward_plus(&out, residual)
    }
}

#[derive(Debug, Clone)]
pub struct CLIPMLP {
    fc1: Linear,
    fc2: Linear,
    act: HiddenAct,
}

impl CLIPMLP {
    pub fn new(vb: VarBuilder, c: &CLIPTextConfig) -> Result<Self> {
        Ok(Self { fc1: linear(c.hidden_size, c.intermediate_size, vb.pp("fc1"))?, fc2: linear(c.intermediate_size, c.hidden_size, vb.pp("fc2"))?, act: c.hidden_act })
    }

    /// `residual` + fc2(act(fc1(x))).
    pub fn forward_plus(&self, x: &Tensor, residual: &Tensor) -> Result<Tensor> {
        let h = self.fc1.forward(x)?;
        let h = match self.act {
            HiddenAct::Gelu => h.gelu_erf()?,
            HiddenAct::QuickGelu => (&h * candle_nn::ops::sigmoid(&h.affine(1.702, 0.0)?)?)?,
        };
        self.fc2.forward_plus(&h, residual)
    }
}

#[derive(Debug, Clone)]
pub struct CLIPEncoderLayer {
    self_attn: CLIPAttention,
    layer_norm1: LayerNorm,
    mlp: CLIPMLP,
    layer_norm2: LayerNorm,
}

impl CLIPEncoderLayer {
    pub fn new(vb: VarBuilder, c: &CLIPTextConfig) -> Result<Self> {
        Ok(Self {
            self_attn: CLIPAttention::new(vb.pp("self_attn"), c)?,
            layer_norm1: layer_norm(c.hidden_size, c.layer_norm_eps, vb.pp("layer_norm1"))?,
            mlp: CLIPMLP::new(vb.pp("mlp"), c)?,
            layer_norm2: layer_norm(c.hidden_size, c.layer_norm_eps, vb.pp("layer_norm2"))?,
        })
    }

    pub fn forward(&self, x: &Tensor, causal_mask: &Tensor) -> Result<Tensor> {
        let x = self.self_attn.forward_plus(&self.layer_norm1.forward(x)?, causal_mask, x)?;
        self.mlp.forward_plus(&self.layer_norm2.forward(&x)?, &x)
    }
}

#[derive(Debug, Clone)]
pub struct CLIPEncoder {
    layers: Vec<CLIPEncoderLayer>,
}

impl CLIPEncoder {
    pub fn new(vb: VarBuilder, c: &CLIPTextConfig) -> Result<Self> {
        Ok(Self { layers: (0..c.num_hidden_layers).map(|i| CLIPEncoderLayer::new(vb.pp(format!("layers.{i}")), c)).collect::<Result<_>>()? })
    }

    pub fn forward(&self, x: &Tensor, causal_mask: &Tensor) -> Result<Tensor> {
        self.layers.iter().try_fold(x.clone(), |h, layer| layer.forward(&h, causal_mask))
    }
}

#[derive(Debug, Clone)]
pub struct CLIPTextTransformer {
    embeddings: CLIPTextEmbeddings,
    encoder: CLIPEncoder,
    final_layer_norm: LayerNorm,
}

impl CLIPTextTransformer {
    pub fn new(vb: VarBuilder, c: &CLIPTextConfig) -> Result<Self> {
        Ok(Self {
            embeddings: CLIPTextEmbeddings::new(vb.pp("embeddings"), c)?,
            encoder: CLIPEncoder::new(vb.pp("encoder"), c)?,
            final_layer_norm: layer_norm(c.hidden_size, c.layer_norm_eps, vb.pp("final_layer_norm"))?,
        })
    }
}

/// Additive causal mask [L, L]: 0 on and below the diagonal, −∞ above (token i sees 0…i).
fn causal_mask(l: usize, device: &candle_core::Device) -> Result<Tensor> {
    let m: Vec<f32> = (0..l).flat_map(|i| (0..l).map(move |j| if j > i { f32::NEG_INFINITY } else { 0.0 })).collect();
    Tensor::from_vec(m, (l, l), device)
}

#[derive(Debug, Clone)]
pub struct CLIPTextModel {
    text_model: CLIPTextTransformer,
    pub config: CLIPTextConfig,
}

impl CLIPTextModel {
    pub fn new(vb: VarBuilder, config: CLIPTextConfig) -> Result<Self> {
        Ok(Self { text_model: CLIPTextTransformer::new(vb.pp("text_model"), &config)?, config })
    }

    /// `last_hidden_state` [B, L, hidden] (f32) of token ids [B, L] (no attention mask: the
    /// pipeline passes none, padding tokens included).
    pub fn forward(&self, input_ids: &Tensor) -> Result<Tensor> {
        let l = input_ids.dim(1)?;
        if l > self.config.max_position_embeddings {
            candle_core::bail!("{l} tokens, the text model has {} positions", self.config.max_position_embeddings);
        }
        let t = &self.text_model;
        let h = t.embeddings.forward(&input_ids.to_dtype(DType::U32)?)?;
        let h = t.encoder.forward(&h, &causal_mask(l, input_ids.device())?)?;
        t.final_layer_norm.forward(&h)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, D};

    /// Causality: changing a later token leaves every earlier position's output unchanged, and
    /// changes its own.
    #[test]
    fn later_tokens_do_not_reach_earlier_positions() -> Result<()> {
        let dev = Device::Cpu;
        let c = CLIPTextConfig {
            vocab_size: 11,
            hidden_size: 8,
            intermediate_size: 16,
            num_hidden_layers: 2,
            num_attention_heads: 2,
            max_position_embeddings: 6,
            hidden_act: HiddenAct::Gelu,
            layer_norm_eps: 1e-5,
            architectures: None,
        };
        let vm = candle_nn::VarMap::new();
        let vb = VarBuilder::from_varmap(&vm, DType::F32, &dev);
        let model = CLIPTextModel::new(vb, c)?;
        let a = model.forward(&Tensor::new(&[[1u32, 2, 3, 4, 5, 6]], &dev)?)?;
        let b = model.forward(&Tensor::new(&[[1u32, 2, 3, 9, 5, 6]], &dev)?)?;
        let diff = (a - b)?.abs()?.max(D::Minus1)?.squeeze(0)?.to_vec1::<f32>()?;
        assert!(diff[..3].iter().all(|&d| d == 0.0), "{diff:?}");
        assert!(diff[3..].iter().all(|&d| d > 1e-4), "{diff:?}");
        Ok(())
    }
}

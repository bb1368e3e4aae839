//! Finding and loading the official diffusers weights (`unet/`, `vae/`) by key name, memory-mapped
//! (f32, f16 or bf16 on disk; computed in f32), plus the prompt-embedding file.
use super::autoencoder_kl::{AutoencoderKL, AutoencoderKLConfig};
use super::pipeline_idarbdiffusion::IdarbPipeline;
use super::unet_dr2d_condition::{UNetDR2DConditionModel, UNetDR2DConfig};
use anyhow::{bail, Context, Result};
use candle_core::{DType, Device};
use candle_nn::VarBuilder;
use std::io::Read;
use std::path::{Path, PathBuf};

/// Environment variable naming the weights directory when no flag is given.
pub const WEIGHTS_ENV: &str = "IDARB_WEIGHTS";
/// The prompt-embedding file inside the weights directory.
pub const TEXT_EMBEDDINGS_FILE: &str = "text_embeddings.safetensors";
/// Its tensor name: [3, 77, 1024] for 'albedo', 'normal', 'metallic and roughness'.
pub const TEXT_EMBEDDINGS_KEY: &str = "text_embeddings";

/// What the user sees when `--prior idarb` has neither cached labels nor weights.
pub const NO_WEIGHTS_MESSAGE: &str = "\
--prior idarb needs either cached labels or the IDArb network weights, and found neither.
To get the weights (about 4 GB):
  1. download the official IDArb pipeline checkpoint (Hugging Face model `lizb6626/IDArb`,
     the folder with unet/, vae/, text_encoder/, tokenizer/), e.g.
       pip install huggingface_hub && huggingface-cli download lizb6626/IDArb --local-dir idarb-weights
  2. make the prompt embeddings once (needs torch + transformers):
       python tools/idarb/make_text_embeddings.py idarb-weights
  3. pass the folder: --idarb-weights idarb-weights   (or set IDARB_WEIGHTS=idarb-weights)
On synthetic scenes with ground-truth materials, --prior idarb-sim gives simulated labels
without the network.";

/// The files of one weights directory.
#[derive(Debug, Clone)]
pub struct WeightFiles {
    pub root: PathBuf,
    pub unet_config: PathBuf,
    pub unet_weights: Vec<PathBuf>,
    pub vae_config: PathBuf,
    pub vae_weights: Vec<PathBuf>,
    pub text_embeddings: PathBuf,
}

/// The weights directory from an explicit path, else `IDARB_WEIGHTS`, else None.
pub fn resolve_weights_dir(explicit: Option<&Path>) -> Option<PathBuf> {
    explicit.map(Path::to_path_buf).or_else(|| std::env::var_os(WEIGHTS_ENV).filter(|v| !v.is_empty()).map(PathBuf::from))
}

/// The safetensors of a diffusers model folder: the full-precision file, else the fp16 variant,
/// else the shards of a sharded checkpoint.
fn model_files(dir: &Path) -> Result<Vec<PathBuf>> {
    for name in ["diffusion_pytorch_model.safetensors", "diffusion_pytorch_model.fp16.safetensors"] {
        let p = dir.join(name);
        if p.is_file() {
            return Ok(vec![p]);
        }
    }
    let mut shards: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("reading weights folder {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.file_name().and_then(|n| n.to_str()).is_some_and(|n| n.starts_with("diffusion_pytorch_model-") && n.ends_with(".safetensors")))
        .collect();
    shards.sort();
    if shards.is_empty() {
        bail!("{}: no diffusion_pytorch_model*.safetensors (only safetensors checkpoints are read)", dir.display());
    }
    Ok(shards)
}

impl WeightFiles {
    pub fn locate(root: &Path) -> Result<Self> {
        if !root.is_dir() {
            bail!("IDArb weights folder {} does not exist\n\n{NO_WEIGHTS_MESSAGE}", root.display());
        }
        let need = |p: PathBuf| -> Result<PathBuf> {
            if p.is_file() { Ok(p) } else { bail!("IDArb weights: missing {}\n\n{NO_WEIGHTS_MESSAGE}", p.display()) }
        };
        Ok(Self {
            unet_config: need(root.join("unet/config.json"))?,
            unet_weights: model_files(&root.join("unet"))?,
            vae_config: need(root.join("vae/config.json"))?,
            vae_weights: model_files(&root.join("vae"))?,
            text_embeddings: need(root.join(TEXT_EMBEDDINGS_FILE))?,
            root: root.to_path_buf(),
        })
    }

    /// Every weight file with its content hash (for the label cache's provenance).
    pub fn hashes(&self) -> Result<Vec<(String, String)>> {
        let mut files: Vec<&PathBuf> = self.unet_weights.iter().chain(&self.vae_weights).collect();
        files.push(&self.text_embeddings);
        files.into_iter().map(|p| Ok((p.strip_prefix(&self.root).unwrap_or(p).display().to_string(), file_hash(p)?))).collect()
    }

    /// Build the pipeline, memory-mapping the safetensors; any stored float dtype becomes f32.
    pub fn load(&self, device: &Device) -> Result<IdarbPipeline> {
        load_pipeline(
            &UNetDR2DConfig::from_json_file(&self.unet_config)?,
            &self.unet_weights,
            &AutoencoderKLConfig::from_json_file(&self.vae_config)?,
            &self.vae_weights,
            &self.text_embeddings,
            device,
        )
    }
}

/// Build the pipeline from explicit configs and files (also used by the parity test).
pub fn load_pipeline(
    unet_config: &UNetDR2DConfig,
    unet_files: &[PathBuf],
    vae_config: &AutoencoderKLConfig,
    vae_files: &[PathBuf],
    text_file: &Path,
    device: &Device,
) -> Result<IdarbPipeline> {
    // SAFETY: the files are opened read-only and not modified while mapped (memmap2's contract).
    let unet_vb = unsafe { VarBuilder::from_mmaped_safetensors(unet_files, DType::F32, device) }
        .with_context(|| format!("memory-mapping UNet weights {unet_files:?}"))?;
    let unet = UNetDR2DConditionModel::new(unet_vb, unet_config.clone()).with_context(|| format!("UNet weights {unet_files:?} do not match the config"))?;
    let vae_vb = unsafe { VarBuilder::from_mmaped_safetensors(vae_files, DType::F32, device) }
        .with_context(|| format!("memory-mapping VAE weights {vae_files:?}"))?;
    let vae = AutoencoderKL::new(vae_vb, vae_config.clone()).with_context(|| format!("VAE weights {vae_files:?} do not match the config"))?;
    let text = load_text_embeddings(text_file, device)?;
    IdarbPipeline::new(unet, vae, text).with_context(|| format!("prompt embeddings {}", text_file.display()))
}

/// The prompt embeddings tensor from its safetensors file.
pub fn load_text_embeddings(path: &Path, device: &Device) -> Result<candle_core::Tensor> {
    let mut tensors = candle_core::safetensors::load(path, device).with_context(|| format!("reading prompt embeddings {}", path.display()))?;
    let t = tensors.remove(TEXT_EMBEDDINGS_KEY).with_context(|| format!("{}: no tensor `{TEXT_EMBEDDINGS_KEY}`", path.display()))?;
    Ok(t.to_dtype(DType::F32)?)
}

/// 64-bit FNV-1a of a file's bytes, as 16 hex digits (provenance, not security).
pub fn file_hash(path: &Path) -> Result<String> {
    let mut f = std::fs::File::open(path).with_context(|| format!("opening {}", path.display()))?;
    let mut buf = vec![0u8; 1 << 20];
    let mut h: u64 = 0xcbf29ce484222325;
    loop {
        let n = f.read(&mut buf).with_context(|| format!("reading {}", path.display()))?;
        if n == 0 {
            break;
        }
        for &b in &buf[..n] {
            h ^= b as u64;
            h = h.wrapping_mul(0x100000001b3);
        }
    }
    Ok(format!("{h:016x}"))
}

/// FNV-1a of a slice of floats (identifies the input views in the cache).
pub fn floats_hash(data: &[f32]) -> String {
    let mut h: u64 = 0xcbf29ce484222325;
    for v in data {
        for b in v.to_le_bytes() {
            h ^= b as u64;
            h = h.wrapping_mul(0x100000001b3);
        }
    }
    format!("{h:016x}")
}

//! Finding and loading the official diffusers weights folder (`unet/`, `vae/`, `text_encoder/`,
//! `tokenizer/`) by key name, memory-mapped (f32, f16 or bf16 on disk; computed in f32); the prompt
//! embeddings come from the folder's own text tower ([`super::text_embeddings`]), cached.
use super::autoencoder_kl::{AutoencoderKL, AutoencoderKLConfig};
use super::pipeline_idarbdiffusion::IdarbPipeline;
use super::text_embeddings::TextEncoderFiles;
use super::unet_dr2d_condition::{UNetDR2DConditionModel, UNetDR2DConfig};
use anyhow::{bail, Context, Result};
use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use std::io::Read;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

/// Environment variable naming the weights directory when no flag is given.
pub const WEIGHTS_ENV: &str = "IDARB_WEIGHTS";
/// The file `tools/idarb/make_text_embeddings.py` writes into the weights folder (a cross-check of
/// the Rust text tower; the Rust tool does not need it).
pub const TEXT_EMBEDDINGS_FILE: &str = "text_embeddings.safetensors";
/// The tensor name of prompt embeddings [prompts, 77, 1024] in that file, the parity cases and
/// the cache.
pub const TEXT_EMBEDDINGS_KEY: &str = "text_embeddings";

/// What the user sees when `--prior idarb` has neither cached labels nor weights.
pub const NO_WEIGHTS_MESSAGE: &str = "\
--prior idarb needs either cached labels or the IDArb network weights, and found neither.
To get the weights (about 4 GB):
  1. download the official IDArb pipeline checkpoint (Hugging Face model `lizb6626/IDArb`,
     the folder with unet/, vae/, text_encoder/, tokenizer/), e.g.
       pip install huggingface_hub && huggingface-cli download lizb6626/IDArb --local-dir idarb-weights
  2. pass the folder: --idarb-weights idarb-weights   (or set IDARB_WEIGHTS=idarb-weights)
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
    pub text: TextEncoderFiles,
    /// Content hashes, computed once ([`Self::hashes`]).
    hashes: OnceLock<Vec<(String, String)>>,
}

/// The weights directory from an explicit path, else `IDARB_WEIGHTS`, else None.
pub fn resolve_weights_dir(explicit: Option<&Path>) -> Option<PathBuf> {
    explicit.map(Path::to_path_buf).or_else(|| std::env::var_os(WEIGHTS_ENV).filter(|v| !v.is_empty()).map(PathBuf::from))
}

/// Weight-file stem of diffusers models (transformers models use `model`).
const DIFFUSERS_STEM: &str = "diffusion_pytorch_model";

/// The safetensors of a model folder with weight files `<stem>…`: the full-precision file, else
/// the fp16 variant, else the shards of a sharded checkpoint.
pub fn safetensors_files(dir: &Path, stem: &str) -> Result<Vec<PathBuf>> {
    for name in [format!("{stem}.safetensors"), format!("{stem}.fp16.safetensors")] {
        let p = dir.join(name);
        if p.is_file() {
            return Ok(vec![p]);
        }
    }
    if !dir.is_dir() {
        bail!("IDArb weights: missing folder {}", dir.display());
    }
    let mut shards: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("reading weights folder {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.file_name().and_then(|n| n.to_str()).is_some_and(|n| n.starts_with(&format!("{stem}-")) && n.ends_with(".safetensors")))
        .collect();
    shards.sort();
    if shards.is_empty() {
        bail!("{}: no {stem}*.safetensors (only safetensors checkpoints are read)", dir.display());
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
            unet_weights: safetensors_files(&root.join("unet"), DIFFUSERS_STEM)?,
            vae_config: need(root.join("vae/config.json"))?,
            vae_weights: safetensors_files(&root.join("vae"), DIFFUSERS_STEM)?,
            text: TextEncoderFiles::locate(root).map_err(|e| anyhow::anyhow!("{e:#}\n\n{NO_WEIGHTS_MESSAGE}"))?,
            root: root.to_path_buf(),
            hashes: OnceLock::new(),
        })
    }

    /// Every weight file (UNet, VAE, text encoder, tokenizer) with its content hash, for the label
    /// cache's provenance and the prompt-embedding cache's key; computed once.
    pub fn hashes(&self) -> Result<Vec<(String, String)>> {
        if let Some(h) = self.hashes.get() {
            return Ok(h.clone());
        }
        let mut h: Vec<(String, String)> = self
            .unet_weights
            .iter()
            .chain(&self.vae_weights)
            .map(|p| Ok((p.strip_prefix(&self.root).unwrap_or(p).display().to_string(), file_hash(p)?)))
            .collect::<Result<_>>()?;
        h.extend(self.text.hashes()?);
        Ok(self.hashes.get_or_init(|| h).clone())
    }

    /// Build the pipeline, memory-mapping the safetensors (any stored float dtype becomes f32);
    /// the prompt embeddings come from the project's cache folder when made from these files.
    pub fn load(&self, device: &Device) -> Result<IdarbPipeline> {
        self.load_with_cache(device, &crate::scene::spec::cache_dir())
    }

    /// [`Self::load`] with the prompt-embedding cache under `cache_root`.
    pub fn load_with_cache(&self, device: &Device, cache_root: &Path) -> Result<IdarbPipeline> {
        let text_files: Vec<String> = self.text.files().iter().map(|p| p.strip_prefix(&self.root).unwrap_or(p).display().to_string()).collect();
        let text_hashes: Vec<(String, String)> = self.hashes()?.into_iter().filter(|(f, _)| text_files.contains(f)).collect();
        let text = self.text.cached(cache_root, &text_hashes, device)?;
        let unet_config = UNetDR2DConfig::from_json_file(&self.unet_config)?;
        let width = text.dim(2)?;
        if width != unet_config.cross_attention_dim {
            bail!(
                "wrong text encoder for this UNet: {} has hidden_size {width}, {} has cross_attention_dim {}",
                self.text.config.display(),
                self.unet_config.display(),
                unet_config.cross_attention_dim
            );
        }
        build_pipeline(&unet_config, &self.unet_weights, &AutoencoderKLConfig::from_json_file(&self.vae_config)?, &self.vae_weights, text, device)
    }
}

/// Build the pipeline from explicit configs and files, with the prompt embeddings read from the
/// `text_embeddings` tensor of `text_file` (the parity cases carry theirs).
pub fn load_pipeline(
    unet_config: &UNetDR2DConfig,
    unet_files: &[PathBuf],
    vae_config: &AutoencoderKLConfig,
    vae_files: &[PathBuf],
    text_file: &Path,
    device: &Device,
) -> Result<IdarbPipeline> {
    let text = load_text_embeddings(text_file, device)?;
    build_pipeline(unet_config, unet_files, vae_config, vae_files, text, device).with_context(|| format!("prompt embeddings {}", text_file.display()))
}

/// Build the pipeline from explicit configs, weight files and prompt embeddings [≥3, 77, C].
pub fn build_pipeline(
    unet_config: &UNetDR2DConfig,
    unet_files: &[PathBuf],
    vae_config: &AutoencoderKLConfig,
    vae_files: &[PathBuf],
    text: Tensor,
    device: &Device,
) -> Result<IdarbPipeline> {
    // SAFETY: the files are opened read-only and not modified while mapped (memmap2's contract).
    let unet_vb = unsafe { VarBuilder::from_mmaped_safetensors(unet_files, DType::F32, device) }
        .with_context(|| format!("memory-mapping UNet weights {unet_files:?}"))?;
    let unet = UNetDR2DConditionModel::new(unet_vb, unet_config.clone()).with_context(|| format!("UNet weights {unet_files:?} do not match the config"))?;
    let vae_vb = unsafe { VarBuilder::from_mmaped_safetensors(vae_files, DType::F32, device) }
        .with_context(|| format!("memory-mapping VAE weights {vae_files:?}"))?;
    let vae = AutoencoderKL::new(vae_vb, vae_config.clone()).with_context(|| format!("VAE weights {vae_files:?} do not match the config"))?;
    Ok(IdarbPipeline::new(unet, vae, text)?)
}

/// The prompt embeddings tensor from its safetensors file.
pub fn load_text_embeddings(path: &Path, device: &Device) -> Result<Tensor> {
    let mut tensors = candle_core::safetensors::load(path, device).with_context(|| format!("reading prompt embeddings {}", path.display()))?;
    let t = tensors.remove(TEXT_EMBEDDINGS_KEY).with_context(|| format!("{}: no tensor `{TEXT_EMBEDDINGS_KEY}`", path.display()))?;
    Ok(t.to_dtype(DType::F32)?)
}

/// 64-bit FNV-1a of a file's bytes, as 16 hex digits (provenance, not security).
pub fn file_hash(path: &Path) -> Result<String> {
    let mut f = std::fs::File::open(path).with_context(|| format!("opening {}", path.display()))?;
    let mut buf = vec![0u8; 1 << 20];
    let mut h = FNV_OFFSET;
    loop {
        let n = f.read(&mut buf).with_context(|| format!("reading {}", path.display()))?;
        if n == 0 {
            break;
        }
        h = fnv1a(h, &buf[..n]);
    }
    Ok(format!("{h:016x}"))
}

/// FNV-1a 64-bit parameters.
const FNV_OFFSET: u64 = 0xcbf29ce484222325;

/// FNV-1a of `bytes`, continuing from `h`.
fn fnv1a(h: u64, bytes: &[u8]) -> u64 {
    bytes.iter().fold(h, |h, &b| (h ^ b as u64).wrapping_mul(0x100000001b3))
}

/// FNV-1a of a slice of floats (identifies the input views in the cache).
pub fn floats_hash(data: &[f32]) -> String {
    format!("{:016x}", data.iter().fold(FNV_OFFSET, |h, v| fnv1a(h, &v.to_le_bytes())))
}

/// FNV-1a of a string (cache keys).
pub fn text_hash(s: &str) -> String {
    format!("{:016x}", fnv1a(FNV_OFFSET, s.as_bytes()))
}

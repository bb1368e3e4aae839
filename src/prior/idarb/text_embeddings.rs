//! The official pipeline's `prepare_text_embeddings`: IDArb's five task prompts through the weights
//! folder's own `tokenizer/` and `text_encoder/` ([`ClipTokenizer`], [`CLIPTextModel`]), giving the
//! `last_hidden_state` the UNet cross-attends to. The prompts never change, so the result is
//! computed once per weights folder and cached under the project's cache folder, keyed by the
//! content hashes of the text-encoder and tokenizer files.
use super::modeling_clip::{CLIPTextConfig, CLIPTextModel};
use super::tokenization_clip::{ClipTokenizer, MERGES_FILE, SPECIAL_TOKENS_MAP_FILE, TOKENIZER_CONFIG_FILE, VOCAB_FILE};
use super::weights::{file_hash, safetensors_files, text_hash, TEXT_EMBEDDINGS_KEY};
use anyhow::{bail, Context, Result};
use candle_core::{DType, Device, Tensor};
use candle_nn::VarBuilder;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// The official task prompts, in the official order; the pipeline conditions domain d (albedo,
/// normal, metallic+roughness) on row d, the last two rows are computed but unused.
pub const TASK_PROMPTS: [&str; 5] = ["albedo", "normal", "metallic and roughness", "metallic", "roughness"];
/// The text encoder's folder and the weight-file stem transformers saves under it.
pub const TEXT_ENCODER_DIR: &str = "text_encoder";
const TEXT_ENCODER_STEM: &str = "model";
pub const TOKENIZER_DIR: &str = "tokenizer";
/// Cache subfolder (under `scene::spec::cache_dir()`).
pub const CACHE_SUBDIR: &str = "idarb_text_embeddings";

/// The text tower's files in an official weights folder.
#[derive(Debug, Clone)]
pub struct TextEncoderFiles {
    pub root: PathBuf,
    pub config: PathBuf,
    pub weights: Vec<PathBuf>,
    pub tokenizer: PathBuf,
}

impl TextEncoderFiles {
    /// `text_encoder/config.json`, its safetensors (fp32 `model.safetensors`, fp16
    /// `model.fp16.safetensors` or shards) and `tokenizer/`; the error names what is missing.
    pub fn locate(root: &Path) -> Result<Self> {
        let config = root.join(TEXT_ENCODER_DIR).join("config.json");
        if !config.is_file() {
            bail!("IDArb weights: missing {} (the prompt text encoder's config)", config.display());
        }
        let weights = safetensors_files(&root.join(TEXT_ENCODER_DIR), TEXT_ENCODER_STEM)?;
        let tokenizer = root.join(TOKENIZER_DIR);
        for f in [VOCAB_FILE, MERGES_FILE] {
            let p = tokenizer.join(f);
            if !p.is_file() {
                bail!("IDArb weights: missing {} (the prompt tokenizer)", p.display());
            }
        }
        Ok(Self { root: root.to_path_buf(), config, weights, tokenizer })
    }

    /// Every file the embeddings depend on, relative to the root.
    pub fn files(&self) -> Vec<PathBuf> {
        let mut files = vec![self.config.clone()];
        files.extend(self.weights.iter().cloned());
        files.extend([VOCAB_FILE, MERGES_FILE, TOKENIZER_CONFIG_FILE, SPECIAL_TOKENS_MAP_FILE].iter().map(|f| self.tokenizer.join(f)).filter(|p| p.is_file()));
        files
    }

    /// (relative path, content hash) of [`Self::files`].
    pub fn hashes(&self) -> Result<Vec<(String, String)>> {
        self.files().iter().map(|p| Ok((self.relative(p), file_hash(p)?))).collect()
    }

    fn relative(&self, p: &Path) -> String {
        p.strip_prefix(&self.root).unwrap_or(p).display().to_string()
    }

    /// Load the tokenizer and the text tower (any float dtype on disk; computed in f32).
    pub fn load(&self, device: &Device) -> Result<(ClipTokenizer, CLIPTextModel)> {
        let tokenizer = ClipTokenizer::from_dir(&self.tokenizer)?;
        let config = CLIPTextConfig::from_json_file(&self.config)?;
        if tokenizer.model_max_length > config.max_position_embeddings {
            bail!(
                "{}: model_max_length {} exceeds the text encoder's {} positions ({})",
                self.tokenizer.join(TOKENIZER_CONFIG_FILE).display(),
                tokenizer.model_max_length,
                config.max_position_embeddings,
                self.config.display()
            );
        }
        // SAFETY: the files are opened read-only and not modified while mapped (memmap2's contract).
        let vb = unsafe { VarBuilder::from_mmaped_safetensors(&self.weights, DType::F32, device) }
            .with_context(|| format!("memory-mapping text encoder weights {:?}", self.weights))?;
        let model = CLIPTextModel::new(vb, config).with_context(|| format!("text encoder weights {:?} do not match {}", self.weights, self.config.display()))?;
        Ok((tokenizer, model))
    }

    /// The five prompts' embeddings [5, L, hidden], computed now.
    pub fn compute(&self, device: &Device) -> Result<Tensor> {
        let (tokenizer, model) = self.load(device)?;
        prepare_text_embeddings(&tokenizer, &model, device)
    }

    /// The embeddings from `cache_root`'s copy made from these exact files, else computed and
    /// stored there. `hashes` = [`Self::hashes`] (passed in when the caller has them already).
    pub fn cached(&self, cache_root: &Path, hashes: &[(String, String)], device: &Device) -> Result<Tensor> {
        let key = text_hash(&format!("{TASK_PROMPTS:?}{hashes:?}"));
        let path = cache_root.join(CACHE_SUBDIR).join(format!("{key}.safetensors"));
        if path.is_file() {
            let mut t = candle_core::safetensors::load(&path, device).with_context(|| format!("reading cached prompt embeddings {}", path.display()))?;
            if let Some(e) = t.remove(TEXT_EMBEDDINGS_KEY).filter(|e| e.dims().first() == Some(&TASK_PROMPTS.len())) {
                return Ok(e.to_dtype(DType::F32)?);
            }
            // a damaged or foreign cache file is recomputed and overwritten
        }
        let emb = self.compute(device)?;
        std::fs::create_dir_all(path.parent().expect("has a parent")).with_context(|| format!("creating {}", cache_root.join(CACHE_SUBDIR).display()))?;
        candle_core::safetensors::save(&HashMap::from([(TEXT_EMBEDDINGS_KEY.to_string(), emb.clone())]), &path)
            .with_context(|| format!("writing prompt embeddings cache {}", path.display()))?;
        Ok(emb)
    }
}

/// Token ids [5, L] of the five prompts as the pipeline pads them.
pub fn task_prompt_ids(tokenizer: &ClipTokenizer, device: &Device) -> Result<Tensor> {
    let ids = TASK_PROMPTS.iter().map(|p| tokenizer.encode_padded(p)).collect::<Result<Vec<_>>>()?;
    let l = tokenizer.model_max_length;
    Ok(Tensor::from_vec(ids.concat(), (TASK_PROMPTS.len(), l), device)?)
}

/// `prepare_text_embeddings`: `last_hidden_state` of the five padded prompts, [5, L, hidden].
pub fn prepare_text_embeddings(tokenizer: &ClipTokenizer, model: &CLIPTextModel, device: &Device) -> Result<Tensor> {
    Ok(model.forward(&task_prompt_ids(tokenizer, device)?)?)
}

//! Checkpoints: the parameters, Adam's moments and the history of a run, written every few
//! iterations so an interrupted run resumes where it stopped (same settings required).
//! Files: `state.safetensors` (tensors) and `progress.json` (iteration, settings fingerprint,
//! history), each written to a temporary name and renamed, so a crash never leaves half a checkpoint.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use candle_core::{Device, Tensor};
use serde::{Deserialize, Serialize};

use crate::optim::adam::AdamState;

use super::history::IterationRecord;

const STATE_FILE: &str = "state.safetensors";
const PROGRESS_FILE: &str = "progress.json";

#[derive(Serialize, Deserialize)]
pub struct Progress {
    /// Iterations completed.
    pub iteration: usize,
    /// `FitConfig::fingerprint` of the run that wrote it.
    pub fingerprint: String,
    pub history: Vec<IterationRecord>,
    /// Adam: global step and per-tensor (key, steps).
    pub adam_step: usize,
    pub adam_slots: Vec<(String, u64)>,
}

pub struct Checkpoint {
    pub progress: Progress,
    pub kd: Tensor,
    pub ks: Tensor,
    pub light: Tensor,
    pub adam: AdamState,
}

fn write_atomic(path: &Path, write: impl FnOnce(&Path) -> Result<()>) -> Result<()> {
    let tmp = path.with_extension("tmp");
    write(&tmp)?;
    std::fs::rename(&tmp, path).with_context(|| format!("cannot move {} to {}", tmp.display(), path.display()))
}

pub fn save(dir: &Path, kd: &Tensor, ks: &Tensor, light: &Tensor, adam: &AdamState, progress: &Progress) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create checkpoint folder {}", dir.display()))?;
    let mut tensors: HashMap<String, Tensor> = HashMap::new();
    tensors.insert("kd".into(), kd.clone());
    tensors.insert("ks".into(), ks.clone());
    tensors.insert("light".into(), light.clone());
    for (key, m, v, _) in &adam.slots {
        tensors.insert(format!("adam/{key}/m"), m.clone());
        tensors.insert(format!("adam/{key}/v"), v.clone());
    }
    write_atomic(&dir.join(STATE_FILE), |p| {
        candle_core::safetensors::save(&tensors, p).with_context(|| format!("cannot write checkpoint {}", p.display()))
    })?;
    write_atomic(&dir.join(PROGRESS_FILE), |p| {
        std::fs::write(p, serde_json::to_string(progress)?).with_context(|| format!("cannot write {}", p.display()))
    })
}

/// The checkpoint in `dir`, `None` when there is none.
pub fn load(dir: &Path) -> Result<Option<Checkpoint>> {
    let (state, progress_path): (PathBuf, PathBuf) = (dir.join(STATE_FILE), dir.join(PROGRESS_FILE));
    if !state.is_file() || !progress_path.is_file() {
        return Ok(None);
    }
    let text = std::fs::read_to_string(&progress_path).with_context(|| format!("cannot read {}", progress_path.display()))?;
    let progress: Progress = serde_json::from_str(&text).with_context(|| format!("{} is not a valid checkpoint progress file", progress_path.display()))?;
    let mut tensors = crate::image::safe_decode::guard(&state, "checkpoint", || {
        candle_core::safetensors::load(&state, &Device::Cpu).with_context(|| format!("cannot read checkpoint {}", state.display()))
    })?;
    // Resuming from NaN or Inf would make every later loss NaN: refuse, naming the tensor.
    for (key, t) in &tensors {
        let values: Vec<f32> = t
            .to_dtype(candle_core::DType::F32)
            .and_then(|t| t.flatten_all())
            .and_then(|t| t.to_vec1())
            .with_context(|| format!("checkpoint {}: tensor {key:?} is not a float tensor", state.display()))?;
        if let Some(k) = values.iter().position(|v| !v.is_finite()) {
            bail!("checkpoint {}: tensor {key:?} holds {} at element {k}", state.display(), values[k]);
        }
    }
    let mut take = |k: &str| tensors.remove(k).with_context(|| format!("checkpoint {} has no tensor {k:?}", state.display()));
    let (kd, ks, light) = (take("kd")?, take("ks")?, take("light")?);
    let mut slots = Vec::new();
    for (key, steps) in &progress.adam_slots {
        slots.push((key.clone(), take(&format!("adam/{key}/m"))?, take(&format!("adam/{key}/v"))?, *steps));
    }
    if progress.history.len() != progress.iteration {
        bail!("checkpoint {}: {} history records for {} iterations", progress_path.display(), progress.history.len(), progress.iteration);
    }
    let adam = AdamState { step: progress.adam_step, slots };
    Ok(Some(Checkpoint { progress, kd, ks, light, adam }))
}

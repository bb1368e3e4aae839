//! Checkpoints: the parameters, Adam's moments and the history of a run, written every few
//! iterations so an interrupted run resumes where it stopped (same run identity required).
//!
//! Files in the checkpoint folder: `state-NNNNNN.safetensors` (tensors after iteration NNNNNN) and
//! `progress.json` (iteration, the state file's name, the run identity, history). A save writes
//! the new state file (temporary name, then renamed), then `progress.json` the same way, and only
//! then deletes older state files; `progress.json` is the commit point. A kill at any moment leaves
//! a `progress.json` whose state file exists and belongs to it: the previous checkpoint or the new.

use std::collections::HashMap;
use std::path::Path;

use anyhow::{bail, Context, Result};
use candle_core::{Device, Tensor};
use serde::{Deserialize, Serialize};

use crate::atomic_write;
use crate::optim::adam::AdamState;

use super::history::IterationRecord;

const PROGRESS_FILE: &str = "progress.json";

#[derive(Serialize, Deserialize)]
pub struct Progress {
    /// Iterations completed.
    pub iteration: usize,
    /// The tensors of this iteration (a file in the same folder).
    pub state_file: String,
    /// What the run that wrote it must share with a run that resumes it (the job's run identity,
    /// or the fit's own settings; see `Fit::set_identity`).
    pub identity: serde_json::Value,
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

/// The state file of iteration `iteration`.
pub fn state_file_name(iteration: usize) -> String {
    format!("state-{iteration:06}.safetensors")
}

/// Saves a checkpoint; `progress.state_file` is set here.
pub fn save(dir: &Path, kd: &Tensor, ks: &Tensor, light: &Tensor, adam: &AdamState, progress: &mut Progress) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create checkpoint folder {}", dir.display()))?;
    let mut tensors: HashMap<String, Tensor> = HashMap::new();
    tensors.insert("kd".into(), kd.clone());
    tensors.insert("ks".into(), ks.clone());
    tensors.insert("light".into(), light.clone());
    for (key, m, v, _) in &adam.slots {
        tensors.insert(format!("adam/{key}/m"), m.clone());
        tensors.insert(format!("adam/{key}/v"), v.clone());
    }
    progress.state_file = state_file_name(progress.iteration);
    atomic_write::replace_file(&dir.join(&progress.state_file), |p| {
        candle_core::safetensors::save(&tensors, p).with_context(|| format!("cannot write checkpoint {}", p.display()))
    })?;
    atomic_write::write(&dir.join(PROGRESS_FILE), serde_json::to_string(progress)?)?;
    // Older state files are no longer named by progress.json.
    for entry in std::fs::read_dir(dir).with_context(|| format!("cannot list {}", dir.display()))?.flatten() {
        let name = entry.file_name().to_string_lossy().into_owned();
        if name.starts_with("state-") && name.ends_with(".safetensors") && name != progress.state_file {
            std::fs::remove_file(entry.path()).with_context(|| format!("cannot remove the old checkpoint {}", entry.path().display()))?;
        }
    }
    Ok(())
}

/// The checkpoint in `dir`, `None` when there is none.
pub fn load(dir: &Path) -> Result<Option<Checkpoint>> {
    let progress_path = dir.join(PROGRESS_FILE);
    if !progress_path.is_file() {
        return Ok(None);
    }
    let text = std::fs::read_to_string(&progress_path).with_context(|| format!("cannot read {}", progress_path.display()))?;
    let progress: Progress = serde_json::from_str(&text).with_context(|| {
        format!("{} is not a checkpoint progress file of this version of reconstruct; delete the folder {} to start afresh", progress_path.display(), dir.display())
    })?;
    let state = dir.join(&progress.state_file);
    let mut tensors = candle_core::safetensors::load(&state, &Device::Cpu).with_context(|| format!("cannot read checkpoint {}", state.display()))?;
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

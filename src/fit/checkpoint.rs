//! Checkpoints: the parameters, Adam's moments and the history of a run, written every few
//! iterations so an interrupted run resumes where it stopped (same run identity required).
//!
//! Files in the checkpoint folder: `state-NNNNNN.safetensors` (tensors after iteration NNNNNN; with
//! vertex refinement also its positions and moments, `refine/…`) and
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
    /// The state file's other tensors (`refine/…`).
    pub extra: HashMap<String, Tensor>,
}

/// The state file of iteration `iteration`.
pub fn state_file_name(iteration: usize) -> String {
    format!("state-{iteration:06}.safetensors")
}

/// Saves a checkpoint; `progress.state_file` is set here. `extra` are further named tensors.
pub fn save(dir: &Path, kd: &Tensor, ks: &Tensor, light: &Tensor, adam: &AdamState, extra: Vec<(String, Tensor)>, progress: &mut Progress) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create checkpoint folder {}", dir.display()))?;
    let mut tensors: HashMap<String, Tensor> = HashMap::new();
    tensors.insert("kd".into(), kd.clone());
    tensors.insert("ks".into(), ks.clone());
    tensors.insert("light".into(), light.clone());
    for (key, m, v, _) in &adam.slots {
        tensors.insert(format!("adam/{key}/m"), m.clone());
        tensors.insert(format!("adam/{key}/v"), v.clone());
    }
    tensors.extend(extra);
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
    // The state file is one this module names (`state_file_name`): a plain name in the same folder,
    // never a path that leads elsewhere.
    let name = &progress.state_file;
    let is_state_file = name.starts_with("state-") && name.ends_with(".safetensors") && !name.contains(['/', '\\']) && !name.contains("..");
    if !is_state_file {
        bail!("{} names {name:?} as its tensors, which is not a checkpoint state file", progress_path.display());
    }
    let state = dir.join(name);
    let mut tensors = crate::image::safe_decode::guard(&state, "checkpoint", || {
        candle_core::safetensors::load(&state, &Device::Cpu)
            .with_context(|| format!("cannot read checkpoint {} (named by {})", state.display(), progress_path.display()))
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
    Ok(Some(Checkpoint { progress, kd, ks, light, adam, extra: tensors }))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fit::objective::LossTerms;

    fn record(iteration: usize) -> IterationRecord {
        IterationRecord { iteration, terms: LossTerms::default(), lr_factor: 1.0, seconds: 0.0, phases: Default::default() }
    }

    fn progress(iteration: usize) -> Progress {
        Progress { iteration, state_file: String::new(), identity: serde_json::json!({"seed": 0}), history: (0..iteration).map(record).collect(), adam_step: iteration, adam_slots: Vec::new() }
    }

    #[test]
    fn a_kill_at_any_step_of_a_save_leaves_one_whole_checkpoint() -> Result<()> {
        let dir = std::env::temp_dir().join(format!("reconstruct-checkpoint-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let t = |v: f32| Tensor::full(v, (2, 3), &Device::Cpu);
        let adam = AdamState { step: 1, slots: Vec::new() };
        save(&dir, &t(1.0)?, &t(1.0)?, &t(1.0)?, &adam, Vec::new(), &mut progress(1))?;
        // Killed while writing iteration 2's state, then after renaming it but before progress.json:
        // the checkpoint of iteration 1 is what loads, with its own tensors.
        std::fs::write(dir.join(format!(".{}", state_file_name(2).replace(".safetensors", ".partial.safetensors"))), b"half")?;
        candle_core::safetensors::save(&HashMap::from([("kd".to_string(), t(2.0)?)]), dir.join(state_file_name(2)))?;
        std::fs::write(dir.join(".progress.partial.json"), b"{\"iteration\": 2")?;
        let cp = load(&dir)?.expect("a checkpoint");
        assert_eq!((cp.progress.iteration, cp.kd.to_vec2::<f32>()?[0][0]), (1, 1.0));
        // A completed save commits iteration 2 and drops the older state files.
        save(&dir, &t(2.0)?, &t(2.0)?, &t(2.0)?, &adam, Vec::new(), &mut progress(2))?;
        let cp = load(&dir)?.expect("a checkpoint");
        assert_eq!((cp.progress.iteration, cp.ks.to_vec2::<f32>()?[1][2]), (2, 2.0));
        assert!(!dir.join(state_file_name(1)).exists());
        std::fs::remove_dir_all(&dir)?;
        Ok(())
    }
}

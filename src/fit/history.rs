//! What each iteration records (for the progress bar, the report's curves and checkpoints).

use serde::{Deserialize, Serialize};

use super::objective::LossTerms;

#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct IterationRecord {
    pub iteration: usize,
    pub terms: LossTerms,
    /// Learning-rate multiplier of the schedule at this step.
    pub lr_factor: f64,
    /// Wall time of the step (render, backward, Adam), seconds.
    pub seconds: f64,
    /// The step's wall time split by phase (records written before the split read as zeros).
    #[serde(default)]
    pub phases: StepPhases,
}

/// Wall seconds of one step's phases, in the order they run. `update` is the parameter update
/// (Adam, the normal map's renormalisation and the vertex refinement's step); what is left of
/// `seconds` (choosing the batch, retracing a refined mesh) is in none of them.
#[derive(Clone, Copy, Debug, Default, Serialize, Deserialize, PartialEq)]
pub struct StepPhases {
    /// Textures looked up and the views shaded, on the tape.
    pub render: f64,
    /// The objective's terms built on the tape.
    pub loss: f64,
    /// The tape walked back to the parameters' gradients.
    pub backward: f64,
    pub update: f64,
}

/// Mean of `f` over the last `window` records (smoother curves and progress readouts).
pub fn trailing_mean(history: &[IterationRecord], window: usize, f: impl Fn(&IterationRecord) -> f64) -> f64 {
    let tail = &history[history.len().saturating_sub(window.max(1))..];
    let vals: Vec<f64> = tail.iter().map(f).filter(|v| v.is_finite()).collect();
    if vals.is_empty() {
        f64::NAN
    } else {
        vals.iter().sum::<f64>() / vals.len() as f64
    }
}

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

//! Sweeps beyond one process: the ablation, the trade-off and labelling planned as a manifest of
//! independent tasks ([`plan`], [`manifest`]), each run on its own by any scheduler ([`task`]:
//! Slurm job arrays, GNU parallel, Kubernetes Indexed Jobs), then gathered into the same tables
//! the one-process jobs write ([`gather`]). docs/scale.md says how to submit them.

pub mod gather;
pub mod manifest;
pub mod plan;
pub mod task;

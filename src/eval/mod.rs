//! Evaluation, all of it: the image metrics (PSNR, scaled albedo, MSE, angular error), label and
//! geometry metrics (against a ground-truth mesh), and the NeRFactor protocol that scores a fitted
//! model with them (`protocol`). Above `render` (the protocol renders), below `fit` and `jobs`.

pub mod geometry_metrics;
pub mod label_metrics;
pub mod metrics;
pub mod protocol;

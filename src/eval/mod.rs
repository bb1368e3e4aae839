//! Metrics (PSNR, scaled albedo, MSE, angular error, geometry against a ground-truth mesh) and reports.

pub mod geometry_metrics;
pub mod label_metrics;
pub mod metrics;

//! Metrics (PSNR, scaled albedo, MSE, angular error) and reports.

pub mod label_metrics;
pub mod metrics;

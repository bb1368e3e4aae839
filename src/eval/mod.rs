//! Metrics (PSNR, scaled albedo, MSE, angular error) and reports.

pub mod metrics;

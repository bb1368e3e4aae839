//! What the command line runs: each job is a library function with plain options, so the CLI only
//! parses arguments and prints.

pub mod ablation;
pub mod geometry;
pub mod geometry_cache;
pub mod label;
pub mod overrides;
pub mod reconstruct;
pub mod run_folder;
pub mod run_identity;
pub mod shared_preparation;
pub mod report_markdown;
pub mod render;
pub mod sweep;
pub mod tradeoff;

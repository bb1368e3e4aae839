//! What the command line runs: each job is a library function with plain options, so the CLI only
//! parses arguments and prints.

pub mod ablation;
pub mod geometry;
pub mod label;
pub mod reconstruct;
pub mod report_markdown;
pub mod render;
pub mod sweep;
pub mod tradeoff;

//! reconstruct: shape, material and light from multi-view images by differentiable rendering
//! (NVDiffRecMC-style), optionally guided by IDArb pseudo-labels. See README.md and docs/model.md.

pub mod allocator;
pub mod atomic_write;
pub mod color;
pub mod eval;
pub mod fit;
pub mod geometry;
pub mod image;
pub mod jobs;
pub mod light;
pub mod material;
pub mod math;
pub mod optim;
pub mod prior;
pub mod render;
pub mod report;
pub mod rng;
pub mod scene;
pub mod scene_data;

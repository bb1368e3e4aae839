//! Cameras, views and datasets (NeRFactor / NeRF-synthetic layout), scene specs and light probes.

pub mod camera;
pub mod dataset;
pub mod default_scene;
pub mod ground_truth;
pub mod probe;
pub mod spec;
pub mod synthetic;

pub use camera::Camera;
pub use dataset::{Dataset, Layout, Split, View, ViewMetadata};
pub use ground_truth::{ground_truth_mesh, ground_truth_mesh_path, ground_truth_source, GroundTruthSource};
pub use probe::Probe;
pub use spec::{cache_dir, crate_dir, shared_dir, SceneSpec};

//! Cameras, views and datasets (NeRFactor / NeRF-synthetic layout), scene specs and light probes.

pub mod camera;
pub mod dataset;
pub mod default_scene;
pub mod probe;
pub mod spec;
pub mod synthetic;

pub use camera::Camera;
pub use dataset::{Dataset, Layout, Split, View, ViewMetadata};
pub use probe::Probe;
pub use spec::{cache_dir, crate_dir, shared_dir, SceneSpec};

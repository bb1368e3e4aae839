//! Cameras, views and datasets (NeRFactor / NeRF-synthetic layout), scene specs and light probes.

pub mod camera;
pub mod dataset;
pub mod default_scene;
pub mod probe;
pub mod spec;
pub mod synthetic;

pub use camera::Camera;

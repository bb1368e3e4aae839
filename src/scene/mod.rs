//! Cameras, views and datasets (NeRFactor / NeRF-synthetic layout), scene specs and light probes.

pub mod camera;
pub mod dataset;
pub mod probe;
pub mod spec;

pub use camera::Camera;

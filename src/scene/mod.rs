//! Cameras, views and datasets (NeRFactor / NeRF-synthetic layout), scene specs, the effects a
//! spec switches on, and light probes: what a run is given, described and read. Nothing here draws
//! or builds a mesh, so every layer above may use it; making a scene's data and loading its
//! ground-truth mesh are in `scene_data`, above `render`.

pub mod camera;
pub mod dataset;
pub mod effect_switches;
pub mod probe;
pub mod spec;

pub use camera::Camera;
pub use dataset::{Dataset, Layout, Split, View, ViewMetadata};
pub use effect_switches::{EffectSwitches, Switch};
pub use probe::Probe;
pub use spec::{cache_dir, crate_dir, shared_dir, SceneSpec};

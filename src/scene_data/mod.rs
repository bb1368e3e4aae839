//! A scene's data and ground truth, wherever they come from: the files its spec names, or the
//! project's own generator (the embedded default scene, rendered by the project into the NeRFactor
//! layout). Above `render`, since making data means rendering it; the descriptions these work
//! from (specs, cameras, datasets, probes) are in `scene/`, below everything that draws.

pub mod default_scene;
pub mod ground_truth;
pub mod load_dataset;
pub mod synthetic;

pub use ground_truth::{ground_truth_mesh, ground_truth_mesh_path, ground_truth_source, GroundTruthSource};

//! A scene's ground-truth mesh: whether the scene has one (asked without reading it, e.g. to decide
//! between known and reconstructed geometry) and the mesh with its materials. The spec's
//! `[ground_truth] folder` is looked up inside the data folder; a folder that does not exist means
//! the data carries no ground truth (the original NeRFactor and NeRF-synthetic releases), not an error.

use std::path::PathBuf;

use anyhow::{bail, Context, Result};

use crate::geometry::ground_truth::{find_mesh_file, load_ground_truth};
use crate::geometry::Mesh;
use crate::scene::SceneSpec;

use super::default_scene;

/// Ground-truth folder value meaning "the generator's own mesh" (see scenes/default.toml).
pub const BUILTIN_DEFAULT_GT: &str = "builtin:default";

/// Where a scene's ground-truth mesh comes from.
#[derive(Clone, Debug, PartialEq)]
pub enum GroundTruthSource {
    /// Built by the project's generator (`builtin:default`): no file.
    Builtin,
    /// A mesh file in the ground-truth folder (materials from the folder's `materials.json`, else the file's own).
    File(PathBuf),
}

/// The scene's ground-truth mesh source, or `None` when the spec names no ground-truth folder or
/// the folder is not in the data. Reads only the folder listing and `materials.json`. An existing
/// folder without a usable mesh (none, or several and nothing says which) is an error.
pub fn ground_truth_source(spec: &SceneSpec) -> Result<Option<GroundTruthSource>> {
    let Some(g) = &spec.ground_truth else { return Ok(None) };
    if g.as_os_str() == BUILTIN_DEFAULT_GT {
        return Ok(Some(GroundTruthSource::Builtin));
    }
    let dir = spec.data_dir.join(g);
    if !dir.exists() {
        return Ok(None);
    }
    let file = find_mesh_file(&dir).with_context(|| format!("the ground truth of scene {:?}", spec.name))?;
    Ok(Some(GroundTruthSource::File(file)))
}

/// The ground-truth mesh file, when the scene's data has one (`None` for generated scenes, whose
/// mesh is code; use [`ground_truth_source`] to ask whether there is a ground-truth mesh at all).
pub fn ground_truth_mesh_path(spec: &SceneSpec) -> Result<Option<PathBuf>> {
    Ok(match ground_truth_source(spec)? {
        Some(GroundTruthSource::File(p)) => Some(p),
        _ => None,
    })
}

/// The scene's ground-truth mesh with its materials.
pub fn ground_truth_mesh(spec: &SceneSpec) -> Result<Mesh> {
    match ground_truth_source(spec)? {
        Some(GroundTruthSource::Builtin) => Ok(default_scene::mesh()),
        Some(GroundTruthSource::File(_)) => {
            let dir = spec.gt_dir().context("a file source has a folder")?;
            load_ground_truth(&dir).with_context(|| format!("loading the ground truth of scene {:?}", spec.name))
        }
        None => match spec.gt_dir() {
            Some(dir) => bail!(
                "scene {:?} has no ground-truth mesh: its ground-truth folder {} does not exist (reconstruct the geometry instead: `--geometry reconstruct`)",
                spec.name,
                dir.display()
            ),
            None => bail!("scene {:?} has no ground truth (no [ground_truth] folder in its spec)", spec.name),
        },
    }
}

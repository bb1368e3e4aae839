//! A scene's dataset, made first when the project generates it: `SceneSpec::load_dataset`. The
//! method is defined here, not beside the spec in `scene/spec.rs`, because generating the data
//! (the `default` generator) renders it, and `scene/` sits below the renderer.

use anyhow::{bail, Context, Result};

use crate::scene::{Dataset, SceneSpec};

impl SceneSpec {
    /// Make the data first when the project generates it (rendered once, then cached).
    pub fn load_dataset(&self) -> Result<Dataset> {
        match self.generator.as_deref() {
            None => {}
            Some("default") => super::default_scene::ensure_dataset(&self.data_dir)?,
            Some(other) => bail!("scene {:?}: unknown generator {other:?} (known: \"default\")", self.name),
        }
        if !self.data_dir.is_dir() {
            bail!(
                "scene {:?}: data folder {} not found; pass --data DIR with the scene's data (a folder in the NeRFactor or \
                 NeRF-synthetic layout holding transforms_train.json)",
                self.name,
                self.data_dir.display()
            );
        }
        Dataset::load(&self.data_dir).with_context(|| format!("loading the data of scene {:?}", self.name))
    }
}

//! Prepared data shared by the runs of a study (the ablation's rows, the trade-off's points):
//! loading the scene, the geometry, the atlas and the traced training views are done once for all
//! runs that would prepare the same thing, and again for a run that would not.
//!
//! Two runs prepare the same thing when they train at the same resolution and their geometry has
//! the same identity (`run_identity::GeometryIdentity`). With the scene's mesh, or a reconstruction
//! whose pass weighs no normal prior, that holds across priors, and the study's rows share one
//! geometry, kept in the study's folder. A reconstruction whose pass holds the normals to the
//! prior's labels depends on the prior, so each prior gets its own geometry, kept in the folder of
//! the first run that asked for it: the rows of an ablation then differ in both passes, as in
//! IDArb's experiment, where the prior enters NVDiffRecMC's optimisation of shape and material.

use std::path::{Path, PathBuf};

use anyhow::Result;

use crate::prior::source::PriorSource;

use super::reconstruct::{load_scene, prepare_run, Prepared, ReconstructOptions};
use super::run_identity::{GeometryIdentity, PriorIdentity};

/// The preparations made so far, by what they depend on.
pub struct SharedPreparation {
    /// The study's folder: where a geometry shared across priors is kept.
    folder: PathBuf,
    entries: Vec<((usize, GeometryIdentity), Prepared)>,
}

impl SharedPreparation {
    pub fn new(folder: &Path) -> SharedPreparation {
        SharedPreparation { folder: folder.to_path_buf(), entries: Vec::new() }
    }

    /// The preparation of `run` (its options) with `prior`: one made earlier for a run that
    /// depends on the same things, else a new one.
    pub fn get(&mut self, run: &ReconstructOptions, prior: &PriorSource) -> Result<&Prepared> {
        let (spec, dataset) = load_scene(&run.scene, run.data.as_ref())?;
        let identity = PriorIdentity::of(prior, run.labelled_views, &dataset);
        let geometry = GeometryIdentity::of(&spec, run.geometry, &run.geometry_pass, identity.labels_any().then_some(&identity))?;
        let key = (run.downscale, geometry);
        let k = match self.entries.iter().position(|(k, _)| *k == key) {
            Some(k) => k,
            None => {
                let mut o = run.clone();
                if key.1.labels.is_none() {
                    o.out = self.folder.clone();
                }
                let prepared = prepare_run(&o, prior)?;
                self.entries.push((key, prepared));
                self.entries.len() - 1
            }
        };
        Ok(&self.entries[k].1)
    }

    /// How many different preparations were made.
    pub fn count(&self) -> usize {
        self.entries.len()
    }
}

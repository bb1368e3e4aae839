//! Default run folders: `runs/<scene>-<geometry>-<prior>-<mode>-<digest>`, a readable name
//! followed by the first digits of the run identity's digest ([`RunIdentity::short_digest`]).
//! The readable part says what a folder is at a glance; the digest separates runs that differ in
//! anything else (data, labelled views, forced effects, optimiser settings, seed…), so a rerun of
//! the same command finds its own folder and resumes, and a rerun with one flag changed starts a
//! new one instead of resuming another run's checkpoint. The iteration count is not in the
//! digest: a rerun with more iterations extends the finished run (docs/runs.md).

use std::path::PathBuf;

use anyhow::Result;

use crate::prior::source::PriorSource;

use super::reconstruct::{load_scene, ReconstructOptions};
use super::run_identity::{mode_tag, RunIdentity};

/// Where default run folders go (relative to the working directory).
pub const RUNS_DIR: &str = "runs";

/// `text` with every character but letters, digits, `.`, `-` and `_` replaced by `_`, so a scene
/// path or a `labels:DIR` tag makes one folder name.
pub fn sanitise(text: &str) -> String {
    text.chars().map(|c| if c.is_ascii_alphanumeric() || matches!(c, '.' | '-' | '_') { c } else { '_' }).collect()
}

/// `<scene>-<geometry>-<prior>-<mode>` of a run (the geometry and mode as asked).
pub fn readable_name(scene: &str, opts: &ReconstructOptions, prior: &PriorSource) -> String {
    format!("{}-{}-{}-{}", sanitise(scene), opts.geometry.tag(), sanitise(&prior.tag()), mode_tag(opts.auto_mode, opts.fit.mode))
}

/// The default folder of a run of `opts` with `prior` (loads the scene's spec and view list to
/// take the data's identity; no image is read).
pub fn default_run_folder(opts: &ReconstructOptions, prior: &PriorSource) -> Result<PathBuf> {
    let (spec, dataset) = load_scene(&opts.scene, opts.data.as_ref())?;
    let identity = RunIdentity::new(&spec, &dataset, opts, prior)?;
    Ok(PathBuf::from(RUNS_DIR).join(format!("{}-{}", readable_name(&spec.name, opts, prior), identity.short_digest())))
}

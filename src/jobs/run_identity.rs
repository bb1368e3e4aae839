//! The identity of a run: everything that changes what a reconstruct run produces, as one
//! serialisable record. A checkpoint records it, and a run resumes a checkpoint only when the
//! identities are equal (otherwise each differing setting is named, old → new); the default run
//! folder's name ends with its digest, so runs that differ in any setting land in different
//! folders (docs/runs.md).
//!
//! What it covers: the data folder and its content (a digest of the `transforms_*.json` files'
//! bytes and of every view's image size and file length: cheap, no pixel is read), the resolved
//! scene spec, the geometry source as decided (`auto` resolved) with the ground-truth mesh file or
//! the geometry pass settings, the label source with its level and labelled-view count, the
//! training mode as asked, the forced effects, the training resolution divisor, every optimiser
//! setting and the seed ([`FitConfig::resume_settings`]: the iteration count is left out so a
//! finished run can be extended), the evaluation settings, and once the run has decided them, the
//! effects and training mode it decided. Not covered: wall times and the progress display.

use std::path::PathBuf;

use anyhow::{Context, Result};
use serde::{Deserialize, Serialize};

use crate::fit::config::FitConfig;
use crate::fit::geometry_pass::GeometryPassConfig;
use crate::prior::source::PriorSource;
use crate::render::effects::Effects;
use crate::scene::EffectSwitches;
use crate::render::view::ShadingMode;
use crate::scene::dataset::{Dataset, Split};
use crate::scene::SceneSpec;
use crate::scene_data::{ground_truth_source, GroundTruthSource};

use super::geometry::{pass_settings, resolve_source, GeometrySource};
use super::reconstruct::ReconstructOptions;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RunIdentity {
    pub data: DataIdentity,
    pub scene: SceneIdentity,
    pub geometry: GeometryIdentity,
    pub prior: PriorIdentity,
    pub training: TrainingIdentity,
    pub evaluation: EvaluationIdentity,
    /// What the run decided from the above (set once the geometry is known; not in the digest).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub decided: Option<Decided>,
}

/// The data folder and a digest of its content.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DataIdentity {
    /// The folder, made absolute.
    pub folder: PathBuf,
    /// Digest of the transforms files' bytes and each view's name, image size and file length.
    pub content: String,
    /// Train, validation and test views.
    pub views: [usize; 3],
}

/// The resolved scene spec (paths expanded), minus its description.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SceneIdentity {
    pub name: String,
    pub train_probe: Option<(PathBuf, f32)>,
    pub test_probes: Vec<String>,
    pub test_probe_folders: Vec<PathBuf>,
    pub test_probe_strength: f32,
    pub ground_truth: Option<PathBuf>,
    pub effects: EffectSwitches,
    pub generator: Option<String>,
}

/// Where the mesh comes from, as decided.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct GeometryIdentity {
    /// `ground-truth` or `reconstruct` (`auto` resolved).
    pub source: GeometrySource,
    /// The ground-truth mesh file and its length in bytes (`builtin` for the generated scene).
    pub mesh: Option<String>,
    /// The geometry pass settings (reconstruction only), as the pass runs them
    /// (`jobs::geometry::pass_settings`).
    pub pass: Option<GeometryPassConfig>,
    /// The labels the pass's normal prior holds the mesh to (a reconstruction with a prior whose
    /// pass weighs it); left out otherwise, so identities from before the prior keep their digests.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub labels: Option<PriorIdentity>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PriorIdentity {
    /// The `--prior` tag (none, idarb, labels:DIR, oracle, idarb-sim:LEVEL).
    pub source: String,
    /// Training views labelled (capped at the training views; none without a prior).
    pub labelled_views: Option<usize>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrainingIdentity {
    /// `auto`, or the mode set by the run.
    pub mode: String,
    /// Effects forced instead of the scene's choice (trade-off points).
    pub effects: Option<Effects>,
    /// Training resolution divisor.
    pub downscale: usize,
    /// Every optimiser setting and the seed.
    pub fit: FitConfig,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EvaluationIdentity {
    pub spp: u32,
    pub test_views: Option<usize>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Decided {
    pub effects: Effects,
    pub mode: ShadingMode,
}

/// 64-bit FNV-1a: a stable hash (the same on every machine and compiler version, unlike std's
/// `DefaultHasher`), so a digest written into a folder name today names the same folder tomorrow.
/// Not cryptographic: it tells settings apart, it does not resist forgery.
fn fnv1a(bytes: &[u8], mut h: u64) -> u64 {
    for &b in bytes {
        h ^= b as u64;
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
}

/// FNV-1a's offset basis.
const FNV_START: u64 = 0xcbf2_9ce4_8422_2325;

/// Hex digits of a digest written into folder names: 32 bits, so two of a handful of runs collide
/// with odds of about one in a billion.
pub const SHORT_DIGEST: usize = 8;

/// The digest of a serialisable record (16 hex digits of FNV-1a over its JSON text).
pub fn digest_of<T: Serialize>(value: &T) -> String {
    let text = serde_json::to_string(value).unwrap_or_default();
    format!("{:016x}", fnv1a(text.as_bytes(), FNV_START))
}

impl DataIdentity {
    pub fn of(dataset: &Dataset) -> Result<DataIdentity> {
        let folder = std::fs::canonicalize(&dataset.root).unwrap_or_else(|_| dataset.root.clone());
        let mut h = FNV_START;
        for split in Split::ALL {
            let file = dataset.root.join(format!("transforms_{}.json", split.name()));
            if file.is_file() {
                let bytes = std::fs::read(&file).with_context(|| format!("cannot read {}", file.display()))?;
                h = fnv1a(split.name().as_bytes(), h);
                h = fnv1a(&bytes, h);
            }
            for v in dataset.views(split) {
                let len = std::fs::metadata(&v.image_path).with_context(|| format!("cannot read the size of {}", v.image_path.display()))?.len();
                h = fnv1a(format!("{}:{}x{}:{len};", v.name, v.camera.width, v.camera.height).as_bytes(), h);
            }
        }
        Ok(DataIdentity { folder, content: format!("{h:016x}"), views: [dataset.train.len(), dataset.val.len(), dataset.test.len()] })
    }
}

impl SceneIdentity {
    pub fn of(spec: &SceneSpec) -> SceneIdentity {
        SceneIdentity {
            name: spec.name.clone(),
            train_probe: spec.train_probe.as_ref().map(|p| (p.path.clone(), p.strength)),
            test_probes: spec.test_probes.names.clone(),
            test_probe_folders: spec.test_probes.folders.clone(),
            test_probe_strength: spec.test_probes.strength,
            ground_truth: spec.ground_truth.clone(),
            effects: spec.effects,
            generator: spec.generator.clone(),
        }
    }
}

impl GeometryIdentity {
    /// The identity of the geometry from `source`; a reconstruction's pass holds its normals to
    /// the labels of `prior` (`None`: no prior).
    pub fn of(spec: &SceneSpec, source: GeometrySource, pass: &GeometryPassConfig, prior: Option<&PriorIdentity>) -> Result<GeometryIdentity> {
        let (used, _) = resolve_source(spec, source)?;
        if used != GeometrySource::GroundTruth {
            let pass = pass_settings(pass, prior.is_some());
            let labels = prior.filter(|_| pass.normal_prior > 0.0).cloned();
            return Ok(GeometryIdentity { source: used, mesh: None, pass: Some(pass), labels });
        }
        let mesh = match ground_truth_source(spec)? {
            Some(GroundTruthSource::Builtin) => Some("builtin".to_string()),
            Some(GroundTruthSource::File(f)) => {
                let len = std::fs::metadata(&f).with_context(|| format!("cannot read the size of {}", f.display()))?.len();
                Some(format!("{} ({len} bytes)", f.display()))
            }
            None => None,
        };
        Ok(GeometryIdentity { source: used, mesh, pass: None, labels: None })
    }
}

/// The tag of a training mode as asked: `auto`, else the mode's own tag (`splitsum` or `mc`).
pub fn mode_tag(auto: bool, mode: ShadingMode) -> &'static str {
    if auto {
        "auto"
    } else {
        mode.tag()
    }
}

impl PriorIdentity {
    /// The identity of `prior` labelling `labelled` training views of `dataset` (at most all).
    pub fn of(prior: &PriorSource, labelled: usize, dataset: &Dataset) -> PriorIdentity {
        PriorIdentity { source: prior.tag(), labelled_views: (*prior != PriorSource::None).then(|| labelled.min(dataset.train.len())) }
    }

    /// Whether the prior labels any view.
    pub fn labels_any(&self) -> bool {
        self.labelled_views.is_some_and(|n| n > 0)
    }
}

impl RunIdentity {
    /// The identity of a run of `opts` with `prior`.
    pub fn new(spec: &SceneSpec, dataset: &Dataset, opts: &ReconstructOptions, prior: &PriorSource) -> Result<RunIdentity> {
        let mut fit = opts.fit.resume_settings();
        fit.prior_source = prior.tag();
        let prior = PriorIdentity::of(prior, opts.labelled_views, dataset);
        Ok(RunIdentity {
            data: DataIdentity::of(dataset)?,
            scene: SceneIdentity::of(spec),
            geometry: GeometryIdentity::of(spec, opts.geometry, &opts.geometry_pass, prior.labels_any().then_some(&prior))?,
            prior,
            training: TrainingIdentity { mode: mode_tag(opts.auto_mode, opts.fit.mode).to_string(), effects: opts.effects_override, downscale: opts.downscale, fit },
            evaluation: EvaluationIdentity { spp: opts.eval_spp, test_views: opts.eval_test_views.map(|n| n.min(dataset.test.len())) },
            decided: None,
        })
    }

    /// The same identity with what the run decided.
    pub fn with_decided(mut self, effects: Effects, mode: ShadingMode) -> RunIdentity {
        self.decided = Some(Decided { effects, mode });
        self
    }

    /// The digest of the settings (what was decided left out: it follows from them).
    pub fn digest(&self) -> String {
        let mut asked = self.clone();
        asked.decided = None;
        digest_of(&asked)
    }

    /// The first [`SHORT_DIGEST`] hex digits of [`RunIdentity::digest`], for folder names.
    pub fn short_digest(&self) -> String {
        self.digest()[..SHORT_DIGEST].to_string()
    }

    pub fn to_value(&self) -> Result<serde_json::Value> {
        Ok(serde_json::to_value(self)?)
    }
}

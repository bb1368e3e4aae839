//! Settings of one optimisation run (materials and light on fixed geometry). Defaults follow
//! NVDiffRecMC where it has a counterpart (learning rates, regulariser weights, material clamps), scaled to
//! a CPU budget (texture and light resolution, batch, iterations); each field says where it comes from.

use serde::{Deserialize, Serialize};

use crate::optim::weights::RegularizerWeights;
use crate::render::view::ShadingMode;

/// Weights of the IDArb prior term (docs/model.md, *Loss*); all zero = no prior. Applied only to
/// views that have labels, so with `--prior none` they weigh nothing.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PriorWeights {
    /// Base colour, compared sRGB-encoded (IDArb's albedo space).
    pub albedo: f64,
    pub roughness: f64,
    pub metallic: f64,
    /// The prior weight is multiplied by (1 − t)^anneal at run fraction t (0 = constant).
    pub anneal: f64,
    /// The shading normal against the normal label (in world space, which the L2 norm does not
    /// distinguish from camera space). Only a run whose normals move has a term to add: with the
    /// normal map (`normal_map`) or the vertex refinement (`refine_geometry`). Off by default
    /// (left out of the run identity while 0, so runs without it keep theirs).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub normal: f64,
}

fn is_zero(v: &f64) -> bool {
    *v == 0.0
}

impl Default for PriorWeights {
    fn default() -> Self {
        PriorWeights { albedo: 1.0, roughness: 1.0, metallic: 1.0, anneal: 0.0, normal: 0.0 }
    }
}

impl PriorWeights {
    /// The multiplier of every prior component at `iteration` of `total`.
    pub fn schedule(&self, iteration: usize, total: usize) -> f64 {
        if self.anneal == 0.0 || total == 0 {
            return 1.0;
        }
        (1.0 - (iteration as f64 / total as f64).min(1.0)).powf(self.anneal)
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FitConfig {
    pub mode: ShadingMode,
    /// Monte Carlo samples per pixel and strategy (NVDiffRecMC: 12 for NeRFactor scenes). The
    /// default is 4 with the denoiser on: the L1 fit of a noisy estimate is biased (on the hotdog,
    /// no prior, 1000 iterations, undenoised 4 / 8 / 16 spp relit at 22.7 / 24.3 / 26.2 dB scaled),
    /// and the denoiser removes that bias for less than 16 spp cost: 4 spp denoised relit at
    /// 26.29 dB in 1000 iterations and 26.44 dB in 600 (docs/performance.md, *Four samples and
    /// the denoiser*).
    pub spp: u32,
    /// Cross-bilateral denoiser on the demodulated MC buffers (NVDiffRecMC's default too).
    pub denoise: bool,
    /// Material/light iterations. 600: with 4 denoised spp the hotdog relit as well at 600 as at
    /// 1000 (26.44 against 26.29 dB scaled), in 214 s of optimisation instead of 563 s.
    pub iterations: usize,
    /// Views per iteration.
    pub batch: usize,
    /// Material texture side (kd and ks share the atlas).
    pub texture_res: usize,
    /// Base cube-map face side of the learned light.
    pub light_res: usize,
    /// Adam learning rate of kd and ks.
    pub lr_material: f64,
    /// Adam learning rate of the light.
    pub lr_light: f64,
    /// Linear warm-up steps, then 10× decay per `decay_steps` (NVDiffRecMC: 5000).
    pub warmup_steps: usize,
    pub decay_steps: usize,
    /// Start values, constant (reproducible). NVDiffRecMC's second pass starts from its first
    /// pass's material baked into textures, and its light at 0.5 (docs/model.md, *Differences from
    /// NVDiffRecMC*).
    pub init_kd: f32,
    pub init_roughness: f32,
    pub init_metallic: f32,
    pub init_light: f32,
    pub regularizers: RegularizerWeights,
    pub prior: PriorWeights,
    pub seed: u64,
    /// Iterations between checkpoints (0 = none).
    pub checkpoint_every: usize,
    /// The label source (set by the job; part of the resume settings so a checkpoint made with
    /// another prior is never resumed).
    #[serde(default)]
    pub prior_source: String,
    /// Move the vertices too, through the shading normal (`fit::vertex_refinement`; Monte Carlo
    /// training only). Off by default until measured to help (docs/geometry.md). Left out of
    /// the settings' JSON when off, so the run identities of runs without it are unchanged.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub refine_geometry: bool,
    /// Learn a tangent-space normal map with the textures (`material::normal_map`, NVDiffRecMC's
    /// second pass; Monte Carlo training only). Left out of the settings' JSON when off, like
    /// `refine_geometry`.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub normal_map: bool,
}

impl Default for FitConfig {
    fn default() -> Self {
        FitConfig {
            mode: ShadingMode::SplitSum,
            spp: 4,
            denoise: true,
            iterations: 600,
            batch: 2,
            texture_res: 512,
            light_res: 64,
            lr_material: 0.01,
            lr_light: 0.03,
            warmup_steps: 50,
            decay_steps: 5000,
            init_kd: 0.5,
            init_roughness: 0.6,
            init_metallic: 0.0,
            init_light: 0.5,
            regularizers: RegularizerWeights::default(),
            prior: PriorWeights::default(),
            seed: 0,
            checkpoint_every: 100,
            prior_source: "none".into(),
            refine_geometry: false,
            normal_map: false,
        }
    }
}

impl FitConfig {
    /// The settings a run must share with a checkpoint to resume it: everything but the
    /// bookkeeping (`checkpoint_every`) and the run's length (`iterations`, so a finished run can be
    /// extended: nothing else in a step depends on the total), unless the prior anneals over the
    /// run's length (then every step's prior weight depends on it).
    pub fn resume_settings(&self) -> FitConfig {
        let mut c = self.clone();
        if self.prior.anneal == 0.0 {
            c.iterations = 0;
        }
        c.checkpoint_every = 0;
        c
    }
}

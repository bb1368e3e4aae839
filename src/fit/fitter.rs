//! The optimisation loop: batches of views → differentiable render → loss → backward → Adam (per
//! parameter group, warm-up and decay, clamps), with a progress bar and checkpoints a rerun resumes.
//! With `FitConfig::refine_geometry` each step also moves the mesh (`vertex_refinement`); with
//! `FitConfig::normal_map` a tangent-space normal map is learned with the textures.

use std::path::Path;
use std::sync::Arc;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use obvhs::BvhBuildParams;

use crate::geometry::bvh::Bvh;
use crate::geometry::Mesh;

use crate::geometry::tangents::corner_tangents;
use crate::material::brdf::MIN_ROUGHNESS;
use crate::material::normal_map::{NormalMap, NORMAL_MAX, NORMAL_MIN};
use crate::optim::adam::{Adam, GroupConfig, LrSchedule};
use crate::optim::adam::set_var;
use crate::render::view::ShadingMode;
use crate::rng::Sampler;

use super::batch_render::{render_batch, ShadingContext};
use super::checkpoint::{self, Progress};
use super::config::FitConfig;
use super::history::{trailing_mean, IterationRecord, StepPhases};
use super::objective::{objective, smoothness_jitter_seed};
use super::settings_diff::differences;
use super::parameters::{NormalParameter, Parameters, NORMAL_NAME};
use super::training_view::TrainingView;
use super::vertex_refinement::VertexRefinement;

/// Lower clamp of the light's radiance after each step: 0, the physical floor. NVDiffRecMC clamps at
/// 0.01 (its comment: the light's gradient vanished at 0); docs/model.md, *Differences from NVDiffRecMC*.
pub const LIGHT_MIN: f64 = 0.0;

pub struct Fit {
    pub config: FitConfig,
    pub params: Parameters,
    pub views: Vec<TrainingView>,
    pub ctx: ShadingContext,
    pub history: Vec<IterationRecord>,
    adam: Adam,
    /// The moving mesh, with `config.refine_geometry` (`ctx.mesh` and `ctx.bvh` follow it).
    refine: Option<VertexRefinement>,
    /// What a checkpoint must match to be resumed: by default the fit's own settings
    /// ([`Fit::own_identity`]); a job replaces it with its run identity ([`Fit::set_identity`]).
    identity: serde_json::Value,
}

fn optimiser(config: &FitConfig, params: &Parameters) -> Result<Adam> {
    let mut adam = Adam::new(LrSchedule { warmup_steps: config.warmup_steps, decay_steps: config.decay_steps, staircase: false });
    adam.add_group(GroupConfig::new("kd", config.lr_material).with_clamp(0.0, 1.0), vec![params.kd.clone()])?;
    adam.add_group(
        // The roughness channel stops at the BRDF's own floor (NVDiffRecMC's 0.08 too): the BRDF
        // clamps there, so a texel below it would render as the floor. ks is f32, so the bound is
        // exactly MIN_ROUGHNESS.
        GroupConfig::new("ks", config.lr_material).with_channel_clamp(&[0.0, MIN_ROUGHNESS as f64, 0.0], &[0.0, 1.0, 1.0]),
        vec![params.ks.clone()],
    )?;
    adam.add_group(GroupConfig::new("light", config.lr_light).with_clamp(LIGHT_MIN, f64::MAX), vec![params.light.clone()])?;
    if let (true, Some(n)) = (config.normal_map, &params.normal) {
        // NVDiffRecMC's rate for its normal map: the material's.
        adam.add_group(GroupConfig::new(NORMAL_NAME, config.lr_material).with_channel_clamp(&NORMAL_MIN, &NORMAL_MAX), vec![n.map.clone()])?;
    }
    Ok(adam)
}

impl Fit {
    /// A run from `params` (e.g. `Parameters::initial(&config)`).
    pub fn new(config: FitConfig, mut params: Parameters, views: Vec<TrainingView>, ctx: ShadingContext) -> Result<Fit> {
        if views.is_empty() || views.iter().all(|v| v.is_empty()) {
            bail!("nothing to optimise: no training view sees the mesh");
        }
        if config.batch == 0 {
            bail!("batch size must be at least 1");
        }
        if config.prior.normal > 0.0 && !config.normal_map && !config.refine_geometry {
            bail!("the normal prior (--prior-normal) needs shading normals that move: add --normal-map or --refine-geometry");
        }
        if config.normal_map {
            if config.mode != ShadingMode::MonteCarlo {
                bail!("the normal map (--normal-map) needs Monte Carlo training (--mode mc): the split-sum operator has no normal input");
            }
            if params.normal.is_none() {
                params.normal = Some(NormalParameter::from_map(&NormalMap::flat(config.texture_res, corner_tangents(&ctx.mesh)?.into()))?);
            }
        }
        let adam = optimiser(&config, &params)?;
        let identity = Self::own_identity(&config, &ctx)?;
        let refine = if config.refine_geometry {
            if config.mode != ShadingMode::MonteCarlo {
                bail!("vertex refinement (--refine-geometry) needs Monte Carlo training (--mode mc): the split-sum operator has no normal input");
            }
            Some(VertexRefinement::new(&ctx.mesh)?)
        } else {
            None
        };
        Ok(Fit { config, params, views, ctx, history: Vec::new(), adam, refine, identity })
    }

    /// The fit's own resume identity: its settings without bookkeeping
    /// ([`FitConfig::resume_settings`]) and the effects it shades with.
    pub fn own_identity(config: &FitConfig, ctx: &ShadingContext) -> Result<serde_json::Value> {
        Ok(serde_json::json!({ "fit": serde_json::to_value(config.resume_settings())?, "effects": serde_json::to_value(ctx.effects)? }))
    }

    /// Sets what a checkpoint must match to be resumed (a job's run identity, which must cover
    /// this fit's settings), and what checkpoints record.
    pub fn set_identity(&mut self, identity: serde_json::Value) {
        self.identity = identity;
    }

    /// The refined mesh at its current positions (None without refinement).
    pub fn refined_mesh(&self) -> Option<Mesh> {
        self.refine.as_ref().map(VertexRefinement::mesh)
    }

    /// Iterations done.
    pub fn iteration(&self) -> usize {
        self.history.len()
    }

    /// The views of iteration `it`: consecutive slices of a seeded permutation per epoch, so a
    /// resumed run sees the same batches as an uninterrupted one.
    pub fn batch_for(&self, it: usize) -> Vec<usize> {
        let n = self.views.len();
        let b = self.config.batch.min(n);
        // A batch spans at most two epochs: shuffle each one once.
        let mut epochs: Vec<(usize, Vec<usize>)> = Vec::with_capacity(2);
        (0..b)
            .map(|k| {
                let slot = it * b + k;
                let (epoch, pos) = (slot / n, slot % n);
                if !epochs.iter().any(|(e, _)| *e == epoch) {
                    epochs.push((epoch, self.epoch_order(epoch)));
                }
                epochs.iter().find(|(e, _)| *e == epoch).map_or(pos, |(_, order)| order[pos])
            })
            .collect()
    }

    /// The seeded visiting order of epoch `epoch` (Fisher–Yates).
    fn epoch_order(&self, epoch: usize) -> Vec<usize> {
        let n = self.views.len();
        let mut order: Vec<usize> = (0..n).collect();
        let mut rng = Sampler::new(self.config.seed, 0x5eed_0000 + epoch as u64);
        for i in (1..n).rev() {
            let j = ((rng.next_f32() * (i + 1) as f32) as usize).min(i);
            order.swap(i, j);
        }
        order
    }

    /// One gradient step; returns its record.
    pub fn step(&mut self) -> Result<IterationRecord> {
        let t = Instant::now();
        let it = self.iteration();
        let indices = self.batch_for(it);
        // With refinement: the mesh at the current positions, its BVH, the batch retraced on it.
        let moved = match &self.refine {
            Some(r) => {
                let mesh = Arc::new(r.mesh());
                let bvh = Arc::new(Bvh::build_with(&mesh, BvhBuildParams::fastest_build()));
                let views: Vec<TrainingView> = indices.iter().map(|&i| self.views[i].retraced(&mesh, &bvh)).collect();
                self.ctx.mesh = mesh;
                self.ctx.bvh = bvh;
                Some(views)
            }
            None => None,
        };
        let batch: Vec<&TrainingView> = match &moved {
            Some(views) => views.iter().collect(),
            None => indices.iter().map(|&i| &self.views[i]).collect(),
        };
        let refine_step = self.refine.as_ref().map(|r| r.begin_step(&batch)).transpose()?;
        let phase = Instant::now();
        let jitter = smoothness_jitter_seed(&self.config, &self.params, it);
        let render = render_batch(&batch, &self.params, &self.ctx, it as u64, refine_step.as_ref().map(|s| &s.normals), jitter)?;
        let (render_s, phase) = (phase.elapsed().as_secs_f64(), Instant::now());
        let (loss, terms) = objective(&batch, &render, &self.params, &self.config, it)?;
        let (loss_s, phase) = (phase.elapsed().as_secs_f64(), Instant::now());
        if !terms.total.is_finite() {
            bail!("the loss became non-finite at iteration {it} (terms: {terms:?}); lower the learning rates or check the inputs");
        }
        let grads = loss.backward()?;
        let (backward_s, phase) = (phase.elapsed().as_secs_f64(), Instant::now());
        let lr_factor = self.adam.lr_factor();
        self.adam.step(&grads)?;
        if let (true, Some(n)) = (self.config.normal_map, &self.params.normal) {
            n.normalize()?;
        }
        if let (Some(r), Some(s)) = (self.refine.as_mut(), &refine_step) {
            r.end_step(s, &grads, lr_factor, it)?;
        }
        let phases = StepPhases { render: render_s, loss: loss_s, backward: backward_s, update: phase.elapsed().as_secs_f64() };
        let record = IterationRecord { iteration: it, terms, lr_factor, seconds: t.elapsed().as_secs_f64(), phases };
        self.history.push(record.clone());
        Ok(record)
    }

    /// Loads the checkpoint in `dir` if there is one; returns whether it did. A checkpoint of
    /// another run identity is refused with each differing setting named (old → new), and so is
    /// one already past `config.iterations`.
    pub fn resume(&mut self, dir: &Path) -> Result<bool> {
        let Some(cp) = checkpoint::load(dir)? else { return Ok(false) };
        if cp.progress.identity != self.identity {
            let lines: Vec<String> = differences(&cp.progress.identity, &self.identity).iter().map(|d| format!("  {d}")).collect();
            bail!(
                "the checkpoint in {} belongs to another run; these settings differ (checkpoint → this run):\n{}\n\
                 rerun with the checkpoint's settings, choose another run folder (--out), or delete {} to start afresh",
                dir.display(),
                lines.join("\n"),
                dir.display()
            );
        }
        if cp.progress.iteration > self.config.iterations {
            bail!(
                "the checkpoint in {} is at iteration {}, past this run's {} iterations; pass at least --iterations {} or choose another run folder (--out)",
                dir.display(),
                cp.progress.iteration,
                self.config.iterations,
                cp.progress.iteration
            );
        }
        set_var(&self.params.kd, &cp.kd).context("checkpoint kd")?;
        set_var(&self.params.ks, &cp.ks).context("checkpoint ks")?;
        set_var(&self.params.light, &cp.light).context("checkpoint light")?;
        if let Some(n) = &self.params.normal {
            let map = cp.extra.get(NORMAL_NAME).with_context(|| format!("the checkpoint in {} has no normal map", dir.display()))?;
            set_var(&n.map, map).context("checkpoint normal map")?;
        }
        self.adam.restore(&cp.adam)?;
        if let Some(r) = self.refine.as_mut() {
            r.restore(&cp.extra).with_context(|| format!("resuming the vertex refinement from {}", dir.display()))?;
        }
        self.history = cp.progress.history;
        Ok(true)
    }

    pub fn save_checkpoint(&self, dir: &Path) -> Result<()> {
        let state = self.adam.state()?;
        let mut progress = Progress {
            iteration: self.iteration(),
            state_file: String::new(),
            identity: self.identity.clone(),
            history: self.history.clone(),
            adam_step: state.step,
            adam_slots: state.slots.iter().map(|(k, _, _, s)| (k.clone(), *s)).collect(),
        };
        let mut extra = match &self.refine {
            Some(r) => r.checkpoint_tensors()?,
            None => Vec::new(),
        };
        if let Some(n) = &self.params.normal {
            extra.push((NORMAL_NAME.to_string(), n.map.as_tensor().clone()));
        }
        checkpoint::save(dir, self.params.kd.as_tensor(), self.params.ks.as_tensor(), self.params.light.as_tensor(), &state, extra, &mut progress)
    }

    /// Runs until `config.iterations`, checkpointing into `checkpoint_dir` every
    /// `config.checkpoint_every` iterations and at the end.
    pub fn run(&mut self, checkpoint_dir: Option<&Path>, show_progress: bool) -> Result<()> {
        let total = self.config.iterations;
        let bar = if show_progress { ProgressBar::new(total as u64) } else { ProgressBar::hidden() };
        bar.set_style(
            ProgressStyle::with_template("{prefix} [{bar:30}] {pos}/{len} {msg} (ETA {eta})")
                .map_err(|e| anyhow::anyhow!("progress bar template: {e}"))?
                .progress_chars("=> "),
        );
        bar.set_prefix(format!("{:?}", self.ctx.mode));
        bar.set_position(self.iteration() as u64);
        while self.iteration() < total {
            self.step()?;
            let it = self.iteration();
            let loss = trailing_mean(&self.history, 20, |r| r.terms.total);
            let psnr = trailing_mean(&self.history, 20, |r| r.terms.psnr);
            bar.set_message(format!("loss {loss:.4} PSNR {psnr:.2} dB"));
            bar.set_position(it as u64);
            if let Some(dir) = checkpoint_dir {
                let every = self.config.checkpoint_every;
                if (every > 0 && it.is_multiple_of(every)) || it == total {
                    self.save_checkpoint(dir)?;
                }
            }
        }
        bar.finish();
        Ok(())
    }
}

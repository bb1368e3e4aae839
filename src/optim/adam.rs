//! Adam (Kingma & Ba) per parameter group, with NVDiffRecMC's schedule and house-keeping:
//! learning-rate warm-up then exponential decay (10× per `decay_steps`), a per-group gradient scale
//! (NVDiffRecMC scales the light's gradient by 64; the fit here uses 1), and a clamp after every
//! step (the fit's: kd ∈ [0, 1], roughness ∈ [0.08, 1], light ≥ 0; docs/model.md, *Optimiser*).
//! No weight decay.
//!
//! The update runs in place on the `Var`'s storage as one rayon pass per tensor (m, v and the
//! parameter touched once), with the same formula as torch.optim.Adam:
//!   m ← β₁m + (1−β₁)g,  v ← β₂v + (1−β₂)g²,  p ← p − lr_t · (m/(1−β₁ᵗ)) / (√(v/(1−β₂ᵗ)) + ε),
//! t counted per tensor (a tensor that gets no gradient in a step is not touched at all).
//!
//! NVDiffRecMC's settings, for reference: material lr 0.01 (kd clamp [0, 1], ks clamp per channel
//! (0, 0.08, 0)–(0, 1, 1)), light lr 3× the material lr with gradient ×64 and clamp ≥ 0.01,
//! vertex positions their own lr; all with the same schedule.

use std::cell::RefCell;

use anyhow::{bail, Context};
use candle_core::backprop::GradStore;
use candle_core::{CpuStorage, DType, InplaceOp2, Layout, Tensor, Var};
use rayon::prelude::*;

use super::tape::{contiguous_slice, Real};

/// Learning-rate multiplier over steps: linear warm-up to 1 over `warmup_steps`, then
/// 10^(−(step − warmup)/decay_steps) (continuous; `staircase` makes it drop 10× at once every
/// `decay_steps`). NVDiffRecMC uses the continuous form with decay over 5000 steps; its warm-up
/// starts at 0 (a wasted first step), ours at 1/warmup.
#[derive(Clone, Copy, Debug)]
pub struct LrSchedule {
    pub warmup_steps: usize,
    pub decay_steps: usize,
    pub staircase: bool,
}

impl Default for LrSchedule {
    fn default() -> Self {
        LrSchedule { warmup_steps: 0, decay_steps: 5000, staircase: false }
    }
}

impl LrSchedule {
    /// The multiplier for step `step` (0-based).
    pub fn factor(&self, step: usize) -> f64 {
        if step < self.warmup_steps {
            return (step + 1) as f64 / self.warmup_steps as f64;
        }
        if self.decay_steps == 0 {
            return 1.0;
        }
        let after = (step - self.warmup_steps) as f64 / self.decay_steps as f64;
        let exponent = if self.staircase { after.floor() } else { after };
        10f64.powf(-exponent)
    }
}

/// Hyper-parameters of one group of tensors.
#[derive(Clone, Debug)]
pub struct GroupConfig {
    pub name: String,
    pub lr: f64,
    pub beta1: f64,
    pub beta2: f64,
    pub eps: f64,
    /// The gradient is multiplied by this before the update (light: 64 in NVDiffRecMC).
    pub grad_scale: f64,
    /// Clamp after each step: `(lo, hi)` per channel of the last dimension (one entry = the same
    /// range for every element, e.g. kd ∈ [0, 1]; three entries for ks [H, W, 3] =
    /// (occlusion, roughness, metallic) ranges).
    pub clamp: Option<(Vec<f64>, Vec<f64>)>,
}

impl GroupConfig {
    /// torch's defaults: β = (0.9, 0.999), ε = 1e-8, no scale, no clamp.
    pub fn new(name: &str, lr: f64) -> Self {
        GroupConfig { name: name.into(), lr, beta1: 0.9, beta2: 0.999, eps: 1e-8, grad_scale: 1.0, clamp: None }
    }
    pub fn with_clamp(mut self, lo: f64, hi: f64) -> Self {
        self.clamp = Some((vec![lo], vec![hi]));
        self
    }
    /// Per-channel ranges over the last dimension (see `clamp`).
    pub fn with_channel_clamp(mut self, lo: &[f64], hi: &[f64]) -> Self {
        self.clamp = Some((lo.to_vec(), hi.to_vec()));
        self
    }
    pub fn with_grad_scale(mut self, s: f64) -> Self {
        self.grad_scale = s;
        self
    }
}

enum Moments {
    F32 { m: Vec<f32>, v: Vec<f32> },
    F64 { m: Vec<f64>, v: Vec<f64> },
}

struct Slot {
    var: Var,
    moments: Moments,
    steps: u64,
}

struct Group {
    config: GroupConfig,
    slots: Vec<Slot>,
}

/// Adam over named groups of `Var`s.
pub struct Adam {
    groups: Vec<Group>,
    schedule: LrSchedule,
    step: usize,
}

impl Adam {
    pub fn new(schedule: LrSchedule) -> Self {
        Adam { groups: Vec::new(), schedule, step: 0 }
    }

    /// The same optimiser with its schedule already at `step` (fresh moments): for a run whose
    /// parameters are replaced part-way, such as the geometry pass after a remesh.
    pub fn starting_at(mut self, step: usize) -> Self {
        self.step = step;
        self
    }

    /// Adds a group; its tensors must be contiguous f32 or f64 CPU `Var`s.
    pub fn add_group(&mut self, config: GroupConfig, vars: Vec<Var>) -> anyhow::Result<()> {
        if let Some((lo, hi)) = &config.clamp {
            if lo.is_empty() || lo.len() != hi.len() || lo.iter().zip(hi).any(|(l, h)| l.partial_cmp(h).is_none_or(|o| o.is_gt())) {
                bail!("Adam group '{}': clamp ranges {lo:?} .. {hi:?} are empty, unequal in length or inverted", config.name);
            }
        }
        let mut slots = Vec::with_capacity(vars.len());
        for (i, var) in vars.into_iter().enumerate() {
            if let Some((lo, _)) = &config.clamp {
                if lo.len() > 1 && var.dims().last() != Some(&lo.len()) {
                    bail!(
                        "Adam group '{}': tensor {i} of shape {:?} does not end in the {} clamp channels",
                        config.name,
                        var.dims(),
                        lo.len()
                    );
                }
            }
            let n = var.elem_count();
            let moments = match var.dtype() {
                DType::F32 => Moments::F32 { m: vec![0.0; n], v: vec![0.0; n] },
                DType::F64 => Moments::F64 { m: vec![0.0; n], v: vec![0.0; n] },
                other => bail!("Adam group '{}': tensor {i} has dtype {other:?}, expected f32 or f64", config.name),
            };
            if !var.as_tensor().is_contiguous() {
                bail!("Adam group '{}': tensor {i} is not contiguous", config.name);
            }
            slots.push(Slot { var, moments, steps: 0 });
        }
        self.groups.push(Group { config, slots });
        Ok(())
    }

    /// Steps taken so far.
    pub fn steps(&self) -> usize {
        self.step
    }

    /// The schedule's multiplier for the next step.
    pub fn lr_factor(&self) -> f64 {
        self.schedule.factor(self.step)
    }

    /// The learning rate group `g` uses in the next step.
    pub fn current_lr(&self, g: usize) -> f64 {
        self.groups[g].config.lr * self.schedule.factor(self.step)
    }

    /// One update of every tensor that has a gradient in `grads`, then the clamps.
    pub fn step(&mut self, grads: &GradStore) -> anyhow::Result<()> {
        let factor = self.schedule.factor(self.step);
        for group in &mut self.groups {
            let cfg = &group.config;
            for (i, slot) in group.slots.iter_mut().enumerate() {
                let Some(grad) = grads.get(slot.var.as_tensor()) else { continue };
                if grad.dims() != slot.var.dims() {
                    bail!("Adam group '{}', tensor {i}: gradient {:?} does not match parameter {:?}", cfg.name, grad.dims(), slot.var.dims());
                }
                let grad = grad.to_dtype(slot.var.dtype())?.contiguous()?;
                slot.steps += 1;
                let update = AdamUpdate {
                    lr: cfg.lr * factor,
                    beta1: cfg.beta1,
                    beta2: cfg.beta2,
                    eps: cfg.eps,
                    grad_scale: cfg.grad_scale,
                    clamp: cfg.clamp.as_ref(),
                    step: slot.steps,
                    moments: RefCell::new(&mut slot.moments),
                };
                slot.var
                    .as_tensor()
                    .inplace_op2(&grad, &update)
                    .with_context(|| format!("Adam group '{}', tensor {i}", cfg.name))?;
            }
        }
        self.step += 1;
        Ok(())
    }
}

/// The fused in-place update of one tensor.
struct AdamUpdate<'a> {
    lr: f64,
    beta1: f64,
    beta2: f64,
    eps: f64,
    grad_scale: f64,
    clamp: Option<&'a (Vec<f64>, Vec<f64>)>,
    step: u64,
    moments: RefCell<&'a mut Moments>,
}

impl AdamUpdate<'_> {
    fn run<T: Real>(&self, p: &mut [T], g: &[T], m: &mut [T], v: &mut [T]) {
        let t = self.step as i32;
        let bc1 = 1.0 - self.beta1.powi(t);
        let bc2 = 1.0 - self.beta2.powi(t);
        // p -= lr/bc1 · m / (√v/√bc2 + ε)
        let step_size = T::from_f64(self.lr / bc1);
        let inv_sqrt_bc2 = T::from_f64(1.0 / bc2.sqrt());
        let (b1, b2) = (T::from_f64(self.beta1), T::from_f64(self.beta2));
        let (one, eps, scale) = (T::one(), T::from_f64(self.eps), T::from_f64(self.grad_scale));
        let (lo, hi): (Vec<T>, Vec<T>) = match self.clamp {
            Some((lo, hi)) => (lo.iter().map(|&v| T::from_f64(v)).collect(), hi.iter().map(|&v| T::from_f64(v)).collect()),
            None => (vec![T::from_f64(f64::NEG_INFINITY)], vec![T::from_f64(f64::INFINITY)]),
        };
        // Blocks are whole multiples of the channel count, so element k of a block has channel k mod nc.
        let nc = lo.len();
        let block = nc * 4096usize.div_ceil(nc);
        p.par_chunks_mut(block).zip(g.par_chunks(block)).zip(m.par_chunks_mut(block).zip(v.par_chunks_mut(block))).for_each(
            |((p, g), (m, v))| {
                for (k, (((p, &g), m), v)) in p.iter_mut().zip(g).zip(m.iter_mut()).zip(v.iter_mut()).enumerate() {
                    let g = g * scale;
                    *m = b1 * *m + (one - b1) * g;
                    *v = b2 * *v + (one - b2) * g * g;
                    let np = *p - step_size * *m / (v.sqrt() * inv_sqrt_bc2 + eps);
                    let c = k % nc;
                    *p = np.fmax(lo[c]).fmin(hi[c]);
                }
            },
        );
    }
}

impl InplaceOp2 for AdamUpdate<'_> {
    fn name(&self) -> &'static str {
        "adam"
    }

    fn cpu_fwd(&self, s1: &mut CpuStorage, l1: &Layout, s2: &CpuStorage, l2: &Layout) -> candle_core::Result<()> {
        let (a, b) = l1.contiguous_offsets().ok_or(candle_core::Error::RequiresContiguous { op: "adam" })?;
        let mut moments = self.moments.borrow_mut();
        match (s1, &mut **moments) {
            (CpuStorage::F32(p), Moments::F32 { m, v }) => self.run(&mut p[a..b], contiguous_slice::<f32>("adam", s2, l2)?, m, v),
            (CpuStorage::F64(p), Moments::F64 { m, v }) => self.run(&mut p[a..b], contiguous_slice::<f64>("adam", s2, l2)?, m, v),
            _ => return Err(candle_core::Error::Msg("adam: parameter dtype changed".into())),
        }
        Ok(())
    }
}

/// Adam state is tied to the `Var`s it was built with; expose them for checkpoints and clamps.
impl Adam {
    pub fn vars(&self, g: usize) -> impl Iterator<Item = &Var> {
        self.groups[g].slots.iter().map(|s| &s.var)
    }
    pub fn group_names(&self) -> impl Iterator<Item = &str> {
        self.groups.iter().map(|g| g.config.name.as_str())
    }
}

/// The moments and step counts of every tensor, keyed `group/index/{m,v}`, for checkpoints.
pub struct AdamState {
    pub step: usize,
    /// (key, first moment, second moment, steps of this tensor).
    pub slots: Vec<(String, Tensor, Tensor, u64)>,
}

impl Adam {
    pub fn state(&self) -> anyhow::Result<AdamState> {
        let mut slots = Vec::new();
        for g in &self.groups {
            for (i, s) in g.slots.iter().enumerate() {
                let shape = s.var.dims();
                let dev = s.var.device();
                let (m, v) = match &s.moments {
                    Moments::F32 { m, v } => (Tensor::from_slice(m, shape, dev)?, Tensor::from_slice(v, shape, dev)?),
                    Moments::F64 { m, v } => (Tensor::from_slice(m, shape, dev)?, Tensor::from_slice(v, shape, dev)?),
                };
                slots.push((format!("{}/{i}", g.config.name), m, v, s.steps));
            }
        }
        Ok(AdamState { step: self.step, slots })
    }

    /// Restores a state taken from an optimiser with the same groups and shapes.
    pub fn restore(&mut self, state: &AdamState) -> anyhow::Result<()> {
        let mut it = state.slots.iter();
        for g in &mut self.groups {
            for (i, s) in g.slots.iter_mut().enumerate() {
                let key = format!("{}/{i}", g.config.name);
                let Some((k, m, v, steps)) = it.next() else { bail!("optimiser state has no entry for {key}") };
                if *k != key || m.dims() != s.var.dims() || v.dims() != s.var.dims() {
                    bail!("optimiser state entry {k} {:?} does not match {key} {:?}", m.dims(), s.var.dims());
                }
                s.moments = match &s.moments {
                    Moments::F32 { .. } => Moments::F32 { m: m.flatten_all()?.to_dtype(DType::F32)?.to_vec1()?, v: v.flatten_all()?.to_dtype(DType::F32)?.to_vec1()? },
                    Moments::F64 { .. } => Moments::F64 { m: m.flatten_all()?.to_dtype(DType::F64)?.to_vec1()?, v: v.flatten_all()?.to_dtype(DType::F64)?.to_vec1()? },
                };
                s.steps = *steps;
            }
        }
        if it.next().is_some() {
            bail!("optimiser state has more tensors than the optimiser");
        }
        self.step = state.step;
        Ok(())
    }
}

/// Overwrites a parameter's values (e.g. from an initial guess), converting the dtype.
pub fn set_var(var: &Var, values: &Tensor) -> anyhow::Result<()> {
    var.set(&values.to_dtype(var.dtype())?).context("setting a parameter tensor")
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    #[test]
    fn first_two_steps_match_hand_computed_adam() -> anyhow::Result<()> {
        let x = Var::new(&[1.0f64, -2.0], &Device::Cpu)?;
        let mut adam = Adam::new(LrSchedule { warmup_steps: 0, decay_steps: 0, staircase: false });
        let (lr, b1, b2, eps) = (0.1, 0.9, 0.999, 1e-8);
        adam.add_group(GroupConfig::new("x", lr), vec![x.clone()])?;
        // L = Σ 3x² → g = 6x.
        let (mut p, mut m, mut v) = ([1.0f64, -2.0], [0.0f64; 2], [0.0f64; 2]);
        for t in 1..=2 {
            let loss = (x.as_tensor().sqr()? * 3.0)?.sum_all()?;
            adam.step(&loss.backward()?)?;
            for k in 0..2 {
                let g = 6.0 * p[k];
                m[k] = b1 * m[k] + (1.0 - b1) * g;
                v[k] = b2 * v[k] + (1.0 - b2) * g * g;
                let mh = m[k] / (1.0 - f64::powi(b1, t));
                let vh = v[k] / (1.0 - f64::powi(b2, t));
                p[k] -= lr * mh / (vh.sqrt() + eps);
            }
            let got = x.as_tensor().to_vec1::<f64>()?;
            for k in 0..2 {
                assert!((got[k] - p[k]).abs() < 1e-12, "step {t}: {} vs {}", got[k], p[k]);
            }
        }
        // The first Adam step moves every coordinate by lr (bias correction makes m̂/√v̂ = sign g).
        Ok(())
    }

    #[test]
    fn converges_on_a_quadratic_and_respects_clamps() -> anyhow::Result<()> {
        let dev = Device::Cpu;
        let target = Tensor::new(&[0.3f32, 0.7, -0.5, 2.0], &dev)?;
        let x = Var::zeros(4, DType::F32, &dev)?;
        let mut adam = Adam::new(LrSchedule { warmup_steps: 10, decay_steps: 300, staircase: false });
        adam.add_group(GroupConfig::new("kd", 0.05).with_clamp(0.0, 1.0), vec![x.clone()])?;
        for _ in 0..600 {
            let loss = (x.as_tensor() - &target)?.sqr()?.sum_all()?;
            adam.step(&loss.backward()?)?;
            let v = x.as_tensor().to_vec1::<f32>()?;
            assert!(v.iter().all(|&a| (0.0..=1.0).contains(&a)), "{v:?}");
        }
        let v = x.as_tensor().to_vec1::<f32>()?;
        let want = [0.3, 0.7, 0.0, 1.0];
        for k in 0..4 {
            assert!((v[k] - want[k]).abs() < 1e-3, "{v:?}");
        }
        Ok(())
    }

    #[test]
    fn per_channel_clamp_holds_for_ks_like_tensors() -> anyhow::Result<()> {
        let dev = Device::Cpu;
        // [N, 3] = (occlusion, roughness, metallic), pushed far outside every range.
        let ks = Var::from_tensor(&Tensor::new(&[[0.5f32, 0.5, 0.5]], &dev)?.repeat((5000, 1))?)?;
        let mut adam = Adam::new(LrSchedule::default());
        adam.add_group(GroupConfig::new("ks", 0.5).with_channel_clamp(&[0.0, 0.08, 0.0], &[0.0, 1.0, 1.0]), vec![ks.clone()])?;
        for sign in [1.0f64, -1.0] {
            for _ in 0..40 {
                let loss = (ks.as_tensor().sum_all()? * sign)?;
                adam.step(&loss.backward()?)?;
            }
            let v = ks.as_tensor().to_vec2::<f32>()?;
            let want = if sign > 0.0 { [0.0, 0.08, 0.0] } else { [0.0, 1.0, 1.0] };
            assert!(v.iter().all(|row| row.iter().zip(&want).all(|(a, b)| (a - b).abs() < 1e-6)), "{:?}", &v[..2]);
        }
        let bad = GroupConfig::new("ks", 0.1).with_channel_clamp(&[0.0, 0.0], &[1.0, 1.0]);
        assert!(Adam::new(LrSchedule::default()).add_group(bad, vec![ks]).is_err());
        Ok(())
    }

    #[test]
    fn schedule_warms_up_then_decays_tenfold() {
        let s = LrSchedule { warmup_steps: 4, decay_steps: 100, staircase: false };
        assert_eq!(s.factor(0), 0.25);
        assert_eq!(s.factor(3), 1.0);
        assert!((s.factor(4) - 1.0).abs() < 1e-12);
        assert!((s.factor(104) - 0.1).abs() < 1e-12);
        assert!((s.factor(204) - 0.01).abs() < 1e-12);
        let st = LrSchedule { staircase: true, ..s };
        assert_eq!(st.factor(103), 1.0);
        assert!((st.factor(104) - 0.1).abs() < 1e-12);
    }

    #[test]
    fn grad_scale_scales_the_gradient_and_missing_grads_skip() -> anyhow::Result<()> {
        let dev = Device::Cpu;
        // With ε large, Adam's step is ≈ lr·g·scale/ε on the first step: scale must show.
        let a = Var::new(&[1.0f64], &dev)?;
        let b = Var::new(&[1.0f64], &dev)?;
        let unused = Var::new(&[5.0f64], &dev)?;
        let mut adam = Adam::new(LrSchedule { warmup_steps: 0, decay_steps: 0, staircase: false });
        let mut cfg = GroupConfig::new("a", 1e-3);
        cfg.eps = 1e6;
        adam.add_group(cfg.clone(), vec![a.clone(), unused.clone()])?;
        adam.add_group(cfg.with_grad_scale(64.0), vec![b.clone()])?;
        let loss = (a.as_tensor() + b.as_tensor())?.sum_all()?;
        adam.step(&loss.backward()?)?;
        let da = 1.0 - a.as_tensor().to_vec1::<f64>()?[0];
        let db = 1.0 - b.as_tensor().to_vec1::<f64>()?[0];
        assert!((db / da - 64.0).abs() < 0.1, "{da} {db}");
        assert_eq!(unused.as_tensor().to_vec1::<f64>()?[0], 5.0);
        Ok(())
    }

    #[test]
    fn restored_state_continues_exactly() -> anyhow::Result<()> {
        let run = |restore_after: Option<usize>| -> anyhow::Result<Vec<f32>> {
            let x = Var::new(&[1.0f32, -2.0, 0.5], &Device::Cpu)?;
            let mut adam = Adam::new(LrSchedule { warmup_steps: 2, decay_steps: 10, staircase: false });
            adam.add_group(GroupConfig::new("x", 0.1).with_clamp(-1.5, 1.5), vec![x.clone()])?;
            for k in 0..4 {
                if restore_after == Some(k) {
                    // Rebuild the optimiser and its parameter from a snapshot, as a resumed run does.
                    let state = adam.state()?;
                    let values = x.as_tensor().copy()?;
                    let y = Var::from_tensor(&values)?;
                    let mut fresh = Adam::new(LrSchedule { warmup_steps: 2, decay_steps: 10, staircase: false });
                    fresh.add_group(GroupConfig::new("x", 0.1).with_clamp(-1.5, 1.5), vec![y.clone()])?;
                    fresh.restore(&state)?;
                    let mut adam2 = fresh;
                    for _ in k..4 {
                        let loss = (y.as_tensor().sqr()? * 3.0)?.sum_all()?;
                        adam2.step(&loss.backward()?)?;
                    }
                    return Ok(y.as_tensor().to_vec1()?);
                }
                let loss = (x.as_tensor().sqr()? * 3.0)?.sum_all()?;
                adam.step(&loss.backward()?)?;
            }
            Ok(x.as_tensor().to_vec1()?)
        };
        assert_eq!(run(None)?, run(Some(2))?);
        Ok(())
    }

}

//! The official IDArb DDIM scheduler (diffusers `DDIMScheduler` with the released config):
//! linear betas 0.00085…0.012 over 1000 steps, rescaled to zero terminal SNR, v-prediction,
//! trailing timestep spacing, `set_alpha_to_one` (ᾱ = 1 before the first training step).
use candle_core::{Result, Tensor};

/// How closely two correct float32 implementations of this schedule agree on ᾱ (what the parity
/// tests allow): four float32 roundings at the scale of 1. ᾱ is made from O(1) quantities (1 − β,
/// √ᾱ, the zero-SNR rescale), so its rounding error is absolute, about one ulp of 1 per operation,
/// and implementations that order the operations differently land a few ulps apart; one ulp of 1
/// (1.19e-7) is already twice the spacing of float32 just below 1.
pub const ALPHA_AGREEMENT: f64 = 4.0 * f32::EPSILON as f64;

#[derive(Debug, Clone)]
pub struct DdimScheduler {
    /// ᾱ_t for t = 0…999 (float32, as diffusers computes them; ᾱ_999 is exactly 0).
    pub alphas_cumprod: Vec<f32>,
    pub num_train_timesteps: usize,
    /// Inference timesteps, descending.
    pub timesteps: Vec<usize>,
    /// `prev = t − num_train_timesteps / S` (integer division), negative at the end.
    pub prev_timesteps: Vec<i64>,
}

/// torch.linspace in float32: the first half counts up from `start`, the second half down from
/// `end`, with the step computed in float32.
fn linspace_f32(start: f32, end: f32, n: usize) -> Vec<f32> {
    let step = (end - start) / (n - 1) as f32;
    let half = n / 2;
    (0..n).map(|i| if i < half { start + step * i as f32 } else { end - step * (n - 1 - i) as f32 }).collect()
}

/// Cumulative product as torch computes it on CPU (accumulating in double, storing float).
fn cumprod(x: &[f32]) -> Vec<f32> {
    let mut acc = 1f64;
    x.iter().map(|&v| { acc *= v as f64; acc as f32 }).collect()
}

/// Zero-terminal-SNR rescale (Lin et al. 2024, Algorithm 1), in float32 as diffusers does.
fn rescale_zero_terminal_snr(betas: &[f32]) -> Vec<f32> {
    let alphas: Vec<f32> = betas.iter().map(|b| 1.0 - b).collect();
    let sqrt_bar: Vec<f32> = cumprod(&alphas).iter().map(|a| a.sqrt()).collect();
    let (first, last) = (sqrt_bar[0], sqrt_bar[sqrt_bar.len() - 1]);
    // Of the float32 orderings tried, this one is closest to both official tables (3e-8 on the
    // fixture's ᾱ, 3e-7 on all 1000 values — PyTorch itself moves them by that much across versions).
    let rescaled: Vec<f32> = sqrt_bar.iter().map(|s| (s - last) * first / (first - last)).collect();
    let bar: Vec<f32> = rescaled.iter().map(|s| s * s).collect();
    let mut alphas = vec![bar[0]];
    alphas.extend(bar.windows(2).map(|w| w[1] / w[0]));
    alphas.iter().map(|a| 1.0 - a).collect()
}

impl DdimScheduler {
    /// The released IDArb scheduler with `num_inference_steps` steps.
    pub fn idarb(num_inference_steps: usize) -> Self {
        let train = 1000;
        let betas = rescale_zero_terminal_snr(&linspace_f32(0.00085, 0.012, train));
        let alphas: Vec<f32> = betas.iter().map(|b| 1.0 - b).collect();
        let alphas_cumprod = cumprod(&alphas);
        let s = num_inference_steps.clamp(1, train);
        // trailing: round(arange(T, 0, −T/S)) − 1, numpy's round (halves to even: 812.5 → 812)
        let ratio = train as f64 / s as f64;
        let timesteps: Vec<usize> = (0..s).map(|i| ((train as f64 - i as f64 * ratio).round_ties_even() as usize).saturating_sub(1)).collect();
        let prev_timesteps = timesteps.iter().map(|&t| t as i64 - (train / s) as i64).collect();
        Self { alphas_cumprod, num_train_timesteps: train, timesteps, prev_timesteps }
    }

    /// ᾱ_t and ᾱ_prev of step `k` (ᾱ_prev = 1 when prev < 0: `set_alpha_to_one`).
    pub fn alphas(&self, k: usize) -> (f32, f32) {
        let a_t = self.alphas_cumprod[self.timesteps[k]];
        let p = self.prev_timesteps[k];
        let a_prev = if p >= 0 { self.alphas_cumprod[p as usize] } else { 1.0 };
        (a_t, a_prev)
    }

    /// σ_t = η·√((1−ᾱ_prev)/(1−ᾱ_t)·(1−ᾱ_t/ᾱ_prev)).
    pub fn sigma(&self, k: usize, eta: f32) -> f32 {
        let (a_t, a_prev) = self.alphas(k);
        let variance = (1.0 - a_prev) / (1.0 - a_t) * (1.0 - a_t / a_prev);
        eta * variance.max(0.0).sqrt()
    }

    /// One DDIM step from x_t with v-prediction `v`; `noise` is required when η > 0.
    pub fn step(&self, k: usize, v: &Tensor, x: &Tensor, eta: f32, noise: Option<&Tensor>) -> Result<Tensor> {
        let (a_t, a_prev) = self.alphas(k);
        let (sa, sb) = (a_t.sqrt(), (1.0 - a_t).sqrt());
        let x0 = (x.affine(sa as f64, 0.0)? - v.affine(sb as f64, 0.0)?)?;
        let eps = (v.affine(sa as f64, 0.0)? + x.affine(sb as f64, 0.0)?)?;
        let sigma = self.sigma(k, eta);
        let dir = (1.0 - a_prev - sigma * sigma).max(0.0).sqrt();
        let prev = (x0.affine(a_prev.sqrt() as f64, 0.0)? + eps.affine(dir as f64, 0.0)?)?;
        match noise {
            Some(z) if sigma > 0.0 => prev + z.affine(sigma as f64, 0.0)?,
            None if sigma > 0.0 => Err(candle_core::Error::Msg("DDIM with eta > 0 needs explicit noise".into())),
            _ => Ok(prev),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn trailing_timesteps_and_prev_rule_when_steps_do_not_divide_1000() {
        // S = 3: arange(1000, 0, −333.33) = 1000, 666.67, 333.33 → round − 1 = 999, 666, 332.
        let s = DdimScheduler::idarb(3);
        assert_eq!(s.timesteps, vec![999, 666, 332]);
        // prev = t − 1000//3 = t − 333: 666, 333, −1. Not the next listed timestep (666 vs 666 ok,
        // but 333 ≠ 332), and the last step lands on ᾱ_prev = 1.
        assert_eq!(s.prev_timesteps, vec![666, 333, -1]);
        assert_eq!(s.alphas(1).1, s.alphas_cumprod[333]);
        assert_eq!(s.alphas(2).1, 1.0);
        // S = 7: 1000//7 = 142.
        let s7 = DdimScheduler::idarb(7);
        assert_eq!(s7.timesteps, vec![999, 856, 713, 570, 428, 285, 142]);
        assert_eq!(s7.prev_timesteps, vec![857, 714, 571, 428, 286, 143, 0]);
        // S = 16: arange steps of 62.5 hit halves, which numpy rounds to even (812.5 → 812 → 811)
        let s16 = DdimScheduler::idarb(16);
        assert_eq!(&s16.timesteps[..4], &[999, 937, 874, 811]);
    }

    #[test]
    fn zero_terminal_snr_and_monotone() {
        let s = DdimScheduler::idarb(50);
        assert_eq!(s.alphas_cumprod[999], 0.0);
        // the rescale keeps ᾱ_0 = 1 − β_0 of the original schedule
        assert!((s.alphas_cumprod[0] - (1.0 - 0.00085)).abs() < 1e-7);
        assert!(s.alphas_cumprod.windows(2).all(|w| w[1] <= w[0]));
    }

    /// x̂₀ and ε̂ recovered from one η = 0 step equal the closed forms: with x = √ᾱ x₀ + √(1−ᾱ) ε and
    /// v = √ᾱ ε − √(1−ᾱ) x₀ (the definition of v), the step must return √ᾱ_prev x₀ + √(1−ᾱ_prev) ε.
    #[test]
    fn v_prediction_step_is_exact_for_consistent_v() -> Result<()> {
        let dev = candle_core::Device::Cpu;
        let s = DdimScheduler::idarb(5);
        let x0 = Tensor::randn(0f32, 1.0, (2, 4, 3, 3), &dev)?;
        let e = Tensor::randn(0f32, 1.0, (2, 4, 3, 3), &dev)?;
        for k in 0..5 {
            let (a, ap) = s.alphas(k);
            let x = (x0.affine(a.sqrt() as f64, 0.)? + e.affine((1. - a).sqrt() as f64, 0.)?)?;
            let v = (e.affine(a.sqrt() as f64, 0.)? - x0.affine((1. - a).sqrt() as f64, 0.)?)?;
            let want = (x0.affine(ap.sqrt() as f64, 0.)? + e.affine((1. - ap).sqrt() as f64, 0.)?)?;
            let got = s.step(k, &v, &x, 0.0, None)?;
            let d = (got - want)?.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?;
            assert!(d < 1e-5, "step {k}: {d}");
        }
        // η = 1 without noise is an error, not a silent deterministic step
        assert!(s.step(1, &x0, &e, 1.0, None).is_err());
        Ok(())
    }
}

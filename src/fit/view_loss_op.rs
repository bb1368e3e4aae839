//! The geometry pass's image loss of one view as one operator: the rendered RGBA image (colour over
//! a background, coverage as the fourth channel) against the target composited over the same
//! background, giving [colour L1 of the tone-mapped images, coverage MSE].
//!
//! It computes exactly what the candle expression `mean|log_srgb(rgb) − log_srgb(target over bg)|`
//! and `mean (a − target_a)²` computed before (same f32 operations in the same order, the same
//! sequential sums, and the same gradient conventions: sign(0) = +1 for |·|, half the gradient at
//! the clamp's ties), in one pass over the image instead of some twenty full-image tensors and
//! their adjoints, and without compositing the target for every view and step: most pixels are
//! background in both images, where the tone map of the background colour is computed once.
//!
//! Forward: T(x) = sRGB(ln(1 + clamp(x, 0, 65535))) (`optim::loss::log_srgb`), per channel;
//! colour = Σ|T(rgb) − T(target)| / (3·H·W), mask = Σ(a − target_a)² / (H·W).
//! Backward: ∂colour/∂rgb = sign(d)·sRGB′(ln(1 + c))/(1 + c)·[clamp share] / (3·H·W) with c the
//! clamped value and d the difference of the tone-mapped values; ∂mask/∂a = 2(a − target_a)/(H·W).
//!
//! Input: the image [H·W, 4] (f32 or f64). Output: [2].

use std::sync::Arc;

use candle_core::{Result, Tensor};
use glam::Vec3;
use rayon::prelude::*;

use crate::optim::loss::HDR_CLAMP;
use crate::optim::srgb::srgb_encode_with_slope;
use crate::optim::tape::{apply, Kernel, Real};

/// One view's loss against `rgb`/`alpha` (linear, straight alpha, row-major) over `background`.
pub struct ViewLoss {
    pub rgb: Arc<[[f32; 3]]>,
    pub alpha: Arc<[f32]>,
    pub background: Vec3,
}

/// The tone map at one value with what its adjoint needs.
#[derive(Clone, Copy)]
struct Tone<T> {
    value: T,
    /// 1 + the clamped input: the logarithm's argument.
    arg: T,
    /// sRGB′ at ln(arg).
    slope: T,
    /// The clamp's share of the gradient: 1 inside, 0 outside, ½ at either bound (candle's
    /// `maximum`/`minimum` adjoint at a tie).
    share: T,
}

#[inline]
fn tone<T: Real>(x: T) -> Tone<T> {
    let (zero, hi) = (T::zero(), T::from_f64(HDR_CLAMP));
    let half = T::from_f64(0.5);
    // clamp = maximum(0) then minimum(65535), with candle's comparisons.
    let m = if x < zero { zero } else { x };
    let c = if m > hi { hi } else { m };
    let arg = c * T::one() + T::one();
    let (value, slope) = srgb_encode_with_slope(arg.ln());
    let tie = |node: T, lhs: T, rhs: T| match (node == lhs, node == rhs) {
        (true, true) => half,
        (true, false) => T::one(),
        _ => zero,
    };
    Tone { value, arg, slope, share: tie(m, x, zero) * tie(c, m, hi) }
}

impl ViewLoss {
    fn len(&self) -> usize {
        self.alpha.len()
    }

    /// The background's tone per channel.
    fn background_tones<T: Real>(&self) -> [Tone<T>; 3] {
        [0, 1, 2].map(|k| tone(T::from_f64(self.background[k] as f64)))
    }

    /// Tone of rendered channel value `x` (the background's when equal to it) and of the target's
    /// channel k at pixel p over the background (the background's when the target is empty there).
    #[inline]
    fn tones<T: Real>(&self, bg: &[Tone<T>; 3], p: usize, k: usize, x: T) -> (Tone<T>, T) {
        let b = T::from_f64(self.background[k] as f64);
        let rendered = if x == b { bg[k] } else { tone(x) };
        let a = self.alpha[p];
        let c = self.rgb[p][k];
        let target = if a == 0.0 && c.is_finite() {
            // c·0 + bg·1 is the background's value.
            bg[k].value
        } else {
            let (a, c) = (T::from_f64(a as f64), T::from_f64(c as f64));
            tone(c * a + b * (T::one() - a)).value
        };
        (rendered, target)
    }
}

impl Kernel for ViewLoss {
    fn name(&self) -> &'static str {
        "view-loss"
    }

    fn output_shape(&self, shapes: &[&[usize]]) -> Result<Vec<usize>> {
        let n = self.len();
        if shapes.len() != 1 || shapes[0] != [n, 4] || self.rgb.len() != n {
            return Err(candle_core::Error::Msg(format!(
                "view-loss: expected an image [{n}, 4] for a target of {} pixels, got {shapes:?}",
                self.rgb.len()
            )));
        }
        Ok(vec![2])
    }

    fn forward<T: Real>(&self, x: &[&[T]], _: &[&[usize]], out: &mut [T]) -> Result<()> {
        let img = x[0];
        let bg = self.background_tones::<T>();
        // Per-pixel terms in parallel, then the sums in candle's order (sequential, f32 or f64).
        let mut terms = vec![[T::zero(); 4]; self.len()];
        terms.par_iter_mut().enumerate().for_each(|(p, t)| {
            for k in 0..3 {
                let (r, target) = self.tones(&bg, p, k, img[4 * p + k]);
                t[k] = (r.value - target).abs();
            }
            let d = img[4 * p + 3] - T::from_f64(self.alpha[p] as f64);
            t[3] = d * d;
        });
        let (mut colour, mut mask) = (T::zero(), T::zero());
        for t in &terms {
            colour += t[0];
            colour += t[1];
            colour += t[2];
        }
        for t in &terms {
            mask += t[3];
        }
        let n = self.len() as f64;
        out[0] = colour * T::from_f64(1.0 / (3.0 * n)) + T::zero();
        out[1] = mask * T::from_f64(1.0 / n) + T::zero();
        Ok(())
    }

    fn backward<T: Real>(&self, x: &[&[T]], _: &[&[usize]], g: &[T], grads: &mut [Option<&mut [T]>]) -> Result<()> {
        let Some(gi) = grads[0].as_deref_mut() else { return Ok(()) };
        let img = x[0];
        let bg = self.background_tones::<T>();
        let n = self.len() as f64;
        let g_colour = g[0] * T::from_f64(1.0 / (3.0 * n)) + T::zero();
        let g_mask = g[1] * T::from_f64(1.0 / n) + T::zero();
        let two = T::from_f64(2.0);
        gi.par_chunks_mut(4).enumerate().for_each(|(p, gp)| {
            for k in 0..3 {
                let (r, target) = self.tones(&bg, p, k, img[4 * p + k]);
                let sign = if r.value - target >= T::zero() { T::one() } else { T::zero() - T::one() };
                gp[k] += (g_colour * sign) * r.slope / r.arg * r.share;
            }
            let d = img[4 * p + 3] - T::from_f64(self.alpha[p] as f64);
            gp[3] += d * g_mask * two;
        });
        Ok(())
    }
}

/// [colour L1, coverage MSE] of `image` [H·W, 4] against the view's target, on the tape.
pub fn view_loss(op: ViewLoss, image: &Tensor) -> Result<Tensor> {
    apply(op, &[image])
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optim::gradcheck::check_gradient;
    use crate::optim::loss::log_srgb;
    use candle_core::{DType, Device, Var, D};

    /// A 5×4 target with empty, full and partial alpha, and an image with background pixels,
    /// out-of-range values and exact ties with the target.
    fn case() -> (ViewLoss, Vec<f32>) {
        let n = 20;
        let background = Vec3::new(0.3, 0.0, 0.8);
        let rgb: Vec<[f32; 3]> = (0..n).map(|i| [(i % 7) as f32 * 0.15, (i % 3) as f32 * 0.4, 1.5 - (i % 5) as f32 * 0.3]).collect();
        let alpha: Vec<f32> = (0..n).map(|i| [0.0, 1.0, 0.25, 0.0, 1.0][i % 5]).collect();
        let mut img = Vec::with_capacity(4 * n);
        for (i, c) in rgb.iter().enumerate() {
            let px = match i % 4 {
                0 => [background.x, background.y, background.z, 0.0],
                1 => [c[0], c[1], c[2], 1.0],
                2 => [-0.2, 7.0e4, 0.5, 0.6],
                _ => [0.1 * i as f32, 0.05, 2.0, 0.3],
            };
            img.extend(px);
        }
        (ViewLoss { rgb: rgb.into(), alpha: alpha.into(), background }, img)
    }

    /// The loss as the pass wrote it with candle's ops.
    fn reference(op: &ViewLoss, image: &Tensor) -> Result<Tensor> {
        let bg = op.background;
        let n = op.len();
        let target_rgb: Vec<f32> =
            op.rgb.iter().zip(op.alpha.iter()).flat_map(|(c, &a)| [0, 1, 2].map(|k| c[k] * a + bg[k] * (1.0 - a))).collect();
        let dev = &Device::Cpu;
        let target_rgb = Tensor::from_vec(target_rgb, (n, 3), dev)?;
        let target_a = Tensor::from_vec(op.alpha.to_vec(), (n, 1), dev)?;
        let colour = (log_srgb(&image.narrow(D::Minus1, 0, 3)?)? - log_srgb(&target_rgb)?)?.abs()?.mean_all()?;
        let mask = (image.narrow(D::Minus1, 3, 1)? - target_a)?.sqr()?.mean_all()?;
        Tensor::stack(&[colour, mask], 0)
    }

    #[test]
    fn equals_the_candle_expression_bit_for_bit_in_f32() -> anyhow::Result<()> {
        let (op, img) = case();
        let (bg, rgb, alpha) = (op.background, op.rgb.clone(), op.alpha.clone());
        let v = Var::from_tensor(&Tensor::from_vec(img, (20, 4), &Device::Cpu)?)?;
        let weights = Tensor::new(&[0.7f32, 1.3], &Device::Cpu)?;
        let ours = view_loss(op, v.as_tensor())?;
        let theirs = reference(&ViewLoss { rgb, alpha, background: bg }, v.as_tensor())?;
        assert_eq!(ours.to_vec1::<f32>()?, theirs.to_vec1::<f32>()?);
        let g_ours = (ours * &weights)?.sum_all()?.backward()?;
        let g_theirs = (theirs * &weights)?.sum_all()?.backward()?;
        let (a, b) = (g_ours.get(v.as_tensor()).expect("gradient"), g_theirs.get(v.as_tensor()).expect("gradient"));
        assert_eq!(a.flatten_all()?.to_vec1::<f32>()?, b.flatten_all()?.to_vec1::<f32>()?);
        Ok(())
    }

    #[test]
    fn gradients_match_finite_differences() -> anyhow::Result<()> {
        // Away from the kinks (ties with the target, the clamp's bounds, the background value).
        let (op, _) = case();
        let img: Vec<f64> = (0..80).map(|i| if i % 4 == 3 { 0.1 + 0.01 * i as f64 } else { 0.05 + 0.037 * i as f64 }).collect();
        let t = Tensor::from_vec(img, (20, 4), &Device::Cpu)?.to_dtype(DType::F64)?;
        let (rgb, alpha, background) = (op.rgb.clone(), op.alpha.clone(), op.background);
        check_gradient(|x| view_loss(ViewLoss { rgb: rgb.clone(), alpha: alpha.clone(), background }, &x[0]), &[t], 1e-7, 1e-5)?;
        Ok(())
    }
}

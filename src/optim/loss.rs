//! The image loss (docs/model.md, *Loss*; NVDiffRecMC's `logl1`): L1 between tone-mapped render and target,
//! both masked by the ground-truth alpha, plus the MSE between rendered and ground-truth alpha.
//!
//! Tone map T(x) = sRGB(log(1 + clamp(x, 0, 65535))): the log compresses HDR highlights so bright
//! pixels do not dominate, the clamp keeps 1e5-sized outliers finite (gradient 0 above the clamp).

use candle_core::{Result, Tensor, D};

use rayon::prelude::*;

use super::srgb::{srgb_encode, srgb_encode_with_slope};
use super::tape::{apply, Kernel, Real};

/// Largest linear value the tone map distinguishes (as NVDiffRecMC).
pub const HDR_CLAMP: f64 = 65535.0;

/// T(y) and dT/dy, as the composition [`log_srgb`] differentiates them, kinks included: the clamp
/// passes half the gradient where y sits exactly on 0 or on [`HDR_CLAMP`] (candle's rule for a tie
/// of `maximum`/`minimum`) and none outside, and the sRGB curve takes its right-hand slope at 0.
/// At those points each equals the central difference. For the fused operators ([`LogL1`],
/// `optim::shading`).
#[inline]
pub fn tone_map_with_slope<T: Real>(y: T) -> (T, T) {
    let (zero, one, top) = (T::zero(), T::one(), T::from_f64(HDR_CLAMP));
    let (clamped, pass) = if y < zero {
        (zero, zero)
    } else if y > top {
        (top, zero)
    } else if y == zero || y == top {
        (y, T::from_f64(0.5))
    } else {
        (y, one)
    };
    let l = (clamped + one).ln();
    let (v, slope) = srgb_encode_with_slope(l);
    (v, slope / (clamped + one) * pass)
}

/// The slope of |z| as candle's `abs` takes it: +1 at z = 0.
#[inline]
pub fn abs_slope<T: Real>(z: T) -> T {
    if z >= T::zero() {
        T::one()
    } else {
        T::zero() - T::one()
    }
}

/// T(x) = sRGB(log(1 + clamp(x, 0, 65535))), on the tape.
pub fn log_srgb(x: &Tensor) -> Result<Tensor> {
    srgb_encode(&(x.clamp(0.0, HDR_CLAMP)? + 1.0)?.log()?)
}

/// A target prepared once for every term that compares a render with it: linear RGB and alpha as
/// [.., 3] and [.., 1], and the constants of the loss terms, computed outside the tape (a
/// training view keeps its own, so no step recomputes them).
#[derive(Clone, Debug)]
pub struct LossTarget {
    /// The target as given, linear RGBA [.., 4].
    pub rgba: Tensor,
    pub alpha: Tensor,
    /// T(rgb·α), [.., 3]: what the image loss compares the render's tone map with.
    tone_mapped: Tensor,
    /// T(max_c(rgb)·α), [.., 1]: the shading regulariser's reference (`optim::shading`).
    pub value_tone_mapped: Tensor,
}

impl LossTarget {
    /// `rgba`: [.., 4] linear RGB (already linearised from sRGB PNG) and alpha in [0, 1]; an image
    /// [H, W, 4] or a column of pixels [N, 1, 4].
    pub fn new(rgba: &Tensor) -> Result<Self> {
        if rgba.rank() != 3 || rgba.dim(D::Minus1)? != 4 {
            return Err(candle_core::Error::Msg(format!("loss target: expected [H, W, 4] RGBA, got {:?}", rgba.dims())));
        }
        let rgba = rgba.detach();
        let alpha = rgba.narrow(D::Minus1, 3, 1)?;
        let rgb = rgba.narrow(D::Minus1, 0, 3)?;
        let tone_mapped = log_srgb(&rgb.broadcast_mul(&alpha)?)?.detach();
        let value_tone_mapped = log_srgb(&(rgb.max_keepdim(D::Minus1)? * &alpha)?)?.detach();
        Ok(LossTarget { rgba, alpha, tone_mapped, value_tone_mapped })
    }

    /// Several column targets [Nᵢ, 1, 4] as one, rows in order (a batch of views).
    pub fn cat(parts: &[&LossTarget]) -> Result<Self> {
        if let [one] = parts {
            return Ok((*one).clone());
        }
        let cat = |f: fn(&LossTarget) -> &Tensor| Tensor::cat(&parts.iter().map(|p| f(p)).collect::<Vec<_>>(), 0);
        Ok(LossTarget {
            rgba: cat(|p| &p.rgba)?,
            alpha: cat(|p| &p.alpha)?,
            tone_mapped: cat(|p| &p.tone_mapped)?,
            value_tone_mapped: cat(|p| &p.value_tone_mapped)?,
        })
    }
}

/// mean |T(render·α) − T(target·α)| over pixels and channels + mean (render_α − α)².
/// `render_rgb`: [H, W, 3] linear HDR; `render_alpha`: [H, W, 1] coverage, when it is rendered
/// differentiably (with a fixed G-buffer it is constant and the term can be skipped with `None`).
/// The L1 term is one operator ([`LogL1`]), not the dozen element-wise candle operators it was
/// written as: candle runs those, and their adjoints, on one thread.
pub fn image_loss(render_rgb: &Tensor, render_alpha: Option<&Tensor>, target: &LossTarget) -> Result<Tensor> {
    let shape_ok = render_rgb.dims() == target.tone_mapped.dims();
    if !shape_ok {
        return Err(candle_core::Error::Msg(format!(
            "image loss: render {:?} does not match target {:?}",
            render_rgb.dims(),
            target.tone_mapped.dims()
        )));
    }
    let dtype = render_rgb.dtype();
    let l1 = apply(LogL1, &[render_rgb, &target.alpha.to_dtype(dtype)?, &target.tone_mapped.to_dtype(dtype)?])?;
    match render_alpha {
        Some(a) => l1 + (a - target.alpha.to_dtype(a.dtype())?)?.sqr()?.mean_all()?,
        None => Ok(l1),
    }
}

/// mean over pixels p and channels c of |T(x_pc·α_p) − R_pc|, with T the tone map of
/// [`log_srgb`]; inputs x [.., 3] (on the tape), α [.., 1] and R [.., 3] (constants of the
/// target); output a scalar.
///
/// Its derivative follows the composition it replaces, kinks included ([`tone_map_with_slope`],
/// [`abs_slope`]).
pub struct LogL1;

/// Pixels per chunk of the forward's sum: fixed, so the sum is the same on any number of threads.
const LOG_L1_CHUNK: usize = 4096;

impl Kernel for LogL1 {
    fn name(&self) -> &'static str {
        "log_l1"
    }

    fn output_shape(&self, shapes: &[&[usize]]) -> Result<Vec<usize>> {
        match shapes {
            [x, a, r] if x.last() == Some(&3) && a.last() == Some(&1) && r == x && x[..x.len() - 1] == a[..a.len() - 1] => Ok(vec![]),
            _ => Err(candle_core::Error::Msg(format!("image loss: expected render [.., 3], alpha [.., 1] and reference [.., 3] of one size, got {shapes:?}"))),
        }
    }

    fn forward<T: Real>(&self, x: &[&[T]], _: &[&[usize]], out: &mut [T]) -> Result<()> {
        let (rgb, alpha, reference) = (x[0], x[1], x[2]);
        let parts: Vec<f64> = rgb
            .par_chunks(3 * LOG_L1_CHUNK)
            .zip(alpha.par_chunks(LOG_L1_CHUNK))
            .zip(reference.par_chunks(3 * LOG_L1_CHUNK))
            .map(|((rgb, alpha), reference)| {
                let mut sum = 0.0f64;
                for ((p, &a), r) in rgb.chunks_exact(3).zip(alpha).zip(reference.chunks_exact(3)) {
                    for c in 0..3 {
                        sum += (tone_map_with_slope(p[c] * a).0 - r[c]).abs().to_f64();
                    }
                }
                sum
            })
            .collect();
        out[0] = T::from_f64(parts.iter().sum::<f64>() / rgb.len().max(1) as f64);
        Ok(())
    }

    fn backward<T: Real>(&self, x: &[&[T]], _: &[&[usize]], g: &[T], grads: &mut [Option<&mut [T]>]) -> Result<()> {
        let Some(gx) = grads[0].as_deref_mut() else { return Ok(()) };
        let (rgb, alpha, reference) = (x[0], x[1], x[2]);
        let scale = g[0] / T::from_f64(rgb.len().max(1) as f64);
        gx.par_chunks_mut(3).zip(rgb.par_chunks(3)).zip(alpha.par_iter()).zip(reference.par_chunks(3)).for_each(|(((o, p), &a), r)| {
            for c in 0..3 {
                let (v, slope) = tone_map_with_slope(p[c] * a);
                o[c] += scale * abs_slope(v - r[c]) * slope * a;
            }
        });
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::color::linear_to_srgb;
    use crate::optim::gradcheck::{check_gradient, check_same_as_composition};
    use candle_core::{DType, Device};

    #[test]
    fn loss_matches_a_hand_computed_pixel() -> Result<()> {
        // One pixel, alpha 0.5: render (1, 2, 0), target (0.5, 0, 4).
        let target = LossTarget::new(&Tensor::new(&[[[0.5f64, 0.0, 4.0, 0.5]]], &Device::Cpu)?)?;
        let render = Tensor::new(&[[[1.0f64, 2.0, 0.0]]], &Device::Cpu)?;
        let ra = Tensor::new(&[[[0.9f64]]], &Device::Cpu)?;
        let got = image_loss(&render, Some(&ra), &target)?.to_scalar::<f64>()?;
        let t = |x: f64| linear_to_srgb((1.0 + x).ln() as f32) as f64;
        let l1 = ((t(0.5) - t(0.25)).abs() + (t(1.0) - t(0.0)).abs() + (t(0.0) - t(2.0)).abs()) / 3.0;
        let want = l1 + 0.4 * 0.4;
        assert!((got - want).abs() < 1e-5, "{got} vs {want}");
        Ok(())
    }

    #[test]
    fn a_batch_of_targets_equals_the_target_of_the_batch() -> Result<()> {
        let dev = Device::Cpu;
        let (a, b) = (Tensor::rand(0f32, 3.0, (5, 1, 4), &dev)?, Tensor::rand(0f32, 3.0, (7, 1, 4), &dev)?);
        let (ta, tb) = (LossTarget::new(&a)?, LossTarget::new(&b)?);
        let joined = LossTarget::cat(&[&ta, &tb])?;
        let whole = LossTarget::new(&Tensor::cat(&[&a, &b], 0)?)?;
        let same = |x: &Tensor, y: &Tensor| -> Result<bool> { Ok(x.dims() == y.dims() && x.flatten_all()?.to_vec1::<f32>()? == y.flatten_all()?.to_vec1::<f32>()?) };
        for (x, y) in [(&joined.rgba, &whole.rgba), (&joined.alpha, &whole.alpha), (&joined.tone_mapped, &whole.tone_mapped), (&joined.value_tone_mapped, &whole.value_tone_mapped)] {
            assert!(same(x, y)?);
        }
        Ok(())
    }

    #[test]
    fn the_l1_operator_equals_the_composition_it_replaces() -> anyhow::Result<()> {
        // The element-wise candle composition the operator replaced, kinks included: exact zeros
        // (the clamp's tie), values past the clamp, alpha 0 and 1, and references equal to the
        // render's own tone map (|z| at 0).
        let dev = Device::Cpu;
        let n = 64;
        let mut s = crate::rng::Sampler::from_seed(5);
        let rgb: Vec<f64> = (0..3 * n).map(|i| match i % 9 { 0 => 0.0, 4 => 1e5, _ => 3.0 * s.next_f32() as f64 }).collect();
        let alpha: Vec<f64> = (0..n).map(|i| match i % 5 { 0 => 0.0, 1 => 1.0, _ => s.next_f32() as f64 }).collect();
        let x = candle_core::Var::from_tensor(&Tensor::from_vec(rgb, (n, 1, 3), &dev)?)?;
        let a = Tensor::from_vec(alpha, (n, 1, 1), &dev)?;
        let own = log_srgb(&x.as_tensor().broadcast_mul(&a)?)?.detach().flatten_all()?.to_vec1::<f64>()?;
        let reference: Vec<f64> = own.iter().enumerate().map(|(i, &v)| if i % 4 == 0 { v } else { 2.0 * s.next_f32() as f64 }).collect();
        let r = Tensor::from_vec(reference, (n, 1, 3), &dev)?;
        let composed = (log_srgb(&x.as_tensor().broadcast_mul(&a)?)? - &r)?.abs()?.mean_all()?;
        let fused = apply(LogL1, &[x.as_tensor(), &a, &r])?;
        check_same_as_composition(&composed, &fused, &[&x], 1e-12)
    }

    #[test]
    fn huge_hdr_values_stay_finite() -> Result<()> {
        let target = LossTarget::new(&Tensor::ones((2, 2, 4), DType::F32, &Device::Cpu)?)?;
        let render = candle_core::Var::from_tensor(&Tensor::new(&[1e5f32, 1e7, 3.0e38, 0.5], &Device::Cpu)?.repeat(3)?.reshape((2, 2, 3))?)?;
        let l = image_loss(render.as_tensor(), None, &target)?;
        assert!(l.to_scalar::<f32>()?.is_finite());
        let g = l.backward()?;
        let g = g.get(render.as_tensor()).expect("grad").flatten_all()?.to_vec1::<f32>()?;
        assert!(g.iter().all(|v| v.is_finite()));
        Ok(())
    }

    #[test]
    fn gradient_matches_finite_differences() -> anyhow::Result<()> {
        let dev = Device::Cpu;
        let rgba = Tensor::rand(0f64, 2.0, (5, 4, 4), &dev)?;
        // Alpha in [0, 1], some pixels fully out.
        let a = Tensor::rand(0f64, 1.0, (5, 4, 1), &dev)?;
        let a = a.ge(0.2)?.where_cond(&a, &a.zeros_like()?)?;
        let rgba = Tensor::cat(&[rgba.narrow(2, 0, 3)?, a], 2)?;
        let target = LossTarget::new(&rgba)?;
        let render = Tensor::rand(0.01f64, 3.0, (5, 4, 3), &dev)?;
        let ra = Tensor::rand(0f64, 1.0, (5, 4, 1), &dev)?;
        check_gradient(|x| image_loss(&x[0], Some(&x[1]), &target), &[render, ra], 1e-6, 1e-2)?;
        Ok(())
    }
}

//! The image loss (docs/model.md, *Loss*; NVDiffRecMC's `logl1`): L1 between tone-mapped render and target,
//! both masked by the ground-truth alpha, plus the MSE between rendered and ground-truth alpha.
//!
//! Tone map T(x) = sRGB(log(1 + clamp(x, 0, 65535))): the log compresses HDR highlights so bright
//! pixels do not dominate, the clamp keeps 1e5-sized outliers finite (gradient 0 above the clamp).

use candle_core::{Result, Tensor, D};

use super::srgb::srgb_encode;

/// Largest linear value the tone map distinguishes (as NVDiffRecMC).
pub const HDR_CLAMP: f64 = 65535.0;

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
pub fn image_loss(render_rgb: &Tensor, render_alpha: Option<&Tensor>, target: &LossTarget) -> Result<Tensor> {
    let shape_ok = render_rgb.dims() == target.tone_mapped.dims();
    if !shape_ok {
        return Err(candle_core::Error::Msg(format!(
            "image loss: render {:?} does not match target {:?}",
            render_rgb.dims(),
            target.tone_mapped.dims()
        )));
    }
    let masked = render_rgb.broadcast_mul(&target.alpha.to_dtype(render_rgb.dtype())?)?;
    let l1 = (log_srgb(&masked)? - target.tone_mapped.to_dtype(render_rgb.dtype())?)?.abs()?.mean_all()?;
    match render_alpha {
        Some(a) => l1 + (a - target.alpha.to_dtype(a.dtype())?)?.sqr()?.mean_all()?,
        None => Ok(l1),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::color::linear_to_srgb;
    use crate::optim::gradcheck::check_gradient;
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

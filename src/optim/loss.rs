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

/// A target view prepared once: linear RGB and alpha as [H, W, 3] and [H, W, 1], plus its tone map
/// (constant, so it is computed outside the tape).
pub struct LossTarget {
    pub alpha: Tensor,
    pub masked_rgb: Tensor,
    tone_mapped: Tensor,
}

impl LossTarget {
    /// `rgba`: [H, W, 4] linear RGB (already linearised from sRGB PNG) and alpha in [0, 1].
    pub fn new(rgba: &Tensor) -> Result<Self> {
        let (_, _, c) = rgba.dims3()?;
        if c != 4 {
            return Err(candle_core::Error::Msg(format!("loss target: expected [H, W, 4] RGBA, got {:?}", rgba.dims())));
        }
        let rgba = rgba.detach();
        let alpha = rgba.narrow(D::Minus1, 3, 1)?;
        let masked_rgb = rgba.narrow(D::Minus1, 0, 3)?.broadcast_mul(&alpha)?;
        let tone_mapped = log_srgb(&masked_rgb)?.detach();
        Ok(LossTarget { alpha, masked_rgb, tone_mapped })
    }
}

/// mean |T(render·α) − T(target·α)| over pixels and channels + mean (render_α − α)².
/// `render_rgb`: [H, W, 3] linear HDR; `render_alpha`: [H, W, 1] coverage, when it is rendered
/// differentiably (with a fixed G-buffer it is constant and the term can be skipped with `None`).
pub fn image_loss(render_rgb: &Tensor, render_alpha: Option<&Tensor>, target: &LossTarget) -> Result<Tensor> {
    let shape_ok = render_rgb.dims() == target.masked_rgb.dims();
    if !shape_ok {
        return Err(candle_core::Error::Msg(format!(
            "image loss: render {:?} does not match target {:?}",
            render_rgb.dims(),
            target.masked_rgb.dims()
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

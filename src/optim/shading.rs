//! The "monochrome shading" regulariser of NVDiffRecMC (its `shading_loss`). It assumes roughly white light:
//! the luminance of the demodulated shading (diffuse + specular light) should explain the target's
//! value channel (max of RGB), weighted by the diffuse share; and specular light should stay small
//! relative to diffuse light. It steers colour into the material (kd) instead of the light.
//!
//! loss = λ_d · mean( |T(lum(d + s)·α) − T(max_rgb(target)·α)| · lum(d) / max(lum(d + s), ε) )
//!      + λ_s · mean(lum(s)) / max(mean(lum(d)), ε)
//! with lum = mean of RGB, T the log-sRGB tone map of the image loss, ε = 1e-3.

use candle_core::{Result, Tensor, D};

use super::loss::{log_srgb, LossTarget};

const EPS: f64 = 1e-3;

/// `diffuse_light`, `specular_light`: [H, W, 3] demodulated shading; `target`: the [H, W, 4] target
/// prepared for the loss (its alpha and `value_tone_mapped` are read).
pub fn shading_regularizer(
    diffuse_light: &Tensor,
    specular_light: &Tensor,
    target: &LossTarget,
    lambda_diffuse: f64,
    lambda_specular: f64,
) -> Result<Tensor> {
    let (h, w, c) = target.rgba.dims3()?;
    if c != 4 || diffuse_light.dims() != [h, w, 3] || specular_light.dims() != [h, w, 3] {
        return Err(candle_core::Error::Msg(format!(
            "shading regulariser: expected light buffers [{h}, {w}, 3] and target [H, W, 4], got {:?}, {:?}, {:?}",
            diffuse_light.dims(),
            specular_light.dims(),
            target.rgba.dims()
        )));
    }
    let dtype = diffuse_light.dtype();
    let alpha = target.alpha.to_dtype(dtype)?;
    let reference = target.value_tone_mapped.to_dtype(dtype)?;
    let lum_d = diffuse_light.mean_keepdim(D::Minus1)?;
    let lum_s = specular_light.mean_keepdim(D::Minus1)?;
    let lum = (&lum_d + &lum_s)?;
    let img = log_srgb(&(&lum * &alpha)?)?;
    let share = (&lum_d / lum.maximum(EPS)?)?;
    let diffuse_term = ((img - reference)?.abs()? * share)?.mean_all()?;
    let specular_term = (lum_s.mean_all()? / lum_d.mean_all()?.maximum(EPS)?)?;
    (diffuse_term * lambda_diffuse)? + (specular_term * lambda_specular)?
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optim::gradcheck::check_gradient;
    use candle_core::Device;

    #[test]
    fn white_light_matching_the_target_costs_only_the_specular_ratio() -> Result<()> {
        let dev = Device::Cpu;
        // Target value 0.6 everywhere, full alpha; diffuse grey 0.5 + specular grey 0.1 = 0.6.
        let target = Tensor::new(&[[[0.6f64, 0.2, 0.3, 1.0]]], &dev)?.repeat((2, 2, 1))?;
        let d = (Tensor::ones((2, 2, 3), candle_core::DType::F64, &dev)? * 0.5)?;
        let s = (Tensor::ones((2, 2, 3), candle_core::DType::F64, &dev)? * 0.1)?;
        let l = shading_regularizer(&d, &s, &LossTarget::new(&target)?, 0.15, 0.0025)?.to_scalar::<f64>()?;
        assert!((l - 0.0025 * 0.2).abs() < 1e-9, "{l}");
        Ok(())
    }

    #[test]
    fn gradient_matches_finite_differences() -> anyhow::Result<()> {
        let dev = Device::Cpu;
        let target = LossTarget::new(&Tensor::rand(0f64, 1.0, (4, 3, 4), &dev)?)?;
        let d = Tensor::rand(0.05f64, 1.0, (4, 3, 3), &dev)?;
        let s = Tensor::rand(0.0f64, 0.5, (4, 3, 3), &dev)?;
        check_gradient(|x| shading_regularizer(&x[0], &x[1], &target, 0.15, 0.0025), &[d, s], 1e-6, 1e-2)?;
        Ok(())
    }
}

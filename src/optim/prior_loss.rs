//! The pseudo-label prior term (docs/model.md, *Loss*): λ · mean over masked pixels of ‖labels − rendered‖²,
//! the squared norm taken over the buffer's channels. Compare in the labels' space: IDArb's albedo is
//! sRGB-encoded, so pass `srgb_encode(kd)` for base colour; roughness/metallic are compared as is.

use candle_core::{Result, Tensor, D};

/// λ · Σ_p m_p ‖label_p − rendered_p‖² / Σ_p m_p; 0 when the mask is empty.
/// `rendered`, `labels`: [H, W, C]; `mask`: [H, W, 1] weights in [0, 1] (coverage, or the labels'
/// confidence).
pub fn prior_loss(rendered: &Tensor, labels: &Tensor, mask: &Tensor, lambda: f64) -> Result<Tensor> {
    let (h, w, _) = rendered.dims3()?;
    if labels.dims() != rendered.dims() || mask.dims() != [h, w, 1] {
        return Err(candle_core::Error::Msg(format!(
            "prior loss: rendered {:?}, labels {:?} and mask {:?} must be [H, W, C], [H, W, C], [H, W, 1]",
            rendered.dims(),
            labels.dims(),
            mask.dims()
        )));
    }
    let dtype = rendered.dtype();
    let mask = mask.detach().to_dtype(dtype)?;
    let weight = mask.sum_all()?.to_dtype(candle_core::DType::F64)?.to_scalar::<f64>()?;
    if weight <= 0.0 {
        return Tensor::zeros((), dtype, rendered.device());
    }
    let sq = (rendered - labels.detach().to_dtype(dtype)?)?.sqr()?.sum_keepdim(D::Minus1)?;
    (sq * mask)?.sum_all()? * (lambda / weight)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optim::gradcheck::check_gradient;
    use candle_core::{DType, Device};

    #[test]
    fn matches_hand_computed_value_and_ignores_unmasked_pixels() -> Result<()> {
        let dev = Device::Cpu;
        let r = Tensor::new(&[[[0.5f64, 0.5], [9.0, 9.0]]], &dev)?; // [1, 2, 2]
        let l = Tensor::new(&[[[0.0f64, 1.5], [0.0, 0.0]]], &dev)?;
        let m = Tensor::new(&[[[1.0f64], [0.0]]], &dev)?;
        let v = prior_loss(&r, &l, &m, 2.0)?.to_scalar::<f64>()?;
        assert!((v - 2.0 * (0.25 + 1.0)).abs() < 1e-12, "{v}");
        let empty = prior_loss(&r, &l, &m.zeros_like()?, 2.0)?.to_scalar::<f64>()?;
        assert_eq!(empty, 0.0);
        assert!(prior_loss(&r, &l, &Tensor::ones((1, 2), DType::F64, &dev)?, 1.0).is_err());
        Ok(())
    }

    #[test]
    fn gradient_matches_finite_differences() -> anyhow::Result<()> {
        let dev = Device::Cpu;
        let r = Tensor::rand(0f64, 1.0, (4, 5, 3), &dev)?;
        let l = Tensor::rand(0f64, 1.0, (4, 5, 3), &dev)?;
        let m = Tensor::rand(0f64, 1.0, (4, 5, 1), &dev)?;
        check_gradient(|x| prior_loss(&x[0], &l, &m, 0.7), &[r], 1e-6, 1e-2)?;
        Ok(())
    }
}

//! NVDiffRec's light white-balance regulariser (`EnvironmentLight.regularizer`, weight 0.005 in its
//! training loop): mean over texels and channels of |L − mean_c(L)|. Without it, light colour and
//! albedo colour trade freely (kd·L is all the images constrain), and the optimiser happily
//! learns an orange light over blue-tinted albedo.

use candle_core::{Result, Tensor, D};

/// mean |L − grey(L)| of a light tensor whose last dimension is RGB.
pub fn light_white_balance(light: &Tensor) -> Result<Tensor> {
    let grey = light.mean_keepdim(D::Minus1)?;
    light.broadcast_sub(&grey)?.abs()?.mean_all()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optim::gradcheck::check_gradient;
    use candle_core::Device;

    #[test]
    fn grey_light_costs_nothing_and_a_tint_costs_its_deviation() -> Result<()> {
        let dev = Device::Cpu;
        let grey = Tensor::new(&[[0.5f64, 0.5, 0.5], [2.0, 2.0, 2.0]], &dev)?;
        assert_eq!(light_white_balance(&grey)?.to_scalar::<f64>()?, 0.0);
        // (1, 0, 0.5): grey 0.5, deviations 0.5, 0.5, 0 → mean over 2 texels × 3 channels = 1/6.
        let tinted = Tensor::new(&[[1.0f64, 0.0, 0.5], [2.0, 2.0, 2.0]], &dev)?;
        assert!((light_white_balance(&tinted)?.to_scalar::<f64>()? - 1.0 / 6.0).abs() < 1e-12);
        Ok(())
    }

    #[test]
    fn gradient_matches_finite_differences() -> anyhow::Result<()> {
        let l = Tensor::rand(0f64, 2.0, (6, 3, 3, 3), &Device::Cpu)?;
        check_gradient(|x| light_white_balance(&x[0]), &[l], 1e-6, 1e-2)?;
        Ok(())
    }
}

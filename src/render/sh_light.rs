//! A low-frequency light for the geometry pass: irradiance as 9 real spherical-harmonic
//! coefficients per colour channel (bands 0–2), and Lambertian shading under it, on the tape.
//!
//! Ramamoorthi and Hanrahan (2001) showed that the irradiance a Lambertian surface receives is
//! captured by the first three SH bands to within a few percent for any environment. The geometry
//! pass needs exactly that much light: enough that shading tells the normal's direction, cheap
//! enough to evaluate and differentiate per pixel with plain tensor ops (candle's autodiff gives
//! the backward), and with no visibility, which a moving mesh could not afford per step. The
//! material pass that follows uses the full cube-map light and BRDF.
//!
//! E(n) = Σₖ cₖ·Yₖ(n), with Yₖ the real SH basis (normalised, Y₀₀ = 0.282095); colour = kd·E(n).

use candle_core::{Result, Tensor, D};

/// Coefficients per channel: bands 0, 1 and 2.
pub const SH_COEFFICIENTS: usize = 9;
/// Y₀₀: the constant basis function, 1/(2√π).
const Y00: f64 = 0.282_094_791_773_878_1;
/// Band-1 factor √(3/4π).
const Y1: f64 = 0.488_602_511_902_919_9;
/// Band-2 factors √(15/4π), √(5/16π), √(15/16π).
const Y2_XY: f64 = 1.092_548_430_592_079_2;
const Y2_ZZ: f64 = 0.315_391_565_252_520_0;
const Y2_XX_YY: f64 = 0.546_274_215_296_039_6;

/// The basis [N, 9] at unit directions `n` [N, 3].
pub fn sh_basis(n: &Tensor) -> Result<Tensor> {
    let x = n.narrow(D::Minus1, 0, 1)?;
    let y = n.narrow(D::Minus1, 1, 1)?;
    let z = n.narrow(D::Minus1, 2, 1)?;
    let ones = x.ones_like()?;
    let cols = [
        (ones.clone() * Y00)?,
        (&y * Y1)?,
        (&z * Y1)?,
        (&x * Y1)?,
        ((&x * &y)? * Y2_XY)?,
        ((&y * &z)? * Y2_XY)?,
        ((((&z * &z)? * 3.0)? - &ones)? * Y2_ZZ)?,
        ((&x * &z)? * Y2_XY)?,
        (((&x * &x)? - (&y * &y)?)? * Y2_XX_YY)?,
    ];
    Tensor::cat(&cols, D::Minus1)
}

/// Coefficients [9, 3] of a constant irradiance `value` in every direction.
pub fn constant_light(value: f64) -> Vec<f32> {
    let mut c = vec![0.0f32; SH_COEFFICIENTS * 3];
    c[..3].fill((value / Y00) as f32);
    c
}

/// kd·E(n): `kd` [N, 3], unit normals `n` [N, 3], coefficients `light` [9, 3] → [N, 3].
pub fn shade_diffuse(kd: &Tensor, n: &Tensor, light: &Tensor) -> Result<Tensor> {
    let irradiance = sh_basis(n)?.matmul(light)?;
    kd * irradiance
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optim::gradcheck::check_gradient;
    use candle_core::Device;

    #[test]
    fn constant_light_is_constant_and_the_basis_is_orthonormal() -> anyhow::Result<()> {
        // Monte Carlo over the sphere (a Fibonacci lattice): ∫ Yᵢ Yⱼ = δᵢⱼ.
        let m = 4000;
        let dirs: Vec<f64> = (0..m)
            .flat_map(|i| {
                let z = 1.0 - 2.0 * (i as f64 + 0.5) / m as f64;
                let r = (1.0 - z * z).sqrt();
                let phi = i as f64 * 2.399_963_229_728_653;
                [r * phi.cos(), r * phi.sin(), z]
            })
            .collect();
        let n = Tensor::from_vec(dirs, (m, 3), &Device::Cpu)?;
        let b = sh_basis(&n)?;
        let gram = (b.t()?.matmul(&b)? * (4.0 * std::f64::consts::PI / m as f64))?.to_vec2::<f64>()?;
        for (i, row) in gram.iter().enumerate() {
            for (j, v) in row.iter().enumerate() {
                let want = if i == j { 1.0 } else { 0.0 };
                assert!((v - want).abs() < 2e-3, "⟨Y{i}, Y{j}⟩ = {v}");
            }
        }
        let light = Tensor::from_vec(constant_light(0.7), (9, 3), &Device::Cpu)?.to_dtype(candle_core::DType::F64)?;
        let e = shade_diffuse(&n.ones_like()?, &n, &light)?.flatten_all()?.to_vec1::<f64>()?;
        assert!(e.iter().all(|v| (v - 0.7).abs() < 1e-6));
        Ok(())
    }

    #[test]
    fn gradients_match_finite_differences() -> anyhow::Result<()> {
        let d = &Device::Cpu;
        let n = Tensor::from_vec(vec![0.6, 0.0, 0.8, -0.48, 0.6, 0.64, 0.0, -1.0, 0.0f64], (3, 3), d)?;
        let kd = Tensor::from_vec(vec![0.2, 0.5, 0.9, 0.4, 0.4, 0.1, 0.7, 0.3, 0.6f64], (3, 3), d)?;
        let light = Tensor::from_vec((0..27).map(|i| ((i * 7 % 11) as f64 - 5.0) / 10.0).collect::<Vec<_>>(), (9, 3), d)?;
        check_gradient(|x| shade_diffuse(&x[0], &x[1], &x[2]), &[kd, n, light], 1e-6, 1e-6)?;
        Ok(())
    }
}

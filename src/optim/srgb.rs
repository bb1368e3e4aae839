//! The exact piecewise sRGB encoding curve as a differentiable elementwise operator (the same curve
//! as `crate::color::linear_to_srgb`, generic over f32/f64 so gradient checks run in f64).

use candle_core::{Result, Tensor};
use rayon::prelude::*;

use super::tape::{apply, Kernel, Real};

const KNEE: f64 = 0.003_130_8;

/// Value and derivative of the encoding curve at `x` (negative input encodes to 0, slope 0).
/// At exactly 0 the slope is the right-hand one (12.92): after a `clamp(·, 0, ·)`, whose candle
/// backward gives ½ at the tie, the chain then equals the central difference there.
#[inline]
pub fn srgb_encode_with_slope<T: Real>(x: T) -> (T, T) {
    let knee = T::from_f64(KNEE);
    if x < T::zero() {
        (T::zero(), T::zero())
    } else if x <= knee {
        let s = T::from_f64(12.92);
        (x * s, s)
    } else {
        let p = x.powf(T::from_f64(1.0 / 2.4));
        (T::from_f64(1.055) * p - T::from_f64(0.055), T::from_f64(1.055 / 2.4) * p / x)
    }
}

struct SrgbEncode;

impl Kernel for SrgbEncode {
    fn name(&self) -> &'static str {
        "srgb_encode"
    }
    fn output_shape(&self, shapes: &[&[usize]]) -> Result<Vec<usize>> {
        Ok(shapes[0].to_vec())
    }
    fn forward<T: Real>(&self, x: &[&[T]], _: &[&[usize]], out: &mut [T]) -> Result<()> {
        out.par_iter_mut().zip(x[0].par_iter()).for_each(|(o, &v)| *o = srgb_encode_with_slope(v).0);
        Ok(())
    }
    fn backward<T: Real>(&self, x: &[&[T]], _: &[&[usize]], g: &[T], grads: &mut [Option<&mut [T]>]) -> Result<()> {
        if let Some(gx) = grads[0].as_deref_mut() {
            gx.par_iter_mut()
                .zip(x[0].par_iter().zip(g.par_iter()))
                .for_each(|(o, (&v, &gv))| *o += gv * srgb_encode_with_slope(v).1);
        }
        Ok(())
    }
}

/// Linear → sRGB-encoded, elementwise, on the tape.
pub fn srgb_encode(x: &Tensor) -> Result<Tensor> {
    apply(SrgbEncode, &[x])
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::color::linear_to_srgb;
    use crate::optim::gradcheck::check_gradient;
    use candle_core::Device;

    #[test]
    fn matches_the_shared_curve() {
        for i in 0..2000 {
            let x = i as f32 * 1e-3 - 0.1;
            let (v, _) = srgb_encode_with_slope(x);
            assert!((v - linear_to_srgb(x)).abs() < 1e-6, "{x}");
        }
    }

    #[test]
    fn gradient_matches_finite_differences_on_both_branches() -> anyhow::Result<()> {
        // Below and above the knee, and large HDR-ish values (away from the kinks at 0 and the knee).
        let x = Tensor::new(&[1e-4f64, 0.002, 0.0035, 0.2, 0.9, 3.0, 11.0], &Device::Cpu)?;
        let rep = check_gradient(|a| srgb_encode(&a[0]), &[x], 1e-7, 1e-6)?;
        assert!(rep.rel_err() < 1e-6);
        Ok(())
    }
}

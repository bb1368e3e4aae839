//! The "monochrome shading" regulariser of NVDiffRecMC (its `shading_loss`). It assumes roughly white light:
//! the luminance of the demodulated shading (diffuse + specular light) should explain the target's
//! value channel (max of RGB), weighted by the diffuse share; and specular light should stay small
//! relative to diffuse light. It steers colour into the material (kd) instead of the light.
//!
//! loss = λ_d · mean( |T(lum(d + s)·α) − T(max_rgb(target)·α)| · lum(d) / max(lum(d + s), ε) )
//!      + λ_s · mean(lum(s)) / max(mean(lum(d)), ε)
//! with lum = mean of RGB, T the log-sRGB tone map of the image loss, ε = 1e-3.

use candle_core::{Result, Tensor, D};

use rayon::prelude::*;

use super::loss::{abs_slope, tone_map_with_slope, LossTarget};
use super::tape::{apply, Kernel, Real};

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
    let constants = Tensor::cat(&[target.alpha.to_dtype(dtype)?, target.value_tone_mapped.to_dtype(dtype)?], D::Minus1)?;
    apply(ShadingTerms { lambda_diffuse, lambda_specular }, &[diffuse_light, specular_light, &constants])
}

/// The regulariser as one operator over the light buffers d and s [.., 3] and the target's
/// constants [.., 2] (α and the reference T(max RGB · α)), output a scalar: candle would run the
/// dozen element-wise operators of the formula, and their adjoints, on one thread. The adjoint
/// follows the composition the formula reads as, kinks included: T as [`tone_map_with_slope`],
/// |z| as [`abs_slope`], and max(·, ε) passing half the gradient at a tie (candle's `maximum`).
struct ShadingTerms {
    lambda_diffuse: f64,
    lambda_specular: f64,
}

/// Pixels per chunk of the sums: fixed, so they are the same on any number of threads.
const CHUNK: usize = 4096;

/// max(x, ε) and its slope in x.
#[inline]
fn floor_eps<T: Real>(x: T) -> (T, T) {
    let eps = T::from_f64(EPS);
    if x > eps {
        (x, T::one())
    } else if x == eps {
        (x, T::from_f64(0.5))
    } else {
        (eps, T::zero())
    }
}

/// One pixel's diffuse and specular luminances, the error e = T(lum·α) − reference with dT/dlum
/// (α included), the diffuse share lum_d / max(lum, ε), and max(lum, ε) with its slope.
struct PixelTerms<T> {
    lum_d: T,
    lum_s: T,
    error: T,
    slope: T,
    share: T,
    floor: T,
    floor_slope: T,
}

impl<T: Real> PixelTerms<T> {
    #[inline]
    fn of(d: &[T], s: &[T], alpha: T, reference: T) -> Self {
        let third = T::from_f64(1.0 / 3.0);
        let lum_d = (d[0] + d[1] + d[2]) * third;
        let lum_s = (s[0] + s[1] + s[2]) * third;
        let lum = lum_d + lum_s;
        let (v, slope) = tone_map_with_slope(lum * alpha);
        let (floor, floor_slope) = floor_eps(lum);
        PixelTerms { lum_d, lum_s, error: v - reference, slope: slope * alpha, share: lum_d / floor, floor, floor_slope }
    }
}

impl ShadingTerms {
    /// Sums over pixels of |e|·share, lum_d and lum_s.
    fn sums<T: Real>(d: &[T], s: &[T], k: &[T]) -> [f64; 3] {
        let parts: Vec<[f64; 3]> = d
            .par_chunks(3 * CHUNK)
            .zip(s.par_chunks(3 * CHUNK))
            .zip(k.par_chunks(2 * CHUNK))
            .map(|((d, s), k)| {
                let mut acc = [0.0f64; 3];
                for ((d, s), k) in d.chunks_exact(3).zip(s.chunks_exact(3)).zip(k.chunks_exact(2)) {
                    let p = PixelTerms::of(d, s, k[0], k[1]);
                    acc[0] += (p.error.abs() * p.share).to_f64();
                    acc[1] += p.lum_d.to_f64();
                    acc[2] += p.lum_s.to_f64();
                }
                acc
            })
            .collect();
        parts.iter().fold([0.0; 3], |a, p| [a[0] + p[0], a[1] + p[1], a[2] + p[2]])
    }
}

impl Kernel for ShadingTerms {
    fn name(&self) -> &'static str {
        "shading_regularizer"
    }

    fn output_shape(&self, shapes: &[&[usize]]) -> Result<Vec<usize>> {
        match shapes {
            [d, s, k] if d.last() == Some(&3) && s == d && k.last() == Some(&2) && d[..d.len() - 1] == k[..k.len() - 1] => Ok(vec![]),
            _ => Err(candle_core::Error::Msg(format!("shading regulariser: expected light buffers [.., 3] and constants [.., 2] of one size, got {shapes:?}"))),
        }
    }

    fn forward<T: Real>(&self, x: &[&[T]], _: &[&[usize]], out: &mut [T]) -> Result<()> {
        let n = (x[0].len() / 3).max(1) as f64;
        let [diffuse, lum_d, lum_s] = Self::sums(x[0], x[1], x[2]);
        let (mean_d, _) = floor_eps(lum_d / n);
        out[0] = T::from_f64(self.lambda_diffuse * diffuse / n + self.lambda_specular * (lum_s / n) / mean_d);
        Ok(())
    }

    fn backward<T: Real>(&self, x: &[&[T]], _: &[&[usize]], g: &[T], grads: &mut [Option<&mut [T]>]) -> Result<()> {
        let n = (x[0].len() / 3).max(1) as f64;
        let [_, lum_d, lum_s] = Self::sums(x[0], x[1], x[2]);
        let (mean_d, mean_slope) = floor_eps(lum_d / n);
        let g = g[0].to_f64();
        // The specular term's gradient is the same for every pixel: per lum_s and per lum_d.
        let spec_s = T::from_f64(g * self.lambda_specular / (n * mean_d));
        let spec_d = T::from_f64(-g * self.lambda_specular * (lum_s / n) * mean_slope / (mean_d * mean_d * n));
        let scale = T::from_f64(g * self.lambda_diffuse / n);
        let third = T::from_f64(1.0 / 3.0);
        // ∂/∂lum_d and ∂/∂lum_s of pixel p's terms.
        let pixel = |d: &[T], s: &[T], k: &[T]| -> (T, T) {
            let p = PixelTerms::of(d, s, k[0], k[1]);
            let through_t = abs_slope(p.error) * p.slope * p.share;
            let share_lum = T::zero() - p.lum_d * p.floor_slope / (p.floor * p.floor);
            let share_d = T::one() / p.floor + share_lum;
            let e = p.error.abs();
            (scale * (through_t + e * share_d) + spec_d, scale * (through_t + e * share_lum) + spec_s)
        };
        let [gd, gs, _] = grads else { return Ok(()) };
        // Each pixel's two weights once, for whichever of d and s wants a gradient.
        let weights: Vec<(T, T)> = x[0].par_chunks(3).zip(x[1].par_chunks(3)).zip(x[2].par_chunks(2)).map(|((d, s), k)| pixel(d, s, k)).collect();
        for (target, pick) in [(gd, (|w: &(T, T)| w.0) as fn(&(T, T)) -> T), (gs, |w: &(T, T)| w.1)] {
            let Some(out) = target.as_deref_mut() else { continue };
            out.par_chunks_mut(3).zip(weights.par_iter()).for_each(|(o, w)| {
                let w = pick(w) * third;
                for v in o.iter_mut() {
                    *v += w;
                }
            });
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optim::gradcheck::{check_gradient, check_same_as_composition};
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
    fn the_operator_equals_the_composition_it_replaces() -> anyhow::Result<()> {
        use crate::optim::loss::log_srgb;
        let dev = Device::Cpu;
        let n = 48;
        let mut r = crate::rng::Sampler::from_seed(3);
        // Kinks: black pixels (lum 0, under ε), a pixel at lum = ε exactly, alpha 0 and 1.
        let mut d: Vec<f64> = (0..3 * n).map(|_| r.next_f32() as f64).collect();
        let mut s: Vec<f64> = (0..3 * n).map(|_| 0.3 * r.next_f32() as f64).collect();
        for c in 0..3 {
            (d[c], s[c]) = (0.0, 0.0);
            (d[3 + c], s[3 + c]) = (EPS, 0.0);
        }
        let target: Vec<f64> = (0..4 * n).map(|i| if i % 4 == 3 { [0.0, 1.0, r.next_f32() as f64][i / 4 % 3] } else { r.next_f32() as f64 }).collect();
        let target = LossTarget::new(&Tensor::from_vec(target, (n, 1, 4), &dev)?)?;
        let (dv, sv) = (candle_core::Var::from_tensor(&Tensor::from_vec(d, (n, 1, 3), &dev)?)?, candle_core::Var::from_tensor(&Tensor::from_vec(s, (n, 1, 3), &dev)?)?);
        let (lum_d, lum_s) = (dv.as_tensor().mean_keepdim(D::Minus1)?, sv.as_tensor().mean_keepdim(D::Minus1)?);
        let lum = (&lum_d + &lum_s)?;
        let img = log_srgb(&(&lum * &target.alpha)?)?;
        let share = (&lum_d / lum.maximum(EPS)?)?;
        let diffuse_term = ((img - &target.value_tone_mapped)?.abs()? * share)?.mean_all()?;
        let specular_term = (lum_s.mean_all()? / lum_d.mean_all()?.maximum(EPS)?)?;
        let composed = ((diffuse_term * 0.15)? + (specular_term * 0.0025)?)?;
        let fused = shading_regularizer(dv.as_tensor(), sv.as_tensor(), &target, 0.15, 0.0025)?;
        check_same_as_composition(&composed, &fused, &[&dv, &sv], 1e-12)
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

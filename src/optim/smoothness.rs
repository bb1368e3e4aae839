//! Material smoothness regulariser (NVDiffRecMC's kd/ks "gradient" term), and the normal map's
//! flatness beside it (same jittered lookups): for every shaded pixel,
//! |f(uv) − f(uv + jitter)| averaged over channels, weighted by the pixel's coverage, averaged over
//! pixels. It penalises texture variation at the scale of the jitter (the fit uses σ = 0.005 in UV
//! units; NVDiffRecMC jitters in screen space instead), which spreads gradients to texels the
//! cameras barely see.

use std::sync::Arc;

use candle_core::{Result, Tensor, D};

use super::texture::{jitter_uv, sample_bilinear};

/// Standard deviation of the smoothness lookups' jitter, in UV units (per axis). NVDiffRecMC uses
/// 0.005 too, but jitters its rendered kd/ks buffers in screen coordinates; here the textures are
/// looked up at jittered UVs (docs/model.md, *Differences from NVDiffRecMC*).
pub const SMOOTHNESS_JITTER: f32 = 0.005;

/// The covered pixels' UVs followed by their jittered copies (`texture::jitter_uv`), as one list:
/// a texture is looked up at both by one operator.
pub struct JitteredUv {
    both: Arc<[[f32; 2]]>,
}

impl JitteredUv {
    /// `uv` and its copy jittered by σ = `sigma` from the stream `seed`.
    pub fn new(uv: &[[f32; 2]], sigma: f32, seed: u64) -> Self {
        Self::join(uv, &jitter_uv(uv, sigma, seed))
    }

    /// `uv` and a given jittered copy, which must have as many entries.
    pub fn from_pairs(uv: &[[f32; 2]], uv_jitter: &[[f32; 2]]) -> Result<Self> {
        if uv.len() != uv_jitter.len() {
            return Err(candle_core::Error::Msg(format!("jittered lookups: {} UVs, {} jittered copies (must be equal)", uv.len(), uv_jitter.len())));
        }
        Ok(Self::join(uv, uv_jitter))
    }

    fn join(uv: &[[f32; 2]], uv_jitter: &[[f32; 2]]) -> Self {
        JitteredUv { both: uv.iter().chain(uv_jitter).copied().collect::<Vec<_>>().into() }
    }

    /// Lookups per side.
    pub fn len(&self) -> usize {
        self.both.len() / 2
    }

    pub fn is_empty(&self) -> bool {
        self.both.is_empty()
    }
}

/// A texture looked up at the covered pixels' UVs and at their jittered copies, [N, C] each: what
/// the regularisers below compare.
pub struct JitteredLookups {
    pub at: Tensor,
    pub jittered: Tensor,
}

impl JitteredLookups {
    /// Both sides by one lookup operator over the 2N UVs, then split: the texture gets one
    /// gradient (one scatter, and one accumulation into its gradient on candle's tape, which
    /// costs a zeroed texture and a texture-sized add per use) instead of two.
    pub fn look_up(texture: &Tensor, uv: &JitteredUv) -> Result<Self> {
        let n = uv.len();
        let both = sample_bilinear(texture, &uv.both)?;
        Ok(JitteredLookups { at: both.narrow(0, 0, n)?, jittered: both.narrow(0, n, n)? })
    }

    fn check(&self, what: &str, weight: &Tensor) -> Result<()> {
        let n = self.at.dims().first().copied().unwrap_or(0);
        if weight.dims() != [n] {
            return Err(candle_core::Error::Msg(format!("{what}: {n} lookups, weights {:?} (must be [{n}])", weight.dims())));
        }
        Ok(())
    }
}

/// mean_n( w_n · mean_c |tex(uv_n) − tex(uv_jitter_n)| ).
/// `lookups`: a texture [H, W, C] on the tape, looked up at the pixels and at their jittered
/// copies (see `texture::jitter_uv`); `weight`: [N] per-lookup weights (e.g. ground-truth alpha).
pub fn smoothness_regularizer(lookups: &JitteredLookups, weight: &Tensor) -> Result<Tensor> {
    lookups.check("smoothness regulariser", weight)?;
    weighted_mean(&(&lookups.at - &lookups.jittered)?.abs()?.mean(D::Minus1)?, weight)
}

/// The normal map's flatness (NVDiffRecMC's perturbed-normal term):
/// mean_n( w_n · (1 − ẑ · normalize(m(uv_n) + m(uv_jitter_n))) ) of a tangent-space map m
/// [H, W, 3] looked up as `lookups`. It is 1 − cos of the tilt of the two lookups' mean
/// direction: the map is pulled toward (0, 0, 1), and two neighbours that tilt opposite ways cost
/// nothing extra.
pub fn normal_flatness_regularizer(lookups: &JitteredLookups, weight: &Tensor) -> Result<Tensor> {
    lookups.check("normal flatness", weight)?;
    let sum = (&lookups.at + &lookups.jittered)?;
    let len = sum.sqr()?.sum(D::Minus1)?.affine(1.0, 1e-20)?.sqrt()?;
    let z = sum.narrow(D::Minus1, 2, 1)?.squeeze(D::Minus1)?;
    weighted_mean(&(z / len)?.affine(-1.0, 1.0)?, weight)
}

/// mean_n( w_n · per_lookup_n ).
fn weighted_mean(per_lookup: &Tensor, weight: &Tensor) -> Result<Tensor> {
    (per_lookup * weight.to_dtype(per_lookup.dtype())?)?.mean_all()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optim::gradcheck::check_gradient;
    use crate::optim::texture::jitter_uv;
    use candle_core::{DType, Device};

    /// Lookups `uv`, their jittered copies `uvj` and one weight per lookup: the regularizer's inputs.
    type Lookups = (Arc<[[f32; 2]]>, Arc<[[f32; 2]]>, Tensor);

    /// `n` spread lookups, their copies jittered by σ = 0.05 (seed `seed`) and random weights in
    /// [0, 1]: the inputs of a finite-difference check.
    fn random_lookups(n: usize, seed: u64, dev: &Device) -> Result<Lookups> {
        let uv: Vec<[f32; 2]> = (0..n).map(|i| [(i as f32 * 0.137) % 1.0, (i as f32 * 0.291) % 1.0]).collect();
        let uvj = jitter_uv(&uv, 0.05, seed);
        Ok((uv.into(), uvj, Tensor::rand(0f64, 1.0, n, dev)?))
    }

    #[test]
    fn one_lookup_over_both_sides_equals_two_lookups() -> anyhow::Result<()> {
        let dev = Device::Cpu;
        let tex = Tensor::rand(0f32, 1.0, (6, 7, 3), &dev)?;
        let (uv, uvj, _) = random_lookups(25, 4, &dev)?;
        let both = JitteredLookups::look_up(&tex, &JitteredUv::from_pairs(&uv, &uvj)?)?;
        let values = |t: &Tensor| -> Result<Vec<f32>> { t.flatten_all()?.to_vec1::<f32>() };
        assert_eq!(values(&both.at)?, values(&sample_bilinear(&tex, &uv)?)?);
        assert_eq!(values(&both.jittered)?, values(&sample_bilinear(&tex, &uvj)?)?);
        assert!(JitteredUv::from_pairs(&uv, &uvj[1..]).is_err());
        Ok(())
    }

    #[test]
    fn constant_texture_costs_nothing_and_a_ramp_costs_its_slope() -> Result<()> {
        let dev = Device::Cpu;
        let uv: Arc<[[f32; 2]]> = vec![[0.3, 0.4], [0.6, 0.5]].into();
        let uvj: Arc<[[f32; 2]]> = vec![[0.35, 0.4], [0.6, 0.5]].into();
        let w = Tensor::new(&[1.0f32, 1.0], &dev)?;
        let flat = Tensor::ones((8, 8, 3), DType::F32, &dev)?;
        assert!(smoothness_regularizer(&JitteredLookups::look_up(&flat, &JitteredUv::from_pairs(&uv, &uvj)?)?, &w)?.to_scalar::<f32>()?.abs() < 1e-6);
        // Texture = column index: a shift of 0.05 in u on an 8-wide texture changes it by 0.4.
        let ramp = Tensor::arange(0f32, 8.0, &dev)?.reshape((1, 8, 1))?.broadcast_as((8, 8, 3))?.contiguous()?;
        let got = smoothness_regularizer(&JitteredLookups::look_up(&ramp, &JitteredUv::from_pairs(&uv, &uvj)?)?, &w)?.to_scalar::<f32>()?;
        assert!((got - 0.2).abs() < 1e-5, "{got}");
        Ok(())
    }

    #[test]
    fn gradient_matches_finite_differences() -> anyhow::Result<()> {
        let dev = Device::Cpu;
        let tex = Tensor::rand(0f64, 1.0, (6, 7, 3), &dev)?;
        let (uv, uvj, w) = random_lookups(40, 9, &dev)?;
        check_gradient(|x| smoothness_regularizer(&JitteredLookups::look_up(&x[0], &JitteredUv::from_pairs(&uv, &uvj)?)?, &w), &[tex], 1e-6, 1e-2)?;
        Ok(())
    }

    #[test]
    fn normal_flatness_is_one_minus_the_cosine_of_a_uniform_tilt() -> Result<()> {
        let dev = Device::Cpu;
        let uv: Arc<[[f32; 2]]> = vec![[0.3, 0.4], [0.7, 0.2]].into();
        let uvj: Arc<[[f32; 2]]> = vec![[0.31, 0.42], [0.69, 0.21]].into();
        let w = Tensor::ones(2, DType::F32, &dev)?;
        let uniform = |v: [f32; 3]| -> Result<Tensor> { Tensor::new(&v, &dev)?.reshape((1, 1, 3))?.broadcast_as((4, 4, 3))?.contiguous() };
        assert!(normal_flatness_regularizer(&JitteredLookups::look_up(&uniform([0.0, 0.0, 1.0])?, &JitteredUv::from_pairs(&uv, &uvj)?)?, &w)?.to_scalar::<f32>()?.abs() < 1e-7);
        let theta = 0.3f32;
        let got = normal_flatness_regularizer(&JitteredLookups::look_up(&uniform([theta.sin(), 0.0, theta.cos()])?, &JitteredUv::from_pairs(&uv, &uvj)?)?, &w)?.to_scalar::<f32>()?;
        assert!((got - (1.0 - theta.cos())).abs() < 1e-6, "{got}");
        Ok(())
    }

    #[test]
    fn normal_flatness_gradient_matches_finite_differences() -> anyhow::Result<()> {
        let dev = Device::Cpu;
        let up = Tensor::new(&[0f64, 0.0, 1.0], &dev)?.reshape((1, 1, 3))?.broadcast_as((5, 6, 3))?;
        let map = (Tensor::rand(-0.5f64, 0.5, (5, 6, 3), &dev)? + up)?;
        let (uv, uvj, w) = random_lookups(30, 3, &dev)?;
        check_gradient(|x| normal_flatness_regularizer(&JitteredLookups::look_up(&x[0], &JitteredUv::from_pairs(&uv, &uvj)?)?, &w), &[map], 1e-6, 1e-2)?;
        Ok(())
    }
}

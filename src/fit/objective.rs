//! The loss of one step (docs/model.md, *Loss*): the log-sRGB L1 image loss at the covered pixels,
//! the kd/ks smoothness regularisers (jittered lookups), the light white balance, the
//! monochrome-shading regulariser (Monte Carlo buffers only) and the prior term on views that have
//! labels.

use anyhow::Result;
use candle_core::{Tensor, D};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::color::linear_to_srgb;
use crate::optim::light_balance::light_white_balance;
use crate::optim::loss::{image_loss, LossTarget};
use crate::optim::prior_loss::prior_loss;
use crate::optim::shading::shading_regularizer;
use crate::optim::smoothness::{normal_flatness_regularizer, smoothness_regularizer};
use crate::optim::srgb::srgb_encode;

use super::batch_render::BatchRender;
use super::config::FitConfig;
use super::parameters::Parameters;
use super::training_view::TrainingView;

/// Weight of the normal map's smoothness (the kd/ks term's form on the map's texels):
/// NVDiffRecMC's `lambda_nrm`, like the kd and ks weights, which are theirs too.
pub const NORMAL_SMOOTHNESS: f64 = 0.025;
/// Weight of the normal map's flatness, mean of 1 − ẑ·normalize(m(uv) + m(uv + jitter)) over the
/// covered pixels: NVDiffRecMC's `lambda_nrm2`, which keeps the map from bending the normals
/// where the images do not ask for it (a diffuse surface under one light cannot tell a darker
/// albedo from a tilted normal).
pub const NORMAL_FLATNESS: f64 = 0.25;

/// The value of each term of one step (weighted), for logs and curves.
#[derive(Clone, Copy, Debug, Default, Serialize, Deserialize)]
pub struct LossTerms {
    pub image: f64,
    pub smoothness: f64,
    pub shading: f64,
    /// Light white balance.
    #[serde(default)]
    pub light: f64,
    pub prior: f64,
    /// The normal map's smoothness and flatness.
    #[serde(default)]
    pub normal: f64,
    pub total: f64,
    /// PSNR (dB) of the batch's render against its target, sRGB, pixels with alpha > 0.8.
    pub psnr: f64,
}

fn scalar(t: &Tensor) -> Result<f64> {
    Ok(t.to_dtype(candle_core::DType::F64)?.to_scalar::<f64>()?)
}

/// The seed of step `iteration`'s jittered texture lookups when one of its terms reads them (the
/// kd/ks smoothness, the normal map's terms), for `render_batch`; `None` when none does.
pub fn smoothness_jitter_seed(config: &FitConfig, params: &Parameters, iteration: usize) -> Option<u64> {
    let w = &config.regularizers;
    let reads = (params.normal.is_some() && config.normal_map) || w.kd_smoothness > 0.0 || w.ks_smoothness > 0.0;
    reads.then(|| config.seed ^ (iteration as u64).wrapping_mul(0x9e37_79b9))
}

/// Builds the loss of `render` (of `views`, in order) and reports its terms. `render` must carry
/// the jittered lookups when [`smoothness_jitter_seed`] asks for them.
pub fn objective(views: &[&TrainingView], render: &BatchRender, params: &Parameters, config: &FitConfig, iteration: usize) -> Result<(Tensor, LossTerms)> {
    let target = LossTarget::cat(&views.iter().map(|v| &v.target).collect::<Vec<_>>())?;
    let image = image_loss(&render.rgb, None, &target)?;
    let mut total = image.clone();
    let mut terms = LossTerms { image: scalar(&image)?, ..Default::default() };

    let w = &config.regularizers;
    let alpha = target.alpha.flatten_all()?;
    let normal_map = params.normal.as_ref().filter(|_| config.normal_map);
    let smoothness_lookups = || {
        render.jittered.as_ref().ok_or_else(|| anyhow::anyhow!("the smoothness terms need the render's jittered lookups (render_batch with objective::smoothness_jitter_seed)"))
    };
    if normal_map.is_some() {
        let lookups = smoothness_lookups()?.normal_map.as_ref().ok_or_else(|| anyhow::anyhow!("the normal map's terms need its jittered lookups"))?;
        let smooth = smoothness_regularizer(lookups, &alpha)?.affine(NORMAL_SMOOTHNESS, 0.0)?;
        let flat = normal_flatness_regularizer(lookups, &alpha)?.affine(NORMAL_FLATNESS, 0.0)?;
        let t = (smooth + flat)?;
        terms.normal = scalar(&t)?;
        total = (total + t)?;
    }
    if w.kd_smoothness > 0.0 || w.ks_smoothness > 0.0 {
        let lookups = smoothness_lookups()?;
        let smooth = (smoothness_regularizer(&lookups.kd, &alpha)?.affine(w.kd_smoothness, 0.0)? + smoothness_regularizer(&lookups.ks, &alpha)?.affine(w.ks_smoothness, 0.0)?)?;
        terms.smoothness = scalar(&smooth)?;
        total = (total + smooth)?;
    }
    if w.light_white_balance > 0.0 {
        let l = light_white_balance(params.light.as_tensor())?.affine(w.light_white_balance, 0.0)?;
        terms.light = scalar(&l)?;
        total = (total + l)?;
    }
    if let Some((diffuse, specular)) = &render.light_buffers {
        if w.shading_diffuse > 0.0 || w.shading_specular > 0.0 {
            let s = shading_regularizer(diffuse, specular, &target, w.shading_diffuse, w.shading_specular)?;
            terms.shading = scalar(&s)?;
            total = (total + s)?;
        }
    }
    let schedule = config.prior.schedule(iteration, config.iterations);
    let labelled: Vec<usize> = (0..views.len()).filter(|&k| views[k].labels.is_some()).collect();
    if schedule > 0.0 && !labelled.is_empty() {
        let mut prior: Option<Tensor> = None;
        for &k in &labelled {
            let labels = views[k].labels.as_ref().expect("filtered");
            let (start, len) = (render.offsets[k], views[k].len());
            let kd = render.kd.narrow(0, start, len)?.reshape((len, 1, 3))?;
            let ks = render.ks.narrow(0, start, len)?.reshape((len, 1, 3))?;
            let mut parts = Vec::new();
            let p = &config.prior;
            if p.albedo > 0.0 {
                parts.push(prior_loss(&srgb_encode(&kd.clamp(0.0, 1.0)?)?, &labels.albedo_srgb, &labels.mask, p.albedo * schedule)?);
            }
            if p.roughness > 0.0 {
                parts.push(prior_loss(&ks.narrow(D::Minus1, 1, 1)?, &labels.roughness, &labels.mask, p.roughness * schedule)?);
            }
            if p.metallic > 0.0 {
                parts.push(prior_loss(&ks.narrow(D::Minus1, 2, 1)?, &labels.metallic, &labels.mask, p.metallic * schedule)?);
            }
            if let (true, Some(n)) = (p.normal > 0.0, &render.normals) {
                let n = n.narrow(0, start, len)?.reshape((len, 1, 3))?;
                parts.push(prior_loss(&n, &labels.normal_world, &labels.normal_mask, p.normal * schedule)?);
            }
            for t in parts {
                let t = t.affine(1.0 / labelled.len() as f64, 0.0)?;
                prior = Some(match prior {
                    Some(acc) => (acc + t)?,
                    None => t,
                });
            }
        }
        if let Some(prior) = prior {
            terms.prior = scalar(&prior)?;
            total = (total + prior)?;
        }
    }
    terms.total = scalar(&total)?;
    terms.psnr = batch_psnr(&render.rgb, &target.rgba)?;
    Ok((total, terms))
}

/// PSNR of linear `rgb` [N, 1, 3] against linear RGBA `target` [N, 1, 4], both sRGB-encoded and
/// clamped to [0, 1], over pixels with target alpha > 0.8 (the relighting protocol's mask).
pub fn batch_psnr(rgb: &Tensor, target: &Tensor) -> Result<f64> {
    let r = rgb.detach().flatten_all()?.to_dtype(candle_core::DType::F32)?.to_vec1::<f32>()?;
    let t = target.flatten_all()?.to_dtype(candle_core::DType::F32)?.to_vec1::<f32>()?;
    // Fixed chunks summed in order: the same figure on any number of threads.
    const PIXELS_PER_CHUNK: usize = 4096;
    let parts: Vec<(f64, usize)> = r
        .par_chunks(3 * PIXELS_PER_CHUNK)
        .zip(t.par_chunks(4 * PIXELS_PER_CHUNK))
        .map(|(r, t)| {
            let (mut sum, mut count) = (0.0f64, 0usize);
            for (p, q) in r.chunks_exact(3).zip(t.chunks_exact(4)) {
                if q[3] <= 0.8 {
                    continue;
                }
                for c in 0..3 {
                    let d = linear_to_srgb(p[c].clamp(0.0, 1.0)) as f64 - linear_to_srgb(q[c].clamp(0.0, 1.0)) as f64;
                    sum += d * d;
                }
                count += 3;
            }
            (sum, count)
        })
        .collect();
    let (sum, count) = parts.iter().fold((0.0, 0), |(s, n), &(ps, pn)| (s + ps, n + pn));
    Ok(if count == 0 { f64::NAN } else { -10.0 * (sum / count as f64).log10() })
}

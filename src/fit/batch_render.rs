//! The differentiable render of a batch of training views: texture lookups at the covered pixels'
//! atlas UVs, then split-sum or Monte Carlo shading, all on candle's tape. Pixels of the batch's
//! views are concatenated, so each operator runs once per iteration (one light prefilter or one
//! light-sampler build per step, whatever the batch size).

use std::sync::Arc;

use anyhow::Result;
use candle_core::{Tensor, D};

use crate::geometry::bvh::Bvh;
use crate::light::brdf_lut::BrdfLut;
use crate::optim::texture::sample_bilinear;
use crate::render::effects::Effects;
use crate::render::splitsum_op::{shade_splitsum, LightMaps, SplitSumShading};
use crate::render::view::ShadingMode;

use super::parameters::Parameters;
use super::training_view::TrainingView;

/// What every step's shading needs besides the parameters (built once per run).
pub struct ShadingContext {
    pub mode: ShadingMode,
    pub effects: Effects,
    pub spp: u32,
    pub denoise: bool,
    pub seed: u64,
    pub ray_epsilon: f32,
    pub bvh: Arc<Bvh>,
    pub light_maps: Arc<LightMaps>,
    pub lut: Arc<BrdfLut>,
}

/// The batch's buffers, rows = the views' covered pixels in order.
pub struct BatchRender {
    /// Linear radiance [N, 1, 3].
    pub rgb: Tensor,
    /// kd and ks looked up at each pixel, [N, 3].
    pub kd: Tensor,
    pub ks: Tensor,
    /// Demodulated diffuse light and specular light [N, 1, 3] (Monte Carlo only; the shading
    /// regulariser reads them).
    pub light_buffers: Option<(Tensor, Tensor)>,
    /// Where each view's rows start (and the total at the end).
    pub offsets: Vec<usize>,
}

/// Row offsets of the views' pixels in the concatenation.
pub fn row_offsets(views: &[&TrainingView]) -> Vec<usize> {
    let mut offsets = vec![0];
    for v in views {
        offsets.push(offsets[offsets.len() - 1] + v.len());
    }
    offsets
}

/// Renders `views` with the current `params`. `iteration` reseeds the Monte Carlo samples.
pub fn render_batch(views: &[&TrainingView], params: &Parameters, ctx: &ShadingContext, iteration: u64) -> Result<BatchRender> {
    let offsets = row_offsets(views);
    let n = offsets[offsets.len() - 1];
    let uv: Arc<[[f32; 2]]> = views.iter().flat_map(|v| v.uv.iter().copied()).collect::<Vec<_>>().into();
    let kd = sample_bilinear(params.kd.as_tensor(), &uv)?;
    let ks = sample_bilinear(params.ks.as_tensor(), &uv)?;
    let _ = iteration;
    let (rgb, light_buffers) = match ctx.mode {
        ShadingMode::SplitSum => {
            let geometry: Vec<_> = views.iter().flat_map(|v| v.normal_and_view()).collect();
            let op = SplitSumShading::new(&geometry, ctx.light_maps.clone(), ctx.lut.clone(), ctx.effects);
            (shade_splitsum(&op, &kd, &ks, params.light.as_tensor())?, None)
        }
        ShadingMode::MonteCarlo => anyhow::bail!("Monte Carlo training is not available yet"),
    };
    let rgb = rgb.reshape((n, 1, 3))?;
    let light_buffers = light_buffers.map(|(d, s): (Tensor, Tensor)| -> Result<(Tensor, Tensor)> { Ok((d.reshape((n, 1, 3))?, s.reshape((n, 1, 3))?)) }).transpose()?;
    let _ = D::Minus1;
    Ok(BatchRender { rgb, kd, ks, light_buffers, offsets })
}

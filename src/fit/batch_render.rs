//! The differentiable render of a batch of training views: texture lookups at the covered pixels'
//! atlas UVs, then split-sum or Monte Carlo shading, all on candle's tape. Pixels of the batch's
//! views are concatenated, so each operator runs once per iteration (one light prefilter or one
//! light-sampler build per step, whatever the batch size).

use std::sync::Arc;

use anyhow::Result;
use candle_core::{Tensor, D};

use crate::geometry::bvh::Bvh;
use crate::geometry::Mesh;
use crate::light::brdf_lut::BrdfLut;
use crate::optim::texture::sample_bilinear;
use crate::render::denoise::{BilateralParams, CrossBilateral};
use crate::render::effects::Effects;
use crate::render::montecarlo::{McSettings, TraceScene};
use crate::render::montecarlo_op::{shade_mc, shade_mc_with_normal, McPixel, McShading};
use crate::render::splitsum_op::{shade_splitsum, LightMaps, SplitSumShading};
use crate::render::view::ShadingMode;

use super::parameters::Parameters;
use super::pixel_scatter::PixelMap;
use super::training_view::TrainingView;

/// What every step's shading needs besides the parameters (built once per run).
pub struct ShadingContext {
    pub mode: ShadingMode,
    pub effects: Effects,
    pub spp: u32,
    pub denoise: bool,
    pub seed: u64,
    pub ray_epsilon: f32,
    /// The mesh the textures live on (bounce rays land on it) and its BVH.
    pub mesh: Arc<Mesh>,
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
    /// Atlas UV of each row (the lookups above; the smoothness regulariser jitters them).
    pub uv: Arc<[[f32; 2]]>,
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
/// `normals` [N, 3], when given, are the covered pixels' shading normals as a function of the
/// vertices (`fit::vertex_refinement`; Monte Carlo only).
pub fn render_batch(views: &[&TrainingView], params: &Parameters, ctx: &ShadingContext, iteration: u64, normals: Option<&Tensor>) -> Result<BatchRender> {
    let offsets = row_offsets(views);
    let n = offsets[offsets.len() - 1];
    let uv: Arc<[[f32; 2]]> = views.iter().flat_map(|v| v.uv.iter().copied()).collect::<Vec<_>>().into();
    let kd = sample_bilinear(params.kd.as_tensor(), &uv)?;
    let ks = sample_bilinear(params.ks.as_tensor(), &uv)?;
    let (rgb, light_buffers) = match ctx.mode {
        ShadingMode::SplitSum => {
            if normals.is_some() {
                anyhow::bail!("vertex refinement needs Monte Carlo shading (the split-sum operator has no normal input)");
            }
            let geometry: Vec<_> = views.iter().flat_map(|v| v.normal_and_view()).collect();
            let op = SplitSumShading::new(&geometry, ctx.light_maps.clone(), ctx.lut.clone(), ctx.effects);
            (shade_splitsum(&op, &kd, &ks, params.light.as_tensor())?, None)
        }
        ShadingMode::MonteCarlo => {
            let (diffuse, specular) = shade_batch_mc(views, &offsets, &kd, &ks, params, ctx, iteration, normals)?;
            let ks_metal = ks.narrow(D::Minus1, 2, 1)?;
            let albedo = kd.broadcast_mul(&ks_metal.affine(-1.0, 1.0)?)?;
            let rgb = ((albedo * &diffuse)? + &specular)?;
            (rgb, Some((diffuse, specular)))
        }
    };
    let rgb = rgb.reshape((n, 1, 3))?;
    let light_buffers = light_buffers.map(|(d, s): (Tensor, Tensor)| -> Result<(Tensor, Tensor)> { Ok((d.reshape((n, 1, 3))?, s.reshape((n, 1, 3))?)) }).transpose()?;
    Ok(BatchRender { rgb, kd, ks, light_buffers, uv, offsets })
}

/// Monte Carlo shading of the batch: (demodulated diffuse light, specular radiance), [N, 3] each,
/// optionally denoised per view in image space.
#[allow(clippy::too_many_arguments)] // render_batch's inputs, passed on
fn shade_batch_mc(views: &[&TrainingView], offsets: &[usize], kd: &Tensor, ks: &Tensor, params: &Parameters, ctx: &ShadingContext, iteration: u64, normals: Option<&Tensor>) -> Result<(Tensor, Tensor)> {
    let to_rows = |t: &Tensor| -> Result<Vec<[f32; 3]>> {
        Ok(t.detach().flatten_all()?.to_vec1::<f32>()?.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect())
    };
    let pixels: Vec<Option<McPixel>> = views
        .iter()
        .flat_map(|v| {
            let stride = (v.camera.width * v.camera.height) as u64;
            v.surfels.iter().zip(&v.pixels).map(move |(s, &p)| Some(McPixel::from_surfel(s, v.origin, v.index as u64 * stride + p as u64)))
        })
        .collect();
    // A new sample set every iteration (the estimator is unbiased across steps, not within one).
    let settings = McSettings {
        spp: ctx.spp,
        seed: ctx.seed ^ iteration.wrapping_add(1).wrapping_mul(0x9e37_79b9_7f4a_7c15),
        effects: ctx.effects,
        ray_epsilon: ctx.ray_epsilon,
    };
    let light = params.light_cube()?;
    // Bounces read the current textures where they land; without interreflection nothing is read.
    let textures = if ctx.effects.interreflection() { Some(params.textures()?) } else { None };
    let materials: &dyn crate::material::MaterialField = match &textures {
        Some(t) => t,
        None => &*ctx.mesh,
    };
    let scene = TraceScene { mesh: &ctx.mesh, bvh: &ctx.bvh, materials };
    let op = McShading::prepare(&pixels, &to_rows(kd)?, &to_rows(ks)?, &light, &scene, &settings);
    let out = match normals {
        Some(n) => shade_mc_with_normal(&op, kd, ks, params.light.as_tensor(), n)?,
        None => shade_mc(&op, kd, ks, params.light.as_tensor())?,
    };
    let (mut diffuse, mut specular) = (out.narrow(D::Minus1, 0, 3)?, out.narrow(D::Minus1, 3, 3)?);
    if ctx.denoise {
        let (mut d, mut s) = (Vec::new(), Vec::new());
        for (k, v) in views.iter().enumerate() {
            let (start, len) = (offsets[k], v.len());
            let map = PixelMap { pixels: v.pixels.clone().into(), width: v.camera.width, height: v.camera.height };
            let filter = CrossBilateral::new(Arc::new(v.denoise_guides()?), BilateralParams::default());
            d.push(map.gather(&filter.apply(&map.scatter(&diffuse.narrow(0, start, len)?)?)?)?);
            s.push(map.gather(&filter.apply(&map.scatter(&specular.narrow(0, start, len)?)?)?)?);
        }
        diffuse = Tensor::cat(&d, 0)?;
        specular = Tensor::cat(&s, 0)?;
    }
    Ok((diffuse, specular))
}

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
use crate::material::normal_map::{frames_at, perturb_on_tape};
use crate::optim::smoothness::{JitteredLookups, JitteredUv, SMOOTHNESS_JITTER};
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
    /// Where each view's rows start (and the total at the end).
    pub offsets: Vec<usize>,
    /// The shading normals [N, 3] on the tape, when they are parameters (the normal map, the
    /// vertex refinement); `None` when they are the mesh's fixed ones.
    pub normals: Option<Tensor>,
    /// The textures at the rows' UVs and at their jittered copies, when the step asked for them
    /// (the smoothness regularisers read them).
    pub jittered: Option<SmoothnessLookups>,
}

/// kd, ks and the normal map (when there is one) looked up at the rows' UVs and at their jittered
/// copies; the `at` sides are the render's own lookups.
pub struct SmoothnessLookups {
    pub kd: JitteredLookups,
    pub ks: JitteredLookups,
    pub normal_map: Option<JitteredLookups>,
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
/// vertices (`fit::vertex_refinement`; Monte Carlo only). A normal map in `params` perturbs them
/// (or the views' own normals) on the tape. `jitter_seed`, when given, also looks the textures up
/// at UVs jittered from that stream (`objective::smoothness_jitter_seed` says when a step needs
/// them), in the same operator as the render's own lookups.
pub fn render_batch(views: &[&TrainingView], params: &Parameters, ctx: &ShadingContext, iteration: u64, normals: Option<&Tensor>, jitter_seed: Option<u64>) -> Result<BatchRender> {
    let offsets = row_offsets(views);
    let n = offsets[offsets.len() - 1];
    let uv: Arc<[[f32; 2]]> = views.iter().flat_map(|v| v.uv.iter().copied()).collect::<Vec<_>>().into();
    let jittered_uv = jitter_seed.map(|seed| JitteredUv::new(&uv, SMOOTHNESS_JITTER, seed));
    // A texture at the rows' UVs, and at their jittered copies too when asked.
    let look_up = |texture: &Tensor| -> Result<(Tensor, Option<JitteredLookups>)> {
        Ok(match &jittered_uv {
            Some(j) => {
                let both = JitteredLookups::look_up(texture, j)?;
                (both.at.clone(), Some(both))
            }
            None => (sample_bilinear(texture, &uv)?, None),
        })
    };
    let (kd, kd_jittered) = look_up(params.kd.as_tensor())?;
    let (ks, ks_jittered) = look_up(params.ks.as_tensor())?;
    let (mapped, map_jittered) = match &params.normal {
        Some(map) => {
            let (m, jittered) = look_up(map.map.as_tensor())?;
            (Some(normal_mapped(views, n, map, &m, normals)?), jittered)
        }
        None => (None, None),
    };
    let jittered = match (kd_jittered, ks_jittered) {
        (Some(kd), Some(ks)) => Some(SmoothnessLookups { kd, ks, normal_map: map_jittered }),
        _ => None,
    };
    let normals = mapped.or_else(|| normals.cloned());
    let normals = normals.as_ref();
    let (rgb, light_buffers) = match ctx.mode {
        ShadingMode::SplitSum => {
            if normals.is_some() {
                anyhow::bail!("vertex refinement and the normal map need Monte Carlo shading (the split-sum operator has no normal input)");
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
    Ok(BatchRender { rgb, kd, ks, light_buffers, offsets, normals: normals.cloned(), jittered })
}

/// The pixels' shading normals through the normal map, [N, 3] on the tape: the map looked up at
/// the pixels' UVs (`m`) perturbs `normals` (vertex refinement's) or else the views' own normals,
/// in the frames of the pixels' triangles (constants of the normals' values).
fn normal_mapped(views: &[&TrainingView], n: usize, map: &super::parameters::NormalParameter, m: &Tensor, normals: Option<&Tensor>) -> Result<Tensor> {
    let dev = map.map.as_tensor().device();
    let base = match normals {
        Some(t) => t.clone(),
        None => {
            let rows: Vec<f32> = views.iter().flat_map(|v| v.surfels.iter().flat_map(|s| s.normal.to_array())).collect();
            Tensor::from_vec(rows, (n, 3), dev)?
        }
    };
    let values: Vec<f32> = base.detach().flatten_all()?.to_vec1::<f32>()?;
    let points = views.iter().flat_map(|v| v.surfels.iter()).zip(values.chunks_exact(3)).map(|(s, nv)| (s.triangle, s.bary3(), glam::Vec3::from_slice(nv)));
    let (t, b) = frames_at(&map.tangents, points);
    let (t, b) = (Tensor::from_vec(t, (n, 3), dev)?, Tensor::from_vec(b, (n, 3), dev)?);
    Ok(perturb_on_tape(&base, &t, &b, m)?)
}

/// Monte Carlo shading of the batch: (demodulated diffuse light, specular radiance), [N, 3] each,
/// optionally denoised per view in image space.
#[allow(clippy::too_many_arguments)] // render_batch's inputs, passed on
fn shade_batch_mc(views: &[&TrainingView], offsets: &[usize], kd: &Tensor, ks: &Tensor, params: &Parameters, ctx: &ShadingContext, iteration: u64, normals: Option<&Tensor>) -> Result<(Tensor, Tensor)> {
    let to_rows = |t: &Tensor| -> Result<Vec<[f32; 3]>> {
        Ok(t.detach().flatten_all()?.to_vec1::<f32>()?.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect())
    };
    let mut pixels: Vec<Option<McPixel>> = views
        .iter()
        .flat_map(|v| {
            let stride = (v.camera.width * v.camera.height) as u64;
            v.surfels.iter().zip(&v.pixels).map(move |(s, &p)| Some(McPixel::from_surfel(s, v.origin, v.index as u64 * stride + p as u64)))
        })
        .collect();
    // Samples are drawn around the shading normal's current value, as the renderer draws them:
    // a normal map's tilt can be far from the mesh's normal, and directions below the mesh's
    // hemisphere but above the tilted one would otherwise never be drawn.
    if let Some(n) = normals {
        for (p, row) in pixels.iter_mut().zip(to_rows(n)?) {
            if let Some(p) = p {
                // On the camera's side, as the operator flips its input (two-sided shading).
                let n = glam::Vec3::from_array(row).try_normalize().unwrap_or(p.surfel.normal);
                p.surfel.normal = if n.dot(p.surfel.normal) < 0.0 { -n } else { n };
            }
        }
    }
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
    let (kd_rows, ks_rows) = (to_rows(kd)?, to_rows(ks)?);
    let out = match normals {
        Some(n) => shade_mc_with_normal(&McShading::prepare_for_normal_input(&pixels, &kd_rows, &ks_rows, &light, &scene, &settings), kd, ks, params.light.as_tensor(), n)?,
        None => shade_mc(&McShading::prepare(&pixels, &kd_rows, &ks_rows, &light, &scene, &settings), kd, ks, params.light.as_tensor())?,
    };
    // The denoiser filters both buffers (six channels) in one pass per view.
    let out = if ctx.denoise {
        let mut filtered = Vec::with_capacity(views.len());
        for (k, v) in views.iter().enumerate() {
            let map = PixelMap { pixels: v.pixels.clone().into(), width: v.camera.width, height: v.camera.height };
            let filter = CrossBilateral::new(Arc::new(v.denoise_guides()?), BilateralParams::default());
            filtered.push(map.gather(&filter.apply(&map.scatter(&out.narrow(0, offsets[k], v.len())?)?)?)?);
        }
        Tensor::cat(&filtered, 0)?
    } else {
        out
    };
    Ok((out.narrow(D::Minus1, 0, 3)?, out.narrow(D::Minus1, 3, 3)?))
}

//! Monte Carlo direct lighting (NVDiffRecMC): per pixel, stratified light samples (texel pdf ∝
//! max(rgb)·solid angle) and BSDF samples (cosine or GGX VNDF) combined with the balance heuristic,
//! shadow rays through the BVH when shadows are on. Results are demodulated: `diffuse` is the
//! irradiance term before the kd(1−m) product (what a denoiser should filter), `specular` is final.
//! Each pixel draws from its own seeded stream, so a render is reproducible in any thread order.

use glam::Vec3;
use rayon::prelude::*;

use crate::geometry::bvh::Bvh;
use crate::light::sampler::LightSampler;
use crate::material::brdf::{self, COS_EPS};
use crate::material::SurfaceParams;
use crate::math::Frame;
use crate::render::effects::Effects;
use crate::render::gbuffer::{GBuffer, Surfel};
use crate::rng::Sampler;

#[derive(Clone, Copy, Debug)]
pub struct McSettings {
    pub spp: u32,
    pub seed: u64,
    pub effects: Effects,
    /// Shadow-ray offset along the geometric normal, in world units (scale with the scene).
    pub ray_epsilon: f32,
}

/// Demodulated shading of one view.
pub struct McBuffers {
    /// Σ L·cos/π·w/pdf: multiply by kd(1−m) for diffuse radiance.
    pub diffuse: Vec<Vec3>,
    /// Specular radiance.
    pub specular: Vec<Vec3>,
    /// Shadow rays traced (zero when shadows are off: an effect that is off costs nothing).
    pub shadow_rays: u64,
}

impl McBuffers {
    /// Remodulate: radiance per pixel.
    pub fn radiance(&self, params: &[Option<SurfaceParams>]) -> Vec<Vec3> {
        self.diffuse
            .iter()
            .zip(&self.specular)
            .zip(params)
            .map(|((d, s), p)| p.map_or(Vec3::ZERO, |p| p.kd * (1.0 - p.metallic) * *d + *s))
            .collect()
    }
}

fn luminance(c: Vec3) -> f32 {
    c.dot(Vec3::new(0.2126, 0.7152, 0.0722))
}

/// Probability of sampling the specular lobe: its Fresnel-weighted share, kept within [0.1, 0.9]
/// so neither lobe is starved.
fn specular_probability(p: &SurfaceParams, nov: f32, effects: Effects) -> f32 {
    if !effects.specular {
        return 0.0;
    }
    let f0 = Vec3::splat(0.04).lerp(p.kd, p.metallic);
    let fresnel = f0 + (Vec3::ONE - f0) * (1.0 - nov).powi(5);
    let spec = luminance(fresnel);
    let diff = luminance(p.kd) * (1.0 - p.metallic);
    if diff <= 0.0 {
        return 1.0;
    }
    (spec / (spec + diff)).clamp(0.1, 0.9)
}

/// One contributing sample of a pixel's estimator: incident direction (world and local), the
/// radiance the light gives along it, and its weight (MIS weight / pdf). Zero-contribution
/// samples (below the surface, occluded, zero pdf) are not reported.
#[derive(Clone, Copy, Debug)]
pub struct McSample {
    pub wi: Vec3,
    pub wi_l: Vec3,
    pub radiance: Vec3,
    pub weight: f32,
}

/// The local outgoing direction `shade_point` uses for a surfel: kept just above the shading
/// horizon, because interpolated normals can face slightly away from the viewer at silhouettes.
pub fn local_outgoing(s: &Surfel, wo: Vec3) -> (Frame, Vec3) {
    let frame = Frame::from_normal(s.normal);
    let wo_l = frame.to_local(wo);
    let wo_l = if wo_l.z < COS_EPS { Vec3::new(wo_l.x, wo_l.y, COS_EPS).normalize_or(glam::Vec3::Z) } else { wo_l };
    (frame, wo_l)
}

/// Draws one surfel's samples (`spp` of each strategy, balance heuristic) and hands each
/// contributing one to `visit`; returns the shadow rays traced. The single sampling code path of
/// the renderer and of the differentiable shader (`montecarlo_op`), so both see the same samples.
#[allow(clippy::too_many_arguments)] // the renderer's state for one surfel, passed as is
pub fn draw_samples(
    s: &Surfel,
    wo: Vec3,
    p: &SurfaceParams,
    light: &LightSampler,
    bvh: &Bvh,
    settings: &McSettings,
    rng: &mut Sampler,
    visit: &mut dyn FnMut(McSample),
) -> u64 {
    let (frame, wo_l) = local_outgoing(s, wo);
    let nov = brdf::clamp_cos(wo_l.z);
    let alpha = brdf::alpha_from_roughness(p.roughness);
    let ps = specular_probability(p, nov, settings.effects);
    let bsdf_pdf = |wi_l: Vec3| -> f32 {
        let mut pdf = (1.0 - ps) * brdf::pdf_cosine(wi_l);
        if ps > 0.0 {
            pdf += ps * brdf::pdf_ggx_vndf(wo_l, wi_l, alpha);
        }
        pdf
    };
    let origin = s.position + s.geo_normal * settings.ray_epsilon;
    let mut rays = 0u64;
    let mut visible = |wi: Vec3| -> bool {
        // Light arriving from behind the geometric surface is blocked by the surface itself.
        if wi.dot(s.geo_normal) <= 0.0 {
            return false;
        }
        if !settings.effects.shadows {
            return true;
        }
        rays += 1;
        !bvh.any_hit(origin, wi, settings.ray_epsilon, f32::INFINITY)
    };
    let n = settings.spp.max(1);
    for k in 0..n {
        // Light sample, stratified in its first dimension.
        let (r0, r1) = rng.next_2d();
        let ls = light.sample(((k as f32 + r0) / n as f32, r1));
        let wi_l = frame.to_local(ls.dir);
        if ls.pdf > 0.0 && wi_l.z > 0.0 && visible(ls.dir) {
            let w = ls.pdf / (ls.pdf + bsdf_pdf(wi_l));
            visit(McSample { wi: ls.dir, wi_l, radiance: ls.radiance, weight: w / ls.pdf });
        }
        // BSDF sample.
        let lobe = rng.next_f32();
        let u = rng.next_2d();
        let wi_l = if lobe < ps { brdf::sample_ggx_vndf(wo_l, alpha, u) } else { brdf::sample_cosine(u) };
        if wi_l.z > 0.0 {
            let pdf_b = bsdf_pdf(wi_l);
            let wi = frame.to_world(wi_l);
            if pdf_b > 0.0 && visible(wi) {
                let w = pdf_b / (pdf_b + light.pdf(wi));
                visit(McSample { wi, wi_l, radiance: light.radiance(wi), weight: w / pdf_b });
            }
        }
    }
    rays
}

/// Diffuse (demodulated) and specular estimates for one surfel, `spp` samples of each strategy.
/// Returns (diffuse, specular, shadow rays traced).
pub fn shade_point(s: &Surfel, wo: Vec3, p: &SurfaceParams, light: &LightSampler, bvh: &Bvh, settings: &McSettings, rng: &mut Sampler) -> (Vec3, Vec3, u64) {
    let (_, wo_l) = local_outgoing(s, wo);
    let (mut diffuse, mut specular) = (Vec3::ZERO, Vec3::ZERO);
    let rays = draw_samples(s, wo, p, light, bvh, settings, rng, &mut |smp| {
        let cos = brdf::clamp_cos(smp.wi_l.z);
        diffuse += smp.radiance * (cos / std::f32::consts::PI * smp.weight);
        if settings.effects.specular {
            specular += brdf::eval(p, wo_l, smp.wi_l).specular * smp.radiance * smp.weight;
        }
    });
    let n = settings.spp.max(1) as f32;
    (diffuse / n, specular / n, rays)
}

/// Shade every covered pixel. `stream_offset` separates the random streams of different views.
pub fn shade(gbuf: &GBuffer, params: &[Option<SurfaceParams>], light: &LightSampler, bvh: &Bvh, settings: &McSettings, stream_offset: u64) -> McBuffers {
    let shaded: Vec<(Vec3, Vec3, u64)> = gbuf
        .surfels
        .par_iter()
        .zip(params.par_iter())
        .enumerate()
        .map(|(i, (s, p))| match (s, p) {
            (Some(s), Some(p)) => {
                let mut rng = Sampler::new(settings.seed, stream_offset + i as u64);
                let wo = (gbuf.origin - s.position).normalize();
                shade_point(s, wo, p, light, bvh, settings, &mut rng)
            }
            _ => (Vec3::ZERO, Vec3::ZERO, 0),
        })
        .collect();
    McBuffers {
        diffuse: shaded.iter().map(|s| s.0).collect(),
        specular: shaded.iter().map(|s| s.1).collect(),
        shadow_rays: shaded.iter().map(|s| s.2).sum(),
    }
}

//! Monte Carlo shading (NVDiffRecMC): per pixel, stratified light samples (texel pdf ∝
//! max(rgb)·solid angle) and BSDF samples (cosine or GGX VNDF) combined with the balance heuristic,
//! shadow rays through the BVH when shadows are on. Results are demodulated: `diffuse` is the
//! irradiance term before the kd(1−m) product (what a denoiser should filter), `specular` is final.
//! Each pixel draws from its own seeded stream, so a render is reproducible in any thread order.
//!
//! With interreflection on (`Effects::indirect_bounces` > 0), a BSDF sample whose ray the object
//! blocks is not dropped: it carries the radiance the blocking surface sends back, estimated by
//! the same sampler at that point with one sample of each strategy (next-event estimation plus a
//! BSDF sample), recursively for the remaining bounces. Only BSDF sampling can find a surface, so
//! such a sample's weight is 1/pdf (no MIS weight against the light, which cannot produce it).
//!
//! Work per sample is kept to what can change the result: no shadow ray for a direction below
//! either horizon or with zero pdf, and at the vertices of bounce paths (whose radiance is a
//! detached constant, so nothing is differentiated through it) none for a direction whose light
//! is black either. At the pixel's own vertex a black texel still gets its ray: the light is a
//! parameter, and the texel's gradient needs its visibility.

use glam::Vec3;
use rayon::prelude::*;

use crate::color::luminance;
use crate::geometry::bvh::Bvh;
use crate::geometry::Mesh;
use crate::light::sampler::{LightLookup, LightSampler};
use crate::material::brdf::{self, COS_EPS};
use crate::material::{MaterialField, SurfaceParams};
use crate::math::Frame;
use crate::render::effects::Effects;
use crate::render::gbuffer::{GBuffer, Surfel};
use crate::render::ray_count::{self, RayCount};
use crate::rng::Sampler;

#[derive(Clone, Copy, Debug)]
pub struct McSettings {
    pub spp: u32,
    pub seed: u64,
    pub effects: Effects,
    /// Shadow-ray offset along the geometric normal, in world units (scale with the scene).
    pub ray_epsilon: f32,
}

/// What secondary rays see: the geometry (shadow rays and the surfaces interreflection hits) and
/// the material anywhere on it (looked up only when interreflection is on).
#[derive(Clone, Copy)]
pub struct TraceScene<'a> {
    pub mesh: &'a Mesh,
    pub bvh: &'a Bvh,
    pub materials: &'a dyn MaterialField,
}

/// Demodulated shading of one view.
pub struct McBuffers {
    /// Σ L·cos/π·w/pdf: multiply by kd(1−m) for diffuse radiance.
    pub diffuse: Vec<Vec3>,
    /// Specular radiance.
    pub specular: Vec<Vec3>,
    /// Rays traced after the primary ones: shadow rays, and bounce rays with interreflection (zero
    /// when shadows are off: an effect that is off costs nothing). The G-buffer's primary rays
    /// are counted where it is traced.
    pub rays: RayCount,
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

/// Probability of sampling the specular lobe: its Fresnel-weighted share, kept within [0.1, 0.9]
/// so neither lobe is starved; 1 when there is no diffuse lobe (kd(1−m) = 0), 0 when specular is off.
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

/// Where a sample's incident radiance comes from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Incident {
    /// The environment light: this texel of the cube map (the nearest-texel read along `wi`).
    Light(u32),
    /// The object's own surface along `wi` (interreflection): an estimate of its outgoing radiance.
    Surface,
}

/// One contributing sample of a pixel's estimator: incident direction (world and local), the
/// radiance arriving along it, where that comes from, and its weight (MIS weight / pdf).
/// Zero-contribution samples (below the surface, occluded without interreflection, zero pdf) are
/// not reported.
#[derive(Clone, Copy, Debug)]
pub struct McSample {
    pub wi: Vec3,
    pub wi_l: Vec3,
    pub radiance: Vec3,
    pub weight: f32,
    pub incident: Incident,
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
/// contributing one to `visit`; returns the rays traced (shadow rays and, with interreflection,
/// the bounce rays and the shadow rays of the vertices they reach). The single sampling code path
/// of the renderer and of the differentiable shader (`montecarlo_op`), so both see the same samples.
#[allow(clippy::too_many_arguments)] // the renderer's state for one surfel, passed as is
pub fn draw_samples(
    s: &Surfel,
    wo: Vec3,
    p: &SurfaceParams,
    light: &LightSampler,
    scene: &TraceScene,
    settings: &McSettings,
    rng: &mut Sampler,
    visit: &mut dyn FnMut(McSample),
) -> RayCount {
    draw_samples_with_bounces(s, wo, p, light, scene, settings, settings.spp.max(1), settings.effects.indirect_bounces, false, rng, visit)
}

#[allow(clippy::too_many_arguments)]
fn draw_samples_with_bounces(
    s: &Surfel,
    wo: Vec3,
    p: &SurfaceParams,
    light: &LightSampler,
    scene: &TraceScene,
    settings: &McSettings,
    spp: u32,
    bounces_left: u32,
    // A detached vertex (on a bounce path): samples of black light contribute exactly nothing.
    detached: bool,
    rng: &mut Sampler,
    visit: &mut dyn FnMut(McSample),
) -> RayCount {
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
    let eps = settings.ray_epsilon;
    let origin = s.position + s.geo_normal * eps;
    let mut rays = RayCount::ZERO;
    // Light arriving from behind the geometric surface is blocked by the surface itself.
    let above = |wi: Vec3| wi.dot(s.geo_normal) > 0.0;
    for k in 0..spp {
        // Light sample, stratified in its first dimension.
        let (r0, r1) = rng.next_2d();
        let ls = light.sample(((k as f32 + r0) / spp as f32, r1));
        let wi_l = frame.to_local(ls.dir);
        if ls.pdf > 0.0 && wi_l.z > 0.0 && above(ls.dir) && !(detached && ls.radiance == Vec3::ZERO) {
            let visible = !settings.effects.shadows || {
                rays.shadow += 1;
                !scene.bvh.any_hit(origin, ls.dir, eps, f32::INFINITY)
            };
            if visible {
                let w = ls.pdf / (ls.pdf + bsdf_pdf(wi_l));
                visit(McSample { wi: ls.dir, wi_l, radiance: ls.radiance, weight: w / ls.pdf, incident: Incident::Light(ls.texel) });
            }
        }
        // BSDF sample.
        let lobe = rng.next_f32();
        let u = rng.next_2d();
        let wi_l = if lobe < ps { brdf::sample_ggx_vndf(wo_l, alpha, u) } else { brdf::sample_cosine(u) };
        if wi_l.z <= 0.0 {
            continue;
        }
        let pdf_b = bsdf_pdf(wi_l);
        let wi = frame.to_world(wi_l);
        if pdf_b <= 0.0 || !above(wi) {
            continue;
        }
        let env = |l: LightLookup| McSample { wi, wi_l, radiance: l.radiance, weight: pdf_b / (pdf_b + l.pdf) / pdf_b, incident: Incident::Light(l.texel) };
        if !settings.effects.shadows {
            visit(env(light.lookup(wi)));
        } else if bounces_left == 0 {
            let l = light.lookup(wi);
            if detached && l.radiance == Vec3::ZERO {
                continue;
            }
            rays.shadow += 1;
            if !scene.bvh.any_hit(origin, wi, eps, f32::INFINITY) {
                visit(env(l));
            }
        } else {
            rays.bounce += 1;
            match scene.bvh.closest_hit(origin, wi, eps, f32::INFINITY) {
                None => visit(env(light.lookup(wi))),
                Some(hit) => {
                    let y = Surfel::from_hit(scene.mesh, &hit, origin, wi).with_material_normal(scene.materials);
                    let (radiance, r) = outgoing_radiance(&y, -wi, light, scene, settings, bounces_left - 1, rng);
                    rays += r;
                    visit(McSample { wi, wi_l, radiance, weight: 1.0 / pdf_b, incident: Incident::Surface });
                }
            }
        }
    }
    rays
}

/// One-sample estimate of the radiance surface point `y` sends along `wo` (direct light plus
/// `bounces_left` further bounces); returns it with the rays traced.
fn outgoing_radiance(y: &Surfel, wo: Vec3, light: &LightSampler, scene: &TraceScene, settings: &McSettings, bounces_left: u32, rng: &mut Sampler) -> (Vec3, RayCount) {
    let p = y.material(scene.materials);
    let (_, wo_l) = local_outgoing(y, wo);
    let mut radiance = Vec3::ZERO;
    let rays = draw_samples_with_bounces(y, wo, &p, light, scene, settings, 1, bounces_left, true, rng, &mut |smp| {
        radiance += sample_radiance(&p, wo_l, &smp, settings.effects.specular);
    });
    (radiance, rays)
}

/// A sample's contribution to outgoing radiance: (kd(1−m)·cos/π + specular lobe) · L · weight.
fn sample_radiance(p: &SurfaceParams, wo_l: Vec3, smp: &McSample, specular: bool) -> Vec3 {
    let cos = brdf::clamp_cos(smp.wi_l.z);
    let mut f = p.kd * (1.0 - p.metallic) * (cos / std::f32::consts::PI);
    if specular {
        f += brdf::eval(p, wo_l, smp.wi_l).specular;
    }
    f * smp.radiance * smp.weight
}

/// Diffuse (demodulated) and specular estimates for one surfel, `spp` samples of each strategy.
/// Returns (diffuse, specular, rays traced).
#[allow(clippy::too_many_arguments)]
pub fn shade_point(s: &Surfel, wo: Vec3, p: &SurfaceParams, light: &LightSampler, scene: &TraceScene, settings: &McSettings, rng: &mut Sampler) -> (Vec3, Vec3, RayCount) {
    let (_, wo_l) = local_outgoing(s, wo);
    let (mut diffuse, mut specular) = (Vec3::ZERO, Vec3::ZERO);
    let rays = draw_samples(s, wo, p, light, scene, settings, rng, &mut |smp| {
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
/// The rays traced are returned and added to the process-wide tally (`ray_count`).
pub fn shade(gbuf: &GBuffer, params: &[Option<SurfaceParams>], light: &LightSampler, scene: &TraceScene, settings: &McSettings, stream_offset: u64) -> McBuffers {
    let shaded: Vec<(Vec3, Vec3, RayCount)> = gbuf
        .surfels
        .par_iter()
        .zip(params.par_iter())
        .enumerate()
        .map(|(i, (s, p))| match (s, p) {
            (Some(s), Some(p)) => {
                let mut rng = Sampler::new(settings.seed, stream_offset + i as u64);
                let wo = (gbuf.origin - s.position).normalize();
                shade_point(s, wo, p, light, scene, settings, &mut rng)
            }
            _ => (Vec3::ZERO, Vec3::ZERO, RayCount::ZERO),
        })
        .collect();
    let rays = shaded.iter().map(|s| s.2).sum();
    ray_count::record(rays);
    McBuffers { diffuse: shaded.iter().map(|s| s.0).collect(), specular: shaded.iter().map(|s| s.1).collect(), rays }
}

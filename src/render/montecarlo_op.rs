//! Differentiable Monte Carlo shading (NVDiffRecMC): the estimator of `montecarlo::shade` as a
//! tape [`Kernel`], with gradients w.r.t. the per-pixel material and the base cube map of the light.
//!
//! Detached sampling, as NVDiffRecMC: [`McShading::prepare`] draws every pixel's samples once per
//! step with the current (detached) material and light, through the renderer's own
//! `montecarlo::draw_samples` (same seeded streams, strategies and balance heuristic), traces the
//! shadow rays, and keeps for each contributing sample its local direction, the light texel it
//! reads and its weight (MIS weight / pdf). Forward and backward then evaluate the same fixed-sample
//! estimator: directions, visibility, pdfs, MIS weights and the lobe choice get no gradient;
//! radiance (a nearest-texel read) is linear in the light; the specular lobe is differentiated by
//! hand (`material::brdf_grad`), its value and roughness derivative evaluated once per sample by
//! `prepare` (`Lobe`) for both passes. At the prepare-time values the forward equals
//! `montecarlo::shade`.
//! With interreflection, a sample that arrives from the object's own surface keeps the radiance
//! estimated at prepare time as a constant: it is detached like visibility (its dependence on the
//! material elsewhere and on the light is not differentiated), while the BRDF it meets at the
//! pixel is differentiated as for light samples.
//!
//! Inputs (all f32 or all f64): `kd` [N, 3], `ks` [N, 3] = (occlusion, roughness, metallic),
//! `light` [6, R, R, 3], and optionally `normal` [N, 3] (see below). Output [N, 6]: demodulated
//! diffuse light Σ L·cos/π·w (multiply by kd(1−m)) and specular radiance, each averaged over
//! `spp`. Misses: zero, no gradient.
//!
//! The optional shading normal (world space, any length: it is normalised here, and flipped to the
//! side of the prepare-time normal, which faces the camera) lets the material pass move vertices
//! (`fit::vertex_refinement`). Each sample's world direction, its radiance, visibility, pdf and MIS
//! weight stay as drawn with the prepare-time normal; only the BRDF·cos term sees the new normal,
//! through n·wi (Lambert), n·wo, n·wi and n·h (GGX D and G, the 1/(4 n·wo) factor); Fresnel's
//! wo·h does not involve n. Its derivatives are `brdf_grad::lobe_grad`'s. Without the input the
//! operator is the three-input one, unchanged; with it, at the prepare-time normal the forward
//! agrees with it to rounding.

use std::sync::Arc;

use candle_core::{Result, Tensor};
use glam::{DVec3, Vec3};
use rayon::prelude::*;

use crate::light::sampler::LightSampler;
use crate::light::CubeMap;
use crate::material::brdf::clamp_cos;
use crate::material::brdf_grad::{clamped_cos_grad, f0, lobe_and_roughness_grad, lobe_grad, schlick_weight};
use crate::math::Frame;
use crate::material::SurfaceParams;
use crate::optim::tape::{apply, map_scatter_chunked, Kernel, Real};
use crate::render::gbuffer::Surfel;
use crate::render::montecarlo::{draw_samples, local_outgoing, Incident, McSettings, TraceScene};
use crate::render::ray_count::{self, RayCount};
use crate::rng::Sampler;

/// Pixels per parallel work item of [`McShading::prepare`]: enough to amortise one sample list's
/// allocation, few enough that two threads stay balanced on a 20k-pixel view.
const PREPARE_CHUNK: usize = 256;

/// Pixels per partial sum of the light's adjoint. Fixed, so that the sum's order (its rounding)
/// is the same on any thread count; at 4096, a 256² view's 33k covered pixels make 9 partial
/// sums, enough to keep two threads busy, each a copy of the light's gradient (590 KB at 6×64²).
const GRAD_CHUNK_PIXELS: usize = 4096;

/// What `prepare` draws for one chunk of pixels: per pixel its local outgoing direction and its
/// range in the chunk's sample list, the list, and the rays traced.
type ChunkSamples = (Vec<Option<[f32; 3]>>, Vec<(u32, u32)>, Vec<Stored>, RayCount);

/// One pixel's fixed data: its surfel, the direction to the camera and its random stream.
#[derive(Clone, Copy, Debug)]
pub struct McPixel {
    pub surfel: Surfel,
    pub wo: Vec3,
    pub stream: u64,
}

impl McPixel {
    pub fn from_surfel(surfel: &Surfel, camera_origin: Vec3, stream: u64) -> McPixel {
        McPixel { surfel: *surfel, wo: (camera_origin - surfel.position).normalize(), stream }
    }
}

/// Where a stored sample's radiance comes from.
#[derive(Clone, Copy, Debug)]
enum Source {
    /// The light's texel (index into the cube map's texels): differentiable.
    Texel(u32),
    /// Interreflected radiance from the object's surface, fixed at prepare time.
    Surface([f32; 3]),
}

/// A stored sample: radiance source, local incident direction, weight (MIS / pdf / spp), and its
/// specular lobe at the prepare-time roughness.
#[derive(Clone, Copy, Debug)]
struct Stored {
    source: Source,
    wi_l: [f32; 3],
    weight: f32,
    lobe: Lobe,
}

/// The specular lobe of a sample in the prepare-time frame (n = +z): the Fresnel-free lobe S and
/// ∂S/∂roughness at the prepare-time roughness, and Schlick's weight (no roughness in it). It is
/// the one part of a sample's evaluation that costs (a GGX D and two Smith Λ in f64), and forward
/// and backward both need it, so `prepare` evaluates it once; a pass whose roughness input differs
/// from the prepare-time value (a finite-difference probe) or that tilts the normal evaluates it
/// afresh with the same function. Zero without the specular lobe.
#[derive(Clone, Copy, Debug, Default)]
struct Lobe {
    value: f64,
    droughness: f64,
    schlick: f64,
}

impl Lobe {
    fn of(wo_l: DVec3, wi_l: [f32; 3], roughness: f64) -> Lobe {
        let wi = DVec3::new(wi_l[0] as f64, wi_l[1] as f64, wi_l[2] as f64);
        let (value, droughness) = lobe_and_roughness_grad(wo_l, wi, roughness);
        Lobe { value, droughness, schlick: schlick_weight(wo_l, wi) }
    }
}

impl Stored {
    /// The radiance this sample reads, in f64.
    fn radiance<T: Real>(&self, light: &[T]) -> [f64; 3] {
        match self.source {
            Source::Texel(t) => rgb(light, t as usize),
            Source::Surface(r) => r.map(|v| v as f64),
        }
    }
}

/// The operator for one step's samples (see the module doc).
#[derive(Clone)]
pub struct McShading {
    /// Per pixel: local outgoing direction (None for a miss) and its sample range.
    wo_l: Arc<[Option<[f32; 3]>]>,
    /// Per pixel: the shading normal the samples' local frame was built on (zero for a miss).
    normals: Arc<[[f32; 3]]>,
    /// Per pixel: its samples' range in its chunk's list (pixel p is in chunk p / PREPARE_CHUNK).
    ranges: Arc<[(u32, u32)]>,
    /// Per pixel: the roughness the stored lobes were evaluated at (NaN for a miss, or when no
    /// lobe was stored).
    roughness: Arc<[f32]>,
    /// One sample list per chunk of pixels, kept as drawn (no concatenated copy).
    chunks: Arc<[Vec<Stored>]>,
    light_res: usize,
    specular: bool,
    /// Rays traced by `prepare` (shadow and bounce; the G-buffer's primary rays are counted where
    /// it is traced). Also added to the process-wide tally.
    pub rays: RayCount,
    /// Stored samples whose radiance comes from the object's surface (interreflection).
    pub surface_samples: usize,
}

impl McShading {
    /// Draws the samples with the current values (`kd`, `ks` per pixel; `light` the base cube map;
    /// `scene`'s materials are the current ones too, read where bounces land).
    pub fn prepare(pixels: &[Option<McPixel>], kd: &[[f32; 3]], ks: &[[f32; 3]], light: &CubeMap, scene: &TraceScene, settings: &McSettings) -> McShading {
        Self::draw(pixels, kd, ks, light, scene, settings, true)
    }

    /// As [`Self::prepare`], for an operator that will always be given the normal input: its
    /// frames are tilted, so no stored lobe would be read, and none is evaluated (every pass
    /// evaluates the lobes itself, whatever inputs it gets).
    pub fn prepare_for_normal_input(pixels: &[Option<McPixel>], kd: &[[f32; 3]], ks: &[[f32; 3]], light: &CubeMap, scene: &TraceScene, settings: &McSettings) -> McShading {
        Self::draw(pixels, kd, ks, light, scene, settings, false)
    }

    /// The samples, with their lobes at the prepare-time roughness when `store_lobes`.
    fn draw(pixels: &[Option<McPixel>], kd: &[[f32; 3]], ks: &[[f32; 3]], light: &CubeMap, scene: &TraceScene, settings: &McSettings, store_lobes: bool) -> McShading {
        let store_lobes = store_lobes && settings.effects.specular;
        let sampler = LightSampler::new(light);
        let inv_n = 1.0 / settings.spp.max(1) as f32;
        // Pixels in chunks, each filling one sample list (no allocation per pixel, and none of
        // the size of all samples: at 16 spp a view's samples take tens of MB).
        let per_chunk: Vec<ChunkSamples> = pixels
            .par_chunks(PREPARE_CHUNK)
            .enumerate()
            .map(|(c, chunk)| {
                let mut wo_l = Vec::with_capacity(chunk.len());
                let mut ranges = Vec::with_capacity(chunk.len());
                let mut stored = Vec::with_capacity(chunk.len() * 2 * settings.spp.max(1) as usize);
                let mut rays = RayCount::ZERO;
                for (j, px) in chunk.iter().enumerate() {
                    let before = stored.len();
                    let wo = px.map(|px| local_outgoing(&px.surfel, px.wo).1.to_array());
                    wo_l.push(wo);
                    if let (Some(px), Some(wo)) = (px, wo) {
                        let i = c * PREPARE_CHUNK + j;
                        let p = SurfaceParams { kd: Vec3::from_array(kd[i]), roughness: ks[i][1], metallic: ks[i][2] };
                        // The lobe as `eval_sample` would evaluate it: wo widened from the kept f32.
                        let wo = DVec3::new(wo[0] as f64, wo[1] as f64, wo[2] as f64);
                        let mut rng = Sampler::new(settings.seed, px.stream);
                        rays += draw_samples(&px.surfel, px.wo, &p, &sampler, scene, settings, &mut rng, &mut |s| {
                            let source = match s.incident {
                                Incident::Light(texel) => Source::Texel(texel),
                                Incident::Surface => Source::Surface(s.radiance.to_array()),
                            };
                            let wi_l = s.wi_l.to_array();
                            let lobe = if store_lobes { Lobe::of(wo, wi_l, p.roughness as f64) } else { Lobe::default() };
                            stored.push(Stored { source, wi_l, weight: s.weight * inv_n, lobe });
                        });
                    }
                    ranges.push((before as u32, stored.len() as u32));
                }
                (wo_l, ranges, stored, rays)
            })
            .collect();
        let mut ranges = Vec::with_capacity(pixels.len());
        let mut chunks = Vec::with_capacity(per_chunk.len());
        let mut rays = RayCount::ZERO;
        let mut wo_l = Vec::with_capacity(pixels.len());
        for (w, r, s, n) in per_chunk {
            wo_l.extend(w);
            ranges.extend(r);
            chunks.push(s);
            rays += n;
        }
        ray_count::record(rays);
        let surface_samples = chunks.iter().flatten().filter(|s| matches!(s.source, Source::Surface(_))).count();
        let normals = pixels.iter().map(|p| p.map_or([0.0; 3], |p| p.surfel.normal.to_array())).collect();
        // NaN matches no input: without stored lobes every pass evaluates its own.
        let roughness = pixels.iter().zip(ks).map(|(p, k)| if p.is_some() && store_lobes { k[1] } else { f32::NAN }).collect();
        McShading { wo_l: wo_l.into(), normals, ranges: ranges.into(), roughness, chunks: chunks.into(), light_res: light.res, specular: settings.effects.specular, rays, surface_samples }
    }

    pub fn len(&self) -> usize {
        self.wo_l.len()
    }

    pub fn is_empty(&self) -> bool {
        self.wo_l.is_empty()
    }

    fn pixel_samples(&self, p: usize) -> &[Stored] {
        let (start, end) = self.ranges[p];
        &self.chunks[p / PREPARE_CHUNK][start as usize..end as usize]
    }

    fn check_shapes(&self, shapes: &[&[usize]]) -> Result<()> {
        let (n, r) = (self.len(), self.light_res);
        let normal_ok = shapes.len() == 3 || (shapes.len() == 4 && shapes[3] == [n, 3]);
        if normal_ok && shapes[0] == [n, 3] && shapes[1] == [n, 3] && shapes[2] == [6, r, r, 3] {
            Ok(())
        } else {
            Err(candle_core::Error::Msg(format!(
                "Monte Carlo shading: expected kd [{n}, 3], ks [{n}, 3], light [6, {r}, {r}, 3] and optionally normal [{n}, 3], got {shapes:?}"
            )))
        }
    }

    /// Pixel `p`'s shading geometry: its local outgoing direction and, with a normal input, the
    /// normal in the prepare-time frame (None for a miss); whether its stored lobes hold for the
    /// input `roughness`.
    fn geometry<T: Real>(&self, p: usize, normal: Option<&[T]>, roughness: f64) -> Option<PixelGeometry> {
        let wo = self.wo_l[p]?;
        let wo = DVec3::new(wo[0] as f64, wo[1] as f64, wo[2] as f64);
        let tilt = normal.map(|n| {
            let frame = Frame::from_normal(glam::Vec3::from_array(self.normals[p]));
            let axes = [frame.s, frame.t, frame.n].map(|a| a.as_dvec3());
            let v = DVec3::new(n[3 * p].to_f64(), n[3 * p + 1].to_f64(), n[3 * p + 2].to_f64());
            let len = v.length();
            let unit = if len > 0.0 { v / len } else { axes[2] };
            // The prepare-time normal faces the camera; the input follows it to that side.
            let sign = if unit.dot(axes[2]) < 0.0 { -1.0 } else { 1.0 };
            let m = sign * DVec3::new(unit.dot(axes[0]), unit.dot(axes[1]), unit.dot(axes[2]));
            Tilt { m, axes, unit, len, sign }
        });
        let stored_lobes = tilt.is_none() && roughness == self.roughness[p] as f64;
        Some(PixelGeometry { wo, tilt, stored_lobes })
    }
}

/// The shading normal given as input, in the prepare-time local frame, with what its adjoint
/// needs to go back to the world input.
struct Tilt {
    /// Unit normal in the local frame (sign-corrected).
    m: DVec3,
    /// The prepare-time frame's axes (s, t, n) in world space.
    axes: [DVec3; 3],
    /// The input normalised, its length, and the flip applied.
    unit: DVec3,
    len: f64,
    sign: f64,
}

impl Tilt {
    /// ∂L/∂(input normal) from ∂L/∂m (local).
    fn to_input(&self, g_m: DVec3) -> DVec3 {
        let g_unit = self.sign * (self.axes[0] * g_m.x + self.axes[1] * g_m.y + self.axes[2] * g_m.z);
        if self.len > 0.0 {
            (g_unit - self.unit * self.unit.dot(g_unit)) / self.len
        } else {
            DVec3::ZERO
        }
    }
}

struct PixelGeometry {
    wo: DVec3,
    /// None: the prepare-time normal, +z (the three-input operator).
    tilt: Option<Tilt>,
    /// The samples' stored lobes are this pass's: no tilt, and the prepare-time roughness.
    stored_lobes: bool,
}

/// Everything about one sample that both passes use.
#[derive(Default)]
struct SampleEval {
    /// cos/π · weight (the diffuse light's factor).
    diffuse: f64,
    /// Fresnel-free lobe S · weight, its ∂/∂roughness, and Schlick's weight.
    lobe: f64,
    dlobe: f64,
    schlick: f64,
    /// With a normal input: ∂diffuse/∂m and ∂lobe/∂m (local, weight included).
    ddiffuse_dm: DVec3,
    dlobe_dm: DVec3,
}

fn eval_sample(px: &PixelGeometry, s: &Stored, roughness: f64, specular: bool) -> SampleEval {
    let wo_l = px.wo;
    let w = s.weight as f64;
    let Some(tilt) = &px.tilt else {
        let diffuse = clamp_cos(s.wi_l[2]) as f64 / std::f64::consts::PI * w;
        if !specular {
            return SampleEval { diffuse, ..SampleEval::default() };
        }
        let l = if px.stored_lobes { s.lobe } else { Lobe::of(wo_l, s.wi_l, roughness) };
        return SampleEval { diffuse, lobe: l.value * w, dlobe: l.droughness * w, schlick: l.schlick, ..SampleEval::default() };
    };
    let wi = DVec3::new(s.wi_l[0] as f64, s.wi_l[1] as f64, s.wi_l[2] as f64);
    let m = tilt.m;
    let (cos_i, dcos_i) = clamped_cos_grad(m.dot(wi));
    let k = w / std::f64::consts::PI;
    let (diffuse, ddiffuse_dm) = (cos_i * k, wi * (dcos_i * k));
    if !specular {
        return SampleEval { diffuse, ddiffuse_dm, ..SampleEval::default() };
    }
    let h = (wo_l + wi).normalize();
    let l = lobe_grad(m.dot(wo_l), m.dot(wi), m.dot(h), roughness);
    let dlobe_dm = (wo_l * l.cos[0] + wi * l.cos[1] + h * l.cos[2]) * w;
    SampleEval { diffuse, lobe: l.value * w, dlobe: l.roughness * w, schlick: schlick_weight(wo_l, wi), ddiffuse_dm, dlobe_dm }
}

fn rgb<T: Real>(x: &[T], i: usize) -> [f64; 3] {
    [x[3 * i].to_f64(), x[3 * i + 1].to_f64(), x[3 * i + 2].to_f64()]
}

impl Kernel for McShading {
    fn name(&self) -> &'static str {
        "montecarlo_shading"
    }

    fn output_shape(&self, shapes: &[&[usize]]) -> Result<Vec<usize>> {
        self.check_shapes(shapes)?;
        Ok(vec![self.len(), 6])
    }

    fn forward<T: Real>(&self, x: &[&[T]], _shapes: &[&[usize]], out: &mut [T]) -> Result<()> {
        let (kd, ks, light, normal) = (x[0], x[1], x[2], x.get(3).copied());
        out.par_chunks_mut(6).enumerate().for_each(|(p, o)| {
            let (k, rough, metal) = (rgb(kd, p), ks[3 * p + 1].to_f64(), ks[3 * p + 2].to_f64());
            let Some(px) = self.geometry(p, normal, rough) else { return };
            let f0 = f0(k, metal);
            let mut acc = [0.0f64; 6];
            for s in self.pixel_samples(p) {
                let e = eval_sample(&px, s, rough, self.specular);
                let l = s.radiance(light);
                for c in 0..3 {
                    acc[c] += e.diffuse * l[c];
                    acc[3 + c] += (f0[c] * (1.0 - e.schlick) + e.schlick) * e.lobe * l[c];
                }
            }
            for (o, a) in o.iter_mut().zip(acc) {
                *o = T::from_f64(a);
            }
        });
        Ok(())
    }

    fn backward<T: Real>(&self, x: &[&[T]], _shapes: &[&[usize]], g_out: &[T], grads: &mut [Option<&mut [T]>]) -> Result<()> {
        let (kd, ks, light, normal) = (x[0], x[1], x[2], x.get(3).copied());
        // (geometry, kd, roughness, metallic, output gradient) of a covered pixel.
        type PixelData = (PixelGeometry, [f64; 3], f64, f64, [f64; 6]);
        let pixel = |p: usize| -> Option<PixelData> {
            let rough = ks[3 * p + 1].to_f64();
            let px = self.geometry(p, normal, rough)?;
            let g: [f64; 6] = std::array::from_fn(|c| g_out[6 * p + c].to_f64());
            Some((px, rgb(kd, p), rough, ks[3 * p + 2].to_f64(), g))
        };
        // Material and light gradients in one sweep over each pixel's samples: each sample's
        // lobe is evaluated once for both. The light's adjoint sums in fixed chunks of pixels
        // (`GRAD_CHUNK_PIXELS`), so its rounding does not depend on the thread count.
        let want_material = self.specular && (grads[0].is_some() || grads[1].is_some());
        let light_len = grads[2].as_ref().map_or(0, |g| g.len());
        if want_material || light_len > 0 {
            let (per_pixel, light_sum) = map_scatter_chunked(self.len(), GRAD_CHUNK_PIXELS, light_len, |p, light_sum| {
                let Some((px, k, rough, metal, g)) = pixel(p) else { return ([0.0; 3], 0.0, 0.0) };
                let f0 = f0(k, metal);
                let (mut gkd, mut gr, mut gm) = ([0.0f64; 3], 0.0, 0.0);
                for s in self.pixel_samples(p) {
                    let e = eval_sample(&px, s, rough, self.specular);
                    if want_material {
                        let l = s.radiance(light);
                        for c in 0..3 {
                            let gs = g[3 + c] * l[c];
                            let fresnel = f0[c] * (1.0 - e.schlick) + e.schlick;
                            gkd[c] += gs * e.lobe * (1.0 - e.schlick) * metal;
                            gm += gs * e.lobe * (1.0 - e.schlick) * (k[c] - 0.04);
                            gr += gs * fresnel * e.dlobe;
                        }
                    }
                    if let (Source::Texel(texel), true) = (s.source, light_len > 0) {
                        for c in 0..3 {
                            let spec = (f0[c] * (1.0 - e.schlick) + e.schlick) * e.lobe;
                            light_sum[3 * texel as usize + c] += g[c] * e.diffuse + g[3 + c] * spec;
                        }
                    }
                }
                (gkd, gr, gm)
            });
            if want_material {
                if let Some(gkd) = grads[0].as_deref_mut() {
                    gkd.par_chunks_mut(3).zip(per_pixel.par_iter()).for_each(|(o, (g, _, _))| {
                        for c in 0..3 {
                            o[c] += T::from_f64(g[c]);
                        }
                    });
                }
                if let Some(gks) = grads[1].as_deref_mut() {
                    gks.par_chunks_mut(3).zip(per_pixel.par_iter()).for_each(|(o, (_, gr, gm))| {
                        o[1] += T::from_f64(*gr);
                        o[2] += T::from_f64(*gm);
                    });
                }
            }
            if let Some(glight) = grads[2].as_deref_mut() {
                glight.par_iter_mut().zip(light_sum.par_iter()).for_each(|(a, b)| *a += T::from_f64(*b));
            }
        }
        if let Some(gn) = grads.get_mut(3).and_then(|g| g.as_deref_mut()) {
            // Normal gradient: each sample's BRDF·cos term through n (directions fixed).
            gn.par_chunks_mut(3).enumerate().for_each(|(p, o)| {
                let Some((px, k, rough, metal, g)) = pixel(p) else { return };
                let Some(tilt) = &px.tilt else { return };
                let f0 = f0(k, metal);
                let mut g_m = DVec3::ZERO;
                for s in self.pixel_samples(p) {
                    let e = eval_sample(&px, s, rough, self.specular);
                    let l = s.radiance(light);
                    let (mut gd, mut gs) = (0.0, 0.0);
                    for c in 0..3 {
                        gd += g[c] * l[c];
                        gs += g[3 + c] * (f0[c] * (1.0 - e.schlick) + e.schlick) * l[c];
                    }
                    g_m += e.ddiffuse_dm * gd + e.dlobe_dm * gs;
                }
                let g_n = tilt.to_input(g_m);
                for c in 0..3 {
                    o[c] += T::from_f64(g_n[c]);
                }
            });
        }
        Ok(())
    }
}

/// Demodulated diffuse light and specular radiance [N, 6] on the tape.
pub fn shade_mc(op: &McShading, kd: &Tensor, ks: &Tensor, light: &Tensor) -> Result<Tensor> {
    apply(op.clone(), &[kd, ks, light])
}

/// As [`shade_mc`] with the shading normal [N, 3] as an input too (see the module doc).
pub fn shade_mc_with_normal(op: &McShading, kd: &Tensor, ks: &Tensor, light: &Tensor, normal: &Tensor) -> Result<Tensor> {
    apply(op.clone(), &[kd, ks, light, normal])
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::bvh::Bvh;
    use crate::geometry::primitives::MeshBuilder;
    use crate::material::{BaseColor, PartMaterial, Scalar};
    use crate::render::effects::Effects;
    use crate::render::gbuffer::GBuffer;
    use crate::scene::Camera;
    use anyhow::Context;
    use candle_core::{Device, Var};
    use glam::Quat;

    /// The lobes `prepare` stores are the ones a pass would evaluate afresh: forward and every
    /// gradient agree bit for bit with the operator drawn without stored lobes
    /// (`prepare_for_normal_input`, the same samples, every lobe evaluated by the pass itself),
    /// in f32 as training runs it.
    #[test]
    fn stored_lobes_give_the_same_bits_as_fresh_ones() -> anyhow::Result<()> {
        let mut b = MeshBuilder::new();
        let part = b.part(PartMaterial { name: "m".into(), base_color: BaseColor::Constant(Vec3::splat(0.5)), roughness: Scalar::Constant(0.5), metallic: Scalar::Constant(0.0) });
        b.ellipsoid(part, Vec3::new(0.0, 0.0, 0.45), Vec3::splat(0.4), Quat::IDENTITY, 12, 6);
        b.cylinder(part, glam::Vec2::ZERO, 1.0, -0.05, 0.0, 16);
        let mesh = b.build();
        let bvh = Bvh::build(&mesh);
        let camera = Camera::look_at(Vec3::new(2.2, 0.6, 1.2), Vec3::new(0.0, 0.0, 0.3), Vec3::Z, 0.8, 12, 12);
        let g = GBuffer::trace(&mesh, &bvh, &camera);
        let pixels: Vec<Option<McPixel>> = g.surfels.iter().enumerate().map(|(i, s)| s.map(|s| McPixel::from_surfel(&s, g.origin, i as u64))).collect();
        let n = pixels.len();
        let kd: Vec<[f32; 3]> = (0..n).map(|i| [0.1 + (i % 7) as f32 / 8.0, 0.4, 0.7]).collect();
        // Roughness from the floor to 1, metallic 0 to 1.
        let ks: Vec<[f32; 3]> = (0..n).map(|i| [0.0, (i % 11) as f32 / 10.0, (i % 3) as f32 / 2.0]).collect();
        let light = CubeMap::from_fn(3, |d| Vec3::new(1.0 + d.x, 0.5 + d.z.max(0.0) * 4.0, 0.8));
        let settings = McSettings { spp: 3, seed: 9, effects: Effects { shadows: true, specular: true, indirect_bounces: 1 }, ray_epsilon: 1e-4 };
        let scene = TraceScene { mesh: &mesh, bvh: &bvh, materials: &mesh };
        let op = McShading::prepare(&pixels, &kd, &ks, &light, &scene, &settings);
        let fresh = McShading::prepare_for_normal_input(&pixels, &kd, &ks, &light, &scene, &settings);
        let dev = Device::Cpu;
        // A weighted sum, so that every output channel carries its own gradient.
        let weights: Vec<f32> = (0..6 * n).map(|i| 0.5 + (i % 13) as f32 / 13.0).collect();
        let weights = Tensor::from_vec(weights, (n, 6), &dev)?;
        let run = |op: &McShading| -> anyhow::Result<Vec<Vec<f32>>> {
            let kd = Var::from_vec(kd.iter().flatten().copied().collect(), (n, 3), &dev)?;
            let ks = Var::from_vec(ks.iter().flatten().copied().collect(), (n, 3), &dev)?;
            let l = Var::from_vec(light.data.iter().flat_map(|v| v.to_array()).collect(), (6, 3, 3, 3), &dev)?;
            let out = shade_mc(op, kd.as_tensor(), ks.as_tensor(), l.as_tensor())?;
            let grads = (&out * &weights)?.sum_all()?.backward()?;
            let mut all = vec![out.flatten_all()?.to_vec1::<f32>()?];
            for v in [&kd, &ks, &l] {
                all.push(grads.get(v.as_tensor()).context("a gradient for every input")?.flatten_all()?.to_vec1::<f32>()?);
            }
            Ok(all)
        };
        assert!(op.chunks.iter().flatten().any(|s| s.lobe.value > 0.0), "no specular sample stored a lobe");
        assert!(fresh.chunks.iter().flatten().all(|s| s.lobe.value == 0.0), "a lobe stored for a normal input");
        let (a, b) = (run(&op)?, run(&fresh)?);
        for (k, (x, y)) in a.iter().zip(&b).enumerate() {
            assert!(x.iter().zip(y).all(|(x, y)| x.to_bits() == y.to_bits()), "output {k} differs between stored and fresh lobes");
        }
        Ok(())
    }
}

//! Split-sum shading (NVDiffRec): diffuse = kd(1−m)·E(n), specular = L_pref(r, roughness)·(F0·A + B)
//! with the BRDF table's (A, B) at (n·v, roughness). No shadows: the prefiltered light is unoccluded.

use glam::Vec3;
use rayon::prelude::*;

use crate::light::brdf_lut::BrdfLut;
use crate::light::prefilter::SplitSumLight;
use crate::material::brdf;
use crate::material::SurfaceParams;
use crate::render::effects::Effects;
use crate::render::gbuffer::GBuffer;

/// Diffuse and specular radiance of one surface point.
pub fn shade_point(normal: Vec3, wo: Vec3, p: &SurfaceParams, light: &SplitSumLight, lut: &BrdfLut, effects: Effects) -> (Vec3, Vec3) {
    let diffuse = p.kd * (1.0 - p.metallic) * light.diffuse(normal);
    if !effects.specular {
        return (diffuse, Vec3::ZERO);
    }
    let nov = brdf::clamp_cos(normal.dot(wo));
    let refl = (2.0 * normal.dot(wo) * normal - wo).normalize_or(normal);
    let f0 = Vec3::splat(0.04).lerp(p.kd, p.metallic);
    let (a, b) = lut.lookup(nov, p.roughness);
    let specular = light.specular(refl, p.roughness) * (f0 * a + Vec3::splat(b));
    (diffuse, specular)
}

/// Shade every covered pixel of a G-buffer; `params` holds each pixel's material (None = miss).
/// Returns linear radiance per pixel (zero where nothing was hit).
pub fn shade(gbuf: &GBuffer, params: &[Option<SurfaceParams>], light: &SplitSumLight, lut: &BrdfLut, effects: Effects) -> Vec<Vec3> {
    gbuf.surfels
        .par_iter()
        .zip(params.par_iter())
        .map(|(s, p)| match (s, p) {
            (Some(s), Some(p)) => {
                let wo = (gbuf.origin - s.position).normalize();
                let (d, sp) = shade_point(s.normal, wo, p, light, lut, effects);
                d + sp
            }
            _ => Vec3::ZERO,
        })
        .collect()
}

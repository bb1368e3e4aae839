//! The BRDF of docs/model.md, *BRDF* (NVDiffRecMC's): Lambert diffuse + GGX specular with α = roughness²,
//! height-correlated Smith masking and Schlick Fresnel; plus the sampling routines the Monte Carlo
//! renderer and the split-sum BRDF table use (cosine hemisphere, GGX visible normals).
//!
//! Everything works in a local shading frame ([`crate::math::Frame`]) where the normal is +z, so
//! `v.z` is the cosine with the normal. Every function is a pure function of its inputs so that a
//! backward pass can be written beside it.
//!
//! Deviation from NVDiffRec, on purpose: NVDiffRec clamps n·h in D to [1e-4, 1−1e-4] as well. At the
//! roughness floor (α = 0.0064) that cuts D's peak to 3 % of its true value and its integral
//! ∫D(h)(n·h)dω to 0.31 (by quadrature: the cap n·h > 1 − 1e-4 holds 0.83 of the lobe and keeps 3 %
//! of its height), so here n·h is only clamped to [0, 1] and D stays normalised. The cosines with wo
//! and wi (Λ, the 1/(4 n·wo) factor, Lambert's n·wi) and the Fresnel cosine are clamped to
//! [1e-4, 1−1e-4].

use std::f32::consts::{FRAC_1_PI, PI};

use glam::Vec3;

use crate::material::SurfaceParams;

/// Lowest roughness (NVDiffRec's `min_roughness`); α = roughness² ≥ 0.0064. The BRDF, the
/// prefiltered light and the BRDF table clamp at it, and the fit clamps the roughness texture there.
pub const MIN_ROUGHNESS: f32 = 0.08;
/// Cosines with wo and wi are clamped to [COS_EPS, 1 − COS_EPS].
pub const COS_EPS: f32 = 1e-4;
/// Reflectance of a dielectric at normal incidence (Principled "specular 0.5").
pub const DIELECTRIC_F0: f32 = 0.04;

/// The two lobes of the BRDF times the cosine n·wi, in linear RGB.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct BrdfValue {
    pub diffuse: Vec3,
    pub specular: Vec3,
}

impl BrdfValue {
    pub fn total(&self) -> Vec3 {
        self.diffuse + self.specular
    }
}

/// Roughness clamped to [MIN_ROUGHNESS, 1] (NaN maps to the floor).
pub fn clamp_roughness(roughness: f32) -> f32 {
    if roughness.is_nan() {
        MIN_ROUGHNESS
    } else {
        roughness.clamp(MIN_ROUGHNESS, 1.0)
    }
}

/// GGX α = roughness² after clamping the roughness.
pub fn alpha_from_roughness(roughness: f32) -> f32 {
    let r = clamp_roughness(roughness);
    r * r
}

/// A cosine clamped to [COS_EPS, 1 − COS_EPS].
pub fn clamp_cos(c: f32) -> f32 {
    c.clamp(COS_EPS, 1.0 - COS_EPS)
}

/// GGX normal distribution D(h) = α²/(π((n·h)²(α²−1)+1)²); `cos_h` = n·h, clamped to [0, 1] only.
pub fn ndf_ggx(cos_h: f32, alpha: f32) -> f32 {
    let c = cos_h.clamp(0.0, 1.0);
    let a2 = alpha * alpha;
    // (n·h)²(α²−1)+1 written as α²c² + (1−c²) to keep precision when c → 1 and α is tiny.
    let d = a2 * c * c + (1.0 - c) * (1.0 + c);
    a2 / (PI * d * d)
}

/// Smith Λ(c) = ½(√(1+α²(1−c²)/c²) − 1) with the cosine clamped.
pub fn lambda_ggx(cos: f32, alpha: f32) -> f32 {
    let c = clamp_cos(cos);
    let tan2 = (1.0 - c) * (1.0 + c) / (c * c);
    0.5 * ((1.0 + alpha * alpha * tan2).sqrt() - 1.0)
}

/// Smith masking of one direction, G1 = 1/(1+Λ).
pub fn smith_g1(cos: f32, alpha: f32) -> f32 {
    1.0 / (1.0 + lambda_ggx(cos, alpha))
}

/// Height-correlated masking-shadowing G = 1/(1+Λ(n·wo)+Λ(n·wi)).
pub fn smith_g_correlated(cos_o: f32, cos_i: f32, alpha: f32) -> f32 {
    1.0 / (1.0 + lambda_ggx(cos_o, alpha) + lambda_ggx(cos_i, alpha))
}

/// Schlick's weight (1 − cosθ)⁵ with the cosine clamped.
pub fn schlick_weight(cos: f32) -> f32 {
    let m = 1.0 - clamp_cos(cos);
    let m2 = m * m;
    m2 * m2 * m
}

/// Schlick Fresnel F = F0 + (1 − F0)(1 − cosθ)⁵.
pub fn fresnel_schlick(f0: Vec3, cos: f32) -> Vec3 {
    let w = schlick_weight(cos);
    f0 + (Vec3::ONE - f0) * w
}

/// Specular colour at normal incidence, F0 = 0.04(1−m) + kd·m.
pub fn specular_f0(kd: Vec3, metallic: f32) -> Vec3 {
    Vec3::splat(DIELECTRIC_F0 * (1.0 - metallic)) + kd * metallic
}

/// Diffuse albedo kd(1−m).
pub fn diffuse_albedo(kd: Vec3, metallic: f32) -> Vec3 {
    kd * (1.0 - metallic)
}

/// Reflect `wo` about the unit vector `h`: 2(wo·h)h − wo.
pub fn reflect(wo: Vec3, h: Vec3) -> Vec3 {
    2.0 * wo.dot(h) * h - wo
}

/// Both directions strictly above the surface (otherwise the BRDF is zero).
fn front_facing(wo: Vec3, wi: Vec3) -> bool {
    wo.z > 0.0 && wi.z > 0.0
}

/// D·G/(4 n·wo): the specular lobe times n·wi without the Fresnel factor (what the split-sum
/// table integrates). Zero unless both directions are above the surface.
pub fn specular_without_fresnel(wo: Vec3, wi: Vec3, alpha: f32) -> f32 {
    if !front_facing(wo, wi) {
        return 0.0;
    }
    let h = (wo + wi).normalize();
    ndf_ggx(h.z, alpha) * smith_g_correlated(wo.z, wi.z, alpha) / (4.0 * clamp_cos(wo.z))
}

/// The BRDF times n·wi for unit local directions (n = +z). Zero when wo or wi is at or below the
/// surface; the renderer flips normals toward the viewer before calling this.
pub fn eval(params: &SurfaceParams, wo: Vec3, wi: Vec3) -> BrdfValue {
    if !front_facing(wo, wi) {
        return BrdfValue::default();
    }
    let alpha = alpha_from_roughness(params.roughness);
    let h = (wo + wi).normalize();
    let f = fresnel_schlick(specular_f0(params.kd, params.metallic), wo.dot(h));
    BrdfValue {
        diffuse: diffuse_albedo(params.kd, params.metallic) * (clamp_cos(wi.z) * FRAC_1_PI),
        specular: f * specular_without_fresnel(wo, wi, alpha),
    }
}

/// Cosine-weighted hemisphere direction (pdf = cosθ/π), from two uniform numbers in [0, 1).
pub fn sample_cosine(u: (f32, f32)) -> Vec3 {
    let r = u.0.clamp(0.0, 1.0).sqrt();
    let phi = 2.0 * PI * u.1;
    let z = (1.0 - r * r).max(0.0).sqrt();
    Vec3::new(r * phi.cos(), r * phi.sin(), z)
}

/// Solid-angle density of [`sample_cosine`].
pub fn pdf_cosine(wi: Vec3) -> f32 {
    wi.z.max(0.0) * FRAC_1_PI
}

/// Heitz 2018, "Sampling the GGX distribution of visible normals": a microfacet normal h drawn
/// with density D_wo(h) = G1(wo)·max(0, wo·h)·D(h)/(n·wo), then wo reflected about it. The result
/// may point below the surface (the BRDF is zero there); [`pdf_ggx_vndf`] is its density over the
/// whole sphere. `wo` must be above the surface.
pub fn sample_ggx_vndf(wo: Vec3, alpha: f32, u: (f32, f32)) -> Vec3 {
    let h = sample_visible_normal(wo, alpha, u);
    reflect(wo, h)
}

/// The visible microfacet normal of [`sample_ggx_vndf`].
pub fn sample_visible_normal(wo: Vec3, alpha: f32, u: (f32, f32)) -> Vec3 {
    // Stretch the view direction to the hemisphere configuration (α = 1).
    let vh = Vec3::new(alpha * wo.x, alpha * wo.y, wo.z.max(0.0)).normalize_or(Vec3::Z);
    let lensq = vh.x * vh.x + vh.y * vh.y;
    let t1 = if lensq > 1e-12 { Vec3::new(-vh.y, vh.x, 0.0) / lensq.sqrt() } else { Vec3::X };
    let t2 = vh.cross(t1);
    // Uniform disk point, warped toward the visible half of the projected hemisphere.
    let r = u.0.clamp(0.0, 1.0).sqrt();
    let phi = 2.0 * PI * u.1;
    let p1 = r * phi.cos();
    let mut p2 = r * phi.sin();
    let s = 0.5 * (1.0 + vh.z);
    p2 = (1.0 - s) * (1.0 - p1 * p1).max(0.0).sqrt() + s * p2;
    let nh = p1 * t1 + p2 * t2 + (1.0 - p1 * p1 - p2 * p2).max(0.0).sqrt() * vh;
    // Unstretch back to the α-ellipsoid.
    Vec3::new(alpha * nh.x, alpha * nh.y, nh.z.max(0.0)).normalize_or(Vec3::Z)
}

/// Solid-angle density of [`sample_ggx_vndf`] at `wi`: D_wo(h)/(4 wo·h) = G1(wo)·D(h)/(4 n·wo).
pub fn pdf_ggx_vndf(wo: Vec3, wi: Vec3, alpha: f32) -> f32 {
    if wo.z <= 0.0 {
        return 0.0;
    }
    let sum = wo + wi;
    let len = sum.length();
    if len < 1e-6 {
        return 0.0;
    }
    let h = sum / len;
    if h.z <= 0.0 {
        return 0.0;
    }
    smith_g1(wo.z, alpha) * ndf_ggx(h.z, alpha) / (4.0 * clamp_cos(wo.z))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn params(kd: Vec3, roughness: f32, metallic: f32) -> SurfaceParams {
        SurfaceParams { kd, roughness, metallic }
    }

    /// ∫ over the hemisphere of f(θ, φ) sinθ, midpoint rule with θ spacing refined near 0.
    fn hemisphere_integral(n_theta: usize, n_phi: usize, f: impl Fn(Vec3) -> f64) -> f64 {
        // θ = (π/2)·s² puts many nodes near the pole where GGX lobes are sharp; dθ = π s ds.
        let mut sum = 0.0f64;
        for a in 0..n_theta {
            let s = (a as f64 + 0.5) / n_theta as f64;
            let theta = std::f64::consts::FRAC_PI_2 * s * s;
            let dtheta = std::f64::consts::PI * s / n_theta as f64;
            for b in 0..n_phi {
                let phi = 2.0 * std::f64::consts::PI * (b as f64 + 0.5) / n_phi as f64;
                let d = Vec3::new((theta.sin() * phi.cos()) as f32, (theta.sin() * phi.sin()) as f32, theta.cos() as f32);
                sum += f(d) * theta.sin() * dtheta * 2.0 * std::f64::consts::PI / n_phi as f64;
            }
        }
        sum
    }

    #[test]
    fn lambert_white_furnace_gives_the_radiance_back() {
        // kd = 1, m = 0 under constant L: ∫ diffuse dω = L for any normal and view. The integral
        // runs over the whole world sphere; each direction goes to the shading frame of the normal.
        let p = params(Vec3::ONE, 0.5, 0.0);
        let radiance = 2.5f64;
        let normals = [Vec3::Z, -Vec3::Z, Vec3::X, Vec3::new(0.3, -0.5, 0.81).normalize(), Vec3::new(-0.7, 0.7, -0.1).normalize()];
        let (n_theta, n_phi) = (800usize, 400usize);
        for n in normals {
            let frame = crate::math::Frame::from_normal(n);
            let wo = frame.to_local((n + 0.4 * frame.s).normalize());
            let mut out = 0.0f64;
            for a in 0..n_theta {
                let theta = std::f64::consts::PI * (a as f64 + 0.5) / n_theta as f64;
                for b in 0..n_phi {
                    let phi = 2.0 * std::f64::consts::PI * (b as f64 + 0.5) / n_phi as f64;
                    let wi = Vec3::new((theta.sin() * phi.cos()) as f32, (theta.sin() * phi.sin()) as f32, theta.cos() as f32);
                    let dw = theta.sin() * (std::f64::consts::PI / n_theta as f64) * (2.0 * std::f64::consts::PI / n_phi as f64);
                    out += radiance * eval(&p, wo, frame.to_local(wi)).diffuse.x as f64 * dw;
                }
            }
            assert!((out - radiance).abs() < 2e-3 * radiance, "normal {n}: {out}");
        }
    }

    #[test]
    fn ggx_ndf_is_normalised_in_projected_area() {
        for roughness in [0.08f32, 0.2, 0.5, 1.0] {
            let alpha = alpha_from_roughness(roughness);
            let integral = hemisphere_integral(4000, 8, |h| (ndf_ggx(h.z, alpha) * h.z) as f64);
            assert!((integral - 1.0).abs() < 2e-3, "roughness {roughness}: {integral}");
        }
    }

    #[test]
    fn nvdiffrec_style_clamp_of_n_dot_h_would_lose_most_of_d() {
        // Documents the deviation above: with n·h clamped to 1−1e-4, D at the floor integrates to ≪ 1.
        let alpha = alpha_from_roughness(MIN_ROUGHNESS);
        let clamped = hemisphere_integral(4000, 8, |h| (ndf_ggx(clamp_cos(h.z), alpha) * h.z) as f64);
        assert!(clamped < 0.5, "{clamped}");
    }

    #[test]
    fn vndf_normals_are_distributed_as_visible_normals() {
        // ∫ D_wo(h) dω_h = 1: G1 is exactly the normaliser of the visible-normal distribution.
        for (wo, roughness) in [(Vec3::Z, 0.3f32), (Vec3::new(0.8, 0.0, 0.6), 0.5), (Vec3::new(0.0, -0.95, 0.312).normalize(), 1.0)] {
            let alpha = alpha_from_roughness(roughness);
            let g1 = smith_g1(wo.z, alpha);
            let integral = hemisphere_integral(3000, 256, |h| (g1 * wo.dot(h).max(0.0) * ndf_ggx(h.z, alpha) / wo.z) as f64);
            assert!((integral - 1.0).abs() < 3e-3, "wo {wo} r {roughness}: {integral}");
        }
    }

    #[test]
    fn reciprocity_and_zero_below_surface() {
        let p = params(Vec3::new(0.8, 0.4, 0.1), 0.3, 0.2);
        let a = Vec3::new(0.3, 0.2, 0.9).normalize();
        let b = Vec3::new(-0.5, 0.1, 0.6).normalize();
        // f is reciprocal; eval includes the cosine n·wi, so divide it out. Fresnel uses wo·h = wi·h.
        let fab = eval(&p, a, b).specular / b.z;
        let fba = eval(&p, b, a).specular / a.z;
        assert!((fab - fba).abs().max_element() < 1e-5 * fab.max_element());
        assert_eq!(eval(&p, a, Vec3::new(0.3, 0.0, -0.1)), BrdfValue::default());
        assert_eq!(eval(&p, Vec3::new(0.3, 0.0, -0.1), a), BrdfValue::default());
    }
}

//! Derivatives of the specular lobe of `brdf::eval` for the differentiable Monte Carlo shader:
//! specular·cos = F(F0, wo·h) · S(α), S = D·G/(4 n·wo) (`brdf::specular_without_fresnel`),
//! α = roughness², F = F0(1 − w) + w with Schlick's w = (1 − wo·h)⁵, F0 = 0.04(1 − m) + kd·m.
//!
//! By hand, in f64:
//!   ∂D/∂α = D · (2/α) · (1 − 2α²c²/d),   d = α²c² + 1 − c², c = n·h;
//!   ∂Λ/∂α = ½ · α·tan²θ / √(1 + α² tan²θ),   ∂G/∂α = −G² (∂Λo/∂α + ∂Λi/∂α);
//!   ∂S/∂ρ = (∂D/∂α · G + D · ∂G/∂α) / (4 n·wo) · 2ρ   (0 below the 0.08 floor and from 1 up;
//!   at the floor itself the slope from above, the side the optimiser's clamp leaves open);
//!   ∂spec_c/∂kd_c = S (1 − w) m,   ∂spec_c/∂m = S (1 − w)(kd_c − 0.04).
//!
//! And w.r.t. the shading normal n, through the three cosines co = n·wo, ci = n·wi, ch = n·h with
//! the directions (and so h and w = (1 − wo·h)⁵) held fixed:
//!   ∂D/∂ch = −4 D ch (α² − 1) / d   (0 where ch is clamped to [0, 1]);
//!   ∂Λ/∂c = −α² / (2 c³ √(1 + α² tan²θ))   (0 where c is clamped to [ε, 1 − ε]);
//!   ∂S/∂co = (D ∂G/∂co − S · 4) / (4 co),  ∂S/∂ci = D ∂G/∂ci / (4 co),  ∂S/∂ch = ∂D/∂ch G / (4 co),
//!   with ∂G/∂c = −G² ∂Λ/∂c; so ∂S/∂n = ∂S/∂co wo + ∂S/∂ci wi + ∂S/∂ch h. Lambert's clamped ci
//!   gives ∂/∂n = wi inside the clamp, 0 outside.

use glam::DVec3;

use super::brdf::{COS_EPS, DIELECTRIC_F0, MIN_ROUGHNESS};

fn clamp_cos(c: f64) -> f64 {
    c.clamp(COS_EPS as f64, 1.0 - COS_EPS as f64)
}

/// Smith Λ, ∂Λ/∂α and ∂Λ/∂cos for a cosine (clamped as `brdf::lambda_ggx`).
fn lambda_and_grads(cos: f64, alpha: f64) -> (f64, f64, f64) {
    let c = clamp_cos(cos);
    let tan2 = (1.0 - c) * (1.0 + c) / (c * c);
    let root = (1.0 + alpha * alpha * tan2).sqrt();
    let dcos = if c == cos { -alpha * alpha / (2.0 * c * c * c * root) } else { 0.0 };
    (0.5 * (root - 1.0), 0.5 * alpha * tan2 / root, dcos)
}

/// The Fresnel-free lobe S and its derivatives, from the cosines of a configuration.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct LobeGrad {
    pub value: f64,
    /// ∂S/∂roughness.
    pub roughness: f64,
    /// ∂S/∂(n·wo), ∂S/∂(n·wi), ∂S/∂(n·h) with the directions fixed.
    pub cos: [f64; 3],
}

/// The lobe at cosines `cos_o` = n·wo, `cos_i` = n·wi, `cos_h` = n·h (h the half vector of the
/// unit directions) and roughness ρ, with its derivatives. Zero (with zero derivatives) unless
/// both cosines are positive.
pub fn lobe_grad(cos_o: f64, cos_i: f64, cos_h: f64, roughness: f64) -> LobeGrad {
    if cos_o <= 0.0 || cos_i <= 0.0 {
        return LobeGrad::default();
    }
    let floor = MIN_ROUGHNESS as f64;
    let (r, dr) = if roughness.is_nan() || roughness < floor {
        (floor, 0.0)
    } else if roughness >= 1.0 {
        (1.0, 0.0)
    } else {
        (roughness, 1.0)
    };
    let alpha = r * r;
    let c = cos_h.clamp(0.0, 1.0);
    let a2 = alpha * alpha;
    let d = a2 * c * c + (1.0 - c) * (1.0 + c);
    let ndf = a2 / (std::f64::consts::PI * d * d);
    let dndf = ndf * (2.0 / alpha) * (1.0 - 2.0 * a2 * c * c / d);
    let (lo, dlo, dlo_c) = lambda_and_grads(cos_o, alpha);
    let (li, dli, dli_c) = lambda_and_grads(cos_i, alpha);
    let g = 1.0 / (1.0 + lo + li);
    let dg = -g * g * (dlo + dli);
    let clamped_o = clamp_cos(cos_o);
    let denom = 4.0 * clamped_o;
    let s = ndf * g / denom;
    let ds_dalpha = (dndf * g + ndf * dg) / denom;
    let dndf_c = if c == cos_h { -4.0 * ndf * c * (a2 - 1.0) / d } else { 0.0 };
    let ddenom_o = if clamped_o == cos_o { 4.0 } else { 0.0 };
    let cos = [(ndf * -g * g * dlo_c - s * ddenom_o) / denom, ndf * -g * g * dli_c / denom, dndf_c * g / denom];
    LobeGrad { value: s, roughness: ds_dalpha * 2.0 * r * dr, cos }
}

/// The Fresnel-free lobe S at roughness ρ and ∂S/∂ρ, for local unit directions (n = +z).
/// Zero (with zero derivative) unless both directions are above the surface.
pub fn lobe_and_roughness_grad(wo: DVec3, wi: DVec3, roughness: f64) -> (f64, f64) {
    let h = (wo + wi).normalize();
    let l = lobe_grad(wo.z, wi.z, h.z, roughness);
    (l.value, l.roughness)
}

/// Lambert's clamped cosine max(ε, min(c, 1 − ε)) as the f64 renderer clamps it, and its
/// derivative in c.
pub fn clamped_cos_grad(c: f64) -> (f64, f64) {
    let v = clamp_cos(c);
    (v, if v == c { 1.0 } else { 0.0 })
}

/// Schlick's weight w = (1 − wo·h)⁵ for the half vector of `wo`, `wi`.
pub fn schlick_weight(wo: DVec3, wi: DVec3) -> f64 {
    let h = (wo + wi).normalize();
    let m = 1.0 - clamp_cos(wo.dot(h));
    m.powi(5)
}

/// F0 per channel.
pub fn f0(kd: [f64; 3], metallic: f64) -> [f64; 3] {
    kd.map(|k| DIELECTRIC_F0 as f64 * (1.0 - metallic) + k * metallic)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::material::brdf::{self, specular_without_fresnel};
    use crate::material::SurfaceParams;
    use glam::Vec3;

    fn dir(theta: f64, phi: f64) -> DVec3 {
        DVec3::new(theta.sin() * phi.cos(), theta.sin() * phi.sin(), theta.cos())
    }

    #[test]
    fn lobe_matches_the_renderers_brdf() {
        for (wo, wi, r) in [(dir(0.3, 0.0), dir(0.5, 3.0), 0.4), (dir(1.2, 1.0), dir(0.2, 2.0), 0.9), (dir(0.1, 0.0), dir(0.12, 3.1), 0.08)] {
            let (s, _) = lobe_and_roughness_grad(wo, wi, r);
            let want = specular_without_fresnel(wo.as_vec3(), wi.as_vec3(), brdf::alpha_from_roughness(r as f32)) as f64;
            // f32 (renderer) against f64 (here): at the roughness floor the lobe peaks near 150 and
            // f32 rounding of n·h moves it by a few 1e-3 relative.
            assert!((s - want).abs() <= 5e-3 * want.max(1e-6), "{s} vs {want}");
            // And the full specular term: F · S with F from F0.
            let p = SurfaceParams { kd: Vec3::new(0.8, 0.3, 0.1), roughness: r as f32, metallic: 0.4 };
            let w = schlick_weight(wo, wi);
            let f = f0([0.8, 0.3, 0.1], 0.4);
            let spec = brdf::eval(&p, wo.as_vec3(), wi.as_vec3()).specular;
            for c in 0..3 {
                let ours = (f[c] * (1.0 - w) + w) * s;
                assert!((ours - spec[c] as f64).abs() <= 5e-3 * ours.max(1e-6), "channel {c}: {ours} vs {}", spec[c]);
            }
        }
    }

    #[test]
    fn normal_gradient_matches_central_differences() {
        // Random normals around +z (some near grazing for wo or wi), fixed directions: S as a
        // function of the normal through its three cosines against central differences.
        let mut rng = crate::rng::Sampler::from_seed(9);
        let lobe_at = |n: DVec3, wo: DVec3, wi: DVec3, r: f64| {
            let h = (wo + wi).normalize();
            lobe_grad(n.dot(wo), n.dot(wi), n.dot(h), r)
        };
        let mut checked = 0;
        for k in 0..400 {
            let mut u = || rng.next_f32() as f64;
            let (wo, wi) = (dir(1.5 * u(), 6.3 * u()), dir(1.5 * u(), 6.3 * u()));
            let tilt = if k % 4 == 0 { 0.6 } else { 0.15 };
            let n = dir(tilt * u(), 6.3 * u());
            let r = 0.1 + 0.85 * u();
            let l = lobe_at(n, wo, wi, r);
            let h = (wo + wi).normalize();
            let g = l.cos[0] * wo + l.cos[1] * wi + l.cos[2] * h;
            let e = 1e-7;
            let fd = DVec3::new(
                (lobe_at(n + DVec3::X * e, wo, wi, r).value - lobe_at(n - DVec3::X * e, wo, wi, r).value) / (2.0 * e),
                (lobe_at(n + DVec3::Y * e, wo, wi, r).value - lobe_at(n - DVec3::Y * e, wo, wi, r).value) / (2.0 * e),
                (lobe_at(n + DVec3::Z * e, wo, wi, r).value - lobe_at(n - DVec3::Z * e, wo, wi, r).value) / (2.0 * e),
            );
            // Skip configurations within FD reach of a clamp's kink.
            let cs = [n.dot(wo), n.dot(wi), n.dot(h)];
            if cs.iter().any(|c| c.abs() < 1e-5 || (c - 1.0).abs() < 1e-5) {
                continue;
            }
            checked += (l.value > 0.0) as usize;
            assert!((g - fd).length() <= 1e-4 * fd.length().max(1e-3 * l.value.max(1e-6)), "case {k}: n {n} wo {wo} wi {wi} r {r}: {g} vs {fd} (S {})", l.value);
        }
        assert!(checked > 100, "{checked}");
        // Grazing: n·wo = 0.02, n·wi = 0.03.
        let (wo, wi) = (dir(1.55, 0.0), dir(1.54, 2.0));
        let n = DVec3::Z;
        let l = lobe_at(n, wo, wi, 0.3);
        let h = (wo + wi).normalize();
        let g = l.cos[0] * wo + l.cos[1] * wi + l.cos[2] * h;
        let e = 1e-8;
        let fd_x = (lobe_at(n + DVec3::X * e, wo, wi, 0.3).value - lobe_at(n - DVec3::X * e, wo, wi, 0.3).value) / (2.0 * e);
        assert!((g.x - fd_x).abs() <= 1e-4 * fd_x.abs(), "{} vs {fd_x}", g.x);
        // The cosine clamps: no gradient outside, unit slope inside.
        assert_eq!(clamped_cos_grad(0.5), (0.5, 1.0));
        assert_eq!(clamped_cos_grad(-0.2).1, 0.0);
    }

    #[test]
    fn roughness_gradient_matches_central_differences() {
        let cases = [
            (dir(0.3, 0.0), dir(0.5, 3.0), 0.4),
            (dir(1.5, 0.2), dir(1.45, 3.0), 0.6), // grazing
            (dir(0.2, 0.0), dir(0.25, 3.1), 0.0801), // just above the floor
            (dir(0.7, 0.0), dir(0.1, 1.0), 0.97),
        ];
        for (wo, wi, r) in cases {
            let (_, g) = lobe_and_roughness_grad(wo, wi, r);
            let e = 1e-6;
            let fd = (lobe_and_roughness_grad(wo, wi, r + e).0 - lobe_and_roughness_grad(wo, wi, r - e).0) / (2.0 * e);
            assert!((g - fd).abs() <= 1e-2 * fd.abs().max(1e-6), "r {r}: {g} vs {fd}");
        }
        // Clamped below the floor and above 1: no gradient.
        assert_eq!(lobe_and_roughness_grad(dir(0.3, 0.0), dir(0.5, 3.0), 0.05).1, 0.0);
        assert_eq!(lobe_and_roughness_grad(dir(0.3, 0.0), dir(0.5, 3.0), 1.2).1, 0.0);
    }
}

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

use glam::DVec3;

use super::brdf::{COS_EPS, DIELECTRIC_F0, MIN_ROUGHNESS};

fn clamp_cos(c: f64) -> f64 {
    c.clamp(COS_EPS as f64, 1.0 - COS_EPS as f64)
}

/// Smith Λ and ∂Λ/∂α for a cosine (clamped as `brdf::lambda_ggx`).
fn lambda_and_grad(cos: f64, alpha: f64) -> (f64, f64) {
    let c = clamp_cos(cos);
    let tan2 = (1.0 - c) * (1.0 + c) / (c * c);
    let root = (1.0 + alpha * alpha * tan2).sqrt();
    (0.5 * (root - 1.0), 0.5 * alpha * tan2 / root)
}

/// The Fresnel-free lobe S at roughness ρ and ∂S/∂ρ, for local unit directions (n = +z).
/// Zero (with zero derivative) unless both directions are above the surface.
pub fn lobe_and_roughness_grad(wo: DVec3, wi: DVec3, roughness: f64) -> (f64, f64) {
    if wo.z <= 0.0 || wi.z <= 0.0 {
        return (0.0, 0.0);
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
    let h = (wo + wi).normalize();
    let c = h.z.clamp(0.0, 1.0);
    let a2 = alpha * alpha;
    let d = a2 * c * c + (1.0 - c) * (1.0 + c);
    let ndf = a2 / (std::f64::consts::PI * d * d);
    let dndf = ndf * (2.0 / alpha) * (1.0 - 2.0 * a2 * c * c / d);
    let (lo, dlo) = lambda_and_grad(wo.z, alpha);
    let (li, dli) = lambda_and_grad(wi.z, alpha);
    let g = 1.0 / (1.0 + lo + li);
    let dg = -g * g * (dlo + dli);
    let denom = 4.0 * clamp_cos(wo.z);
    let s = ndf * g / denom;
    let ds_dalpha = (dndf * g + ndf * dg) / denom;
    (s, ds_dalpha * 2.0 * r * dr)
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

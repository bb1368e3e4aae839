//! The BRDF's sampling routines: every pdf integrates to 1 over the sphere, and histograms of the
//! samples match the pdf (chi-square). Plus the hard cases that must stay finite.

use std::f64::consts::PI;

use glam::Vec3;
use reconstruct::material::brdf::{self, alpha_from_roughness};
use reconstruct::material::SurfaceParams;
use reconstruct::math::Frame;
use reconstruct::rng::Sampler;

/// Spherical coordinates around `axis`, with θ = w·q/(1−q) so that bins in q resolve a lobe of
/// angular width ≈ w near the axis and still reach θ = π.
struct LobeGrid {
    frame: Frame,
    w: f64,
    q_max: f64,
}

impl LobeGrid {
    fn new(axis: Vec3, w: f64) -> Self {
        LobeGrid { frame: Frame::from_normal(axis.normalize()), w, q_max: PI / (PI + w) }
    }

    /// Direction and solid-angle measure dω/(dq dφ) at (q, φ).
    fn point(&self, q: f64, phi: f64) -> (Vec3, f64) {
        let theta = self.w * q / (1.0 - q);
        let dtheta_dq = self.w / ((1.0 - q) * (1.0 - q));
        let local = Vec3::new((theta.sin() * phi.cos()) as f32, (theta.sin() * phi.sin()) as f32, theta.cos() as f32);
        (self.frame.to_world(local), theta.sin() * dtheta_dq)
    }

    /// (q, φ) of a direction.
    fn coords(&self, d: Vec3) -> (f64, f64) {
        // f64 and atan2: acos of an f32 cosine cannot resolve the 1e-4 rad lobes at grazing angles.
        let dot = |a: Vec3| a.x as f64 * d.x as f64 + a.y as f64 * d.y as f64 + a.z as f64 * d.z as f64;
        let (x, y, z) = (dot(self.frame.s), dot(self.frame.t), dot(self.frame.n));
        let theta = (x * x + y * y).sqrt().atan2(z);
        let phi = y.atan2(x).rem_euclid(2.0 * PI);
        (theta / (theta + self.w), phi)
    }

    /// ∫ pdf over the bin [q0, q1]×[φ0, φ1] by an n×n midpoint rule.
    fn integrate(&self, q0: f64, q1: f64, p0: f64, p1: f64, n: usize, pdf: &impl Fn(Vec3) -> f64) -> f64 {
        let mut sum = 0.0;
        for a in 0..n {
            let q = q0 + (q1 - q0) * (a as f64 + 0.5) / n as f64;
            for b in 0..n {
                let phi = p0 + (p1 - p0) * (b as f64 + 0.5) / n as f64;
                let (d, jac) = self.point(q, phi);
                sum += pdf(d) * jac;
            }
        }
        sum * (q1 - q0) * (p1 - p0) / (n * n) as f64
    }
}

/// Integral of `pdf` over the sphere and chi-square of `samples` drawn from it, on a
/// `nq`×`nphi` lobe grid. Returns (integral, chi², degrees of freedom).
/// `singular`: a direction where the pdf is discontinuous (VNDF: wi = −wo, where h = (wo+wi)/|wo+wi|
/// turns around); bins next to it get a much finer quadrature.
fn check_sampler(grid: &LobeGrid, pdf: impl Fn(Vec3) -> f64, mut sample: impl FnMut() -> Vec3, n_samples: usize, singular: Option<Vec3>) -> (f64, f64, usize) {
    let (nq, nphi) = (24usize, 16usize);
    let bin_of = |d: Vec3| {
        let (q, phi) = grid.coords(d);
        let a = ((q / grid.q_max * nq as f64) as usize).min(nq - 1);
        let b = ((phi / (2.0 * PI) * nphi as f64) as usize).min(nphi - 1);
        (a, b)
    };
    let special = singular.map(bin_of);
    let mut expected = vec![0.0f64; nq * nphi];
    for a in 0..nq {
        for b in 0..nphi {
            let (q0, q1) = (grid.q_max * a as f64 / nq as f64, grid.q_max * (a + 1) as f64 / nq as f64);
            let (p0, p1) = (2.0 * PI * b as f64 / nphi as f64, 2.0 * PI * (b + 1) as f64 / nphi as f64);
            let near = special.is_some_and(|(sa, sb)| sa.abs_diff(a) <= 1 && (sb.abs_diff(b) <= 1 || sb.abs_diff(b) == nphi - 1));
            expected[a * nphi + b] = grid.integrate(q0, q1, p0, p1, if near { 600 } else { 24 }, &pdf);
        }
    }
    let integral: f64 = expected.iter().sum();
    let mut counts = vec![0usize; nq * nphi];
    for _ in 0..n_samples {
        let d = sample();
        assert!(d.is_finite() && (d.length() - 1.0).abs() < 1e-3, "bad sample {d}");
        let (a, b) = bin_of(d);
        counts[a * nphi + b] += 1;
    }
    // Pool bins with small expectations into one, as usual for chi-square.
    let (mut chi2, mut dof, mut pooled_e, mut pooled_c) = (0.0, 0usize, 0.0, 0.0);
    for (bin, (e, c)) in expected.iter().zip(&counts).enumerate() {
        let e = e * n_samples as f64;
        let _ = bin;
        if e < 20.0 {
            pooled_e += e;
            pooled_c += *c as f64;
        } else {
            chi2 += (*c as f64 - e).powi(2) / e;
            dof += 1;
            if std::env::var("CHI_DEBUG").is_ok() && (*c as f64 - e).powi(2) / e > 9.0 {
                println!("  bin q{} phi{}: expected {e:.1} got {c}", bin / nphi, bin % nphi);
            }
        }
    }
    if pooled_e > 20.0 {
        chi2 += (pooled_c - pooled_e).powi(2) / pooled_e;
        dof += 1;
    } else {
        assert!(pooled_c <= 20.0 + 5.0 * pooled_e.sqrt(), "{pooled_c} samples where the pdf puts {pooled_e}");
    }
    (integral, chi2, dof.saturating_sub(1))
}

fn assert_good(name: &str, (integral, chi2, dof): (f64, f64, usize)) {
    // χ² critical value far in the tail (≈ dof + 5σ): the streams are seeded, so this never flickers.
    let limit = dof as f64 + 5.0 * (2.0 * dof as f64).sqrt();
    println!("{name}: ∫pdf = {integral:.5}, χ² = {chi2:.1} (dof {dof}, limit {limit:.1})");
    assert!((integral - 1.0).abs() < 5e-3, "{name}: pdf integrates to {integral}");
    assert!(chi2 < limit, "{name}: χ² {chi2} over {dof} dof");
}

#[test]
fn cosine_sampling_matches_its_pdf() {
    let grid = LobeGrid::new(Vec3::Z, 1.0);
    let mut rng = Sampler::new(11, 0);
    let result = check_sampler(&grid, |d| brdf::pdf_cosine(d) as f64, || brdf::sample_cosine(rng.next_2d()), 200_000, None);
    assert_good("cosine", result);
}

#[test]
fn ggx_vndf_sampling_matches_its_pdf() {
    let wos = [Vec3::Z, Vec3::new(0.6, 0.0, 0.8), Vec3::new(-0.3, 0.9, 0.3).normalize(), Vec3::new(0.998, 0.0, 0.05).normalize()];
    for (k, wo) in wos.iter().enumerate() {
        for roughness in [0.08f32, 0.2, 0.5, 1.0] {
            let alpha = alpha_from_roughness(roughness);
            // Centre the grid on the mirror direction, scaled to the lobe width.
            let mirror = brdf::reflect(*wo, Vec3::Z);
            let grid = LobeGrid::new(mirror, (4.0 * alpha as f64).max(0.02));
            let mut rng = Sampler::new(12, (k * 10) as u64 + (roughness * 100.0) as u64);
            let result = check_sampler(
                &grid,
                |d| brdf::pdf_ggx_vndf(*wo, d, alpha) as f64,
                || brdf::sample_ggx_vndf(*wo, alpha, rng.next_2d()),
                200_000,
                Some(-*wo),
            );
            assert_good(&format!("vndf wo={wo} r={roughness}"), result);
        }
    }
}

#[test]
fn vndf_samples_estimate_the_specular_albedo_like_cosine_samples() {
    // Two estimators of ∫ f·cos dω (with F) must agree: the pdfs are right up to normalisation.
    let p = SurfaceParams { kd: Vec3::new(0.5, 0.5, 0.5), roughness: 0.4, metallic: 0.0 };
    let wo = Vec3::new(0.5, 0.1, 0.7).normalize();
    let alpha = alpha_from_roughness(p.roughness);
    let n = 400_000;
    let mut rng = Sampler::new(13, 0);
    let (mut a, mut b) = (0.0f64, 0.0f64);
    for _ in 0..n {
        let wi = brdf::sample_ggx_vndf(wo, alpha, rng.next_2d());
        let pdf = brdf::pdf_ggx_vndf(wo, wi, alpha);
        if pdf > 0.0 {
            a += (brdf::eval(&p, wo, wi).specular.x / pdf) as f64;
        }
        let wi = brdf::sample_cosine(rng.next_2d());
        let pdf = brdf::pdf_cosine(wi);
        if pdf > 0.0 {
            b += (brdf::eval(&p, wo, wi).specular.x / pdf) as f64;
        }
    }
    let (a, b) = (a / n as f64, b / n as f64);
    assert!((a - b).abs() < 0.01 * a, "VNDF estimate {a} vs cosine estimate {b}");
}

#[test]
fn hard_cases_stay_finite() {
    let kd = Vec3::new(0.9, 0.5, 0.1);
    let dirs = [
        Vec3::Z,
        Vec3::new(1.0, 0.0, 1e-7).normalize(),
        Vec3::new(0.0, 1.0, 1e-5).normalize(),
        Vec3::new(0.3, 0.4, 0.866).normalize(),
        Vec3::new(0.5, 0.0, -0.1).normalize(),
        -Vec3::Z,
    ];
    for roughness in [0.0f32, 0.08, 0.3, 1.0, 1.7, f32::NAN] {
        for metallic in [0.0f32, 1.0] {
            let p = SurfaceParams { kd, roughness, metallic };
            let alpha = alpha_from_roughness(roughness);
            assert!((0.0064 - 1e-9..=1.0).contains(&alpha));
            for wo in dirs {
                for wi in dirs {
                    let v = brdf::eval(&p, wo, wi);
                    assert!(v.diffuse.is_finite() && v.specular.is_finite(), "r={roughness} wo={wo} wi={wi}: {v:?}");
                    assert!(v.diffuse.min_element() >= 0.0 && v.specular.min_element() >= 0.0);
                    if wi.z <= 0.0 || wo.z <= 0.0 {
                        assert_eq!(v.total(), Vec3::ZERO);
                    }
                    let pdf = brdf::pdf_ggx_vndf(wo, wi, alpha);
                    assert!(pdf.is_finite() && pdf >= 0.0);
                }
                if wo.z > 0.0 {
                    for u in [(0.0, 0.0), (0.999_999, 0.999_999), (0.5, 0.25), (1.0, 1.0)] {
                        let wi = brdf::sample_ggx_vndf(wo, alpha, u);
                        assert!(wi.is_finite() && (wi.length() - 1.0).abs() < 1e-3, "wo={wo} u={u:?}: {wi}");
                        assert!(brdf::pdf_ggx_vndf(wo, wi, alpha).is_finite());
                    }
                }
            }
        }
    }
    // Roughness above 1 is clamped to 1.
    let wo = Vec3::new(0.3, 0.0, 0.9).normalize();
    let wi = Vec3::new(-0.2, 0.1, 0.9).normalize();
    let at = |r: f32| brdf::eval(&SurfaceParams { kd, roughness: r, metallic: 0.2 }, wo, wi);
    assert_eq!(at(1.7), at(1.0));
    assert_eq!(at(0.01), at(0.08));
}

//! The split-sum BRDF table (Karis 2013), computed by the project for the BRDF of docs/model.md, *BRDF*.
//!
//! With Schlick's F = F0·(1 − Fc) + Fc, Fc = (1 − v·h)⁵, the directional albedo of the specular
//! lobe is F0·A + B with
//!   A(n·v, r) = ∫ D·G/(4 n·v) · (1 − Fc) dω_l,   B(n·v, r) = ∫ D·G/(4 n·v) · Fc dω_l
//! (D·G/(4 n·v) is the specular lobe with its cosine, [`brdf::specular_without_fresnel`]), using the
//! height-correlated G. Entries are estimated with GGX visible-normal sampling over a Hammersley
//! point set, which makes the per-sample weight G/G1 — nearly constant, so few samples suffice.

use glam::Vec3;
use rayon::prelude::*;

use crate::material::brdf::{self, alpha_from_roughness};

/// Side of the table every renderer and the fit use (tests build smaller ones to stay quick): 32
/// entries along n·v and along roughness, looked up bilinearly; A and B vary smoothly along both.
pub const SIZE: usize = 32;
/// Visible-normal samples per entry of that table: twice the 256 with which
/// `tests/light_splitsum.rs` (`brdf_lut_matches_brute_force_quadrature`) already finds every
/// checked entry within 5·10⁻³ of a brute-force quadrature. The table is computed once per
/// prepared light or fit, not per step.
pub const SAMPLES: u32 = 512;

/// A size×size table: column j ↔ n·v = (j+½)/size, row i ↔ roughness = (i+½)/size.
#[derive(Clone, Debug)]
pub struct BrdfLut {
    pub size: usize,
    /// (A, B) per entry, row-major (roughness rows, n·v columns).
    pub data: Vec<(f32, f32)>,
}

/// Point k of an n-point Hammersley set in [0, 1)².
fn hammersley(k: u32, n: u32) -> (f32, f32) {
    ((k as f32 + 0.5) / n as f32, (k.reverse_bits() as f64 / 4_294_967_296.0) as f32)
}

/// (A, B) for one (n·v, roughness) by `samples` visible-normal samples.
pub fn integrate(nov: f32, roughness: f32, samples: u32) -> (f32, f32) {
    let alpha = alpha_from_roughness(roughness);
    let nov = nov.clamp(brdf::COS_EPS, 1.0);
    let wo = Vec3::new((1.0 - nov * nov).max(0.0).sqrt(), 0.0, nov);
    let (mut a, mut b) = (0.0f64, 0.0f64);
    for k in 0..samples {
        let wi = brdf::sample_ggx_vndf(wo, alpha, hammersley(k, samples));
        let f = brdf::specular_without_fresnel(wo, wi, alpha);
        if f <= 0.0 {
            continue;
        }
        let pdf = brdf::pdf_ggx_vndf(wo, wi, alpha);
        if pdf <= 0.0 {
            continue;
        }
        let w = (f / pdf) as f64;
        let fc = brdf::schlick_weight(wo.dot((wo + wi).normalize())) as f64;
        a += w * (1.0 - fc);
        b += w * fc;
    }
    ((a / samples as f64) as f32, (b / samples as f64) as f32)
}

impl BrdfLut {
    /// The table of [`SIZE`]² entries with [`SAMPLES`] samples each, the one the renderers use.
    pub fn standard() -> Self {
        Self::compute(SIZE, SAMPLES)
    }

    /// Fill a size×size table with `samples` samples per entry (rayon over entries).
    pub fn compute(size: usize, samples: u32) -> Self {
        assert!(size >= 2 && samples >= 1);
        let data = (0..size * size)
            .into_par_iter()
            .map(|k| {
                let (i, j) = (k / size, k % size);
                integrate((j as f32 + 0.5) / size as f32, (i as f32 + 0.5) / size as f32, samples)
            })
            .collect();
        BrdfLut { size, data }
    }

    /// Bilinear (A, B), clamped to the table's edge texel centres.
    pub fn lookup(&self, nov: f32, roughness: f32) -> (f32, f32) {
        let n = self.size;
        let coord = |v: f32| {
            let v = if v.is_nan() { 0.0 } else { v };
            (v.clamp(0.0, 1.0) * n as f32 - 0.5).clamp(0.0, (n - 1) as f32)
        };
        let (x, y) = (coord(nov), coord(roughness));
        let (j0, i0) = (x.floor() as usize, y.floor() as usize);
        let (j1, i1) = ((j0 + 1).min(n - 1), (i0 + 1).min(n - 1));
        let (tx, ty) = (x - j0 as f32, y - i0 as f32);
        let at = |i: usize, j: usize| self.data[i * n + j];
        let lerp = |p: (f32, f32), q: (f32, f32), t: f32| (p.0 + (q.0 - p.0) * t, p.1 + (q.1 - p.1) * t);
        lerp(lerp(at(i0, j0), at(i0, j1), tx), lerp(at(i1, j0), at(i1, j1), tx), ty)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hammersley_is_stratified() {
        let n = 64;
        let mut xs: Vec<f32> = (0..n).map(|k| hammersley(k, n).1).collect();
        xs.sort_by(f32::total_cmp);
        for (k, x) in xs.iter().enumerate() {
            assert!((*x - k as f32 / n as f32).abs() < 1.0 / n as f32);
        }
    }

    #[test]
    fn lookup_reproduces_entries_and_interpolates() {
        let lut = BrdfLut::compute(8, 64);
        let e = lut.data[3 * 8 + 5];
        let l = lut.lookup(5.5 / 8.0, 3.5 / 8.0);
        assert!((l.0 - e.0).abs() < 1e-6 && (l.1 - e.1).abs() < 1e-6);
        let m = lut.lookup(6.0 / 8.0, 3.5 / 8.0);
        let e2 = lut.data[3 * 8 + 6];
        assert!((m.0 - 0.5 * (e.0 + e2.0)).abs() < 1e-6);
    }

    #[test]
    fn energy_is_bounded_and_grazing_fresnel_grows() {
        let lut = BrdfLut::compute(16, 256);
        for &(a, b) in &lut.data {
            assert!(a.is_finite() && b.is_finite() && a >= 0.0 && b >= 0.0 && a + b <= 1.0 + 1e-3, "{a} {b}");
        }
        // At low roughness the lobe is almost all reflected: A + B ≈ 1 away from grazing.
        let (a, b) = integrate(0.9, 0.1, 1024);
        assert!((a + b - 1.0).abs() < 0.02, "{a} {b}");
        // The Fresnel part B grows toward grazing.
        assert!(integrate(0.1, 0.3, 512).1 > integrate(0.9, 0.3, 512).1);
    }
}

//! Importance sampling of a cube-map light by texel (NVDiffRecMC): texel k is chosen with
//! probability P_k ∝ max(r, g, b)·Ω_k, then a point uniform on the texel's square of the cube face.
//!
//! The light seen by the Monte Carlo renderer is the **nearest-texel** (piecewise-constant) radiance,
//! [`LightSampler::radiance`]: it is what `sample` returns and what BSDF-sampled directions must use
//! in MIS, so that sample, pdf and radiance describe one function. Within a texel the density is
//! P_k·|d|³/A_k (uniform on the face plane, A_k = (2/res)² its area there, |d|³ = dA/dω), so the pdf
//! integrates to exactly 1 and [`LightSampler::pdf`] is the density of [`LightSampler::sample`].
//!
//! A map with no positive finite texel falls back to P_k ∝ Ω_k (uniform over the sphere).
//! Non-finite or negative texel values get zero probability (and zero radiance).

use glam::Vec3;

use crate::light::cubemap::{dir_to_face, face_dir, face_solid_angles, CubeMap};

/// One light sample: direction (world, unit), its radiance, and its solid-angle pdf.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LightSample {
    pub dir: Vec3,
    pub radiance: Vec3,
    pub pdf: f32,
}

#[derive(Clone, Debug)]
pub struct LightSampler {
    map: CubeMap,
    /// Inclusive prefix sums of the texel weights (f64: a 1e5 sun must not swamp the rest).
    cdf: Vec<f64>,
    /// P_k of every texel.
    prob: Vec<f32>,
}

/// The radiance the sampler uses for a texel value: non-finite or negative channels become 0.
fn sanitize(v: Vec3) -> Vec3 {
    let c = |x: f32| if x.is_finite() && x > 0.0 { x } else { 0.0 };
    Vec3::new(c(v.x), c(v.y), c(v.z))
}

impl LightSampler {
    pub fn new(map: &CubeMap) -> Self {
        let res = map.res;
        let area = face_solid_angles(res);
        let radiance: Vec<Vec3> = map.data.iter().map(|v| sanitize(*v)).collect();
        let mut weights: Vec<f64> = radiance.iter().enumerate().map(|(k, v)| v.max_element() as f64 * area[k % (res * res)] as f64).collect();
        let mut total: f64 = weights.iter().sum();
        if !(total > 0.0 && total.is_finite()) {
            weights = (0..6 * res * res).map(|k| area[k % (res * res)] as f64).collect();
            total = weights.iter().sum();
        }
        let mut acc = 0.0f64;
        let cdf = weights
            .iter()
            .map(|w| {
                acc += w;
                acc
            })
            .collect();
        let prob = weights.iter().map(|w| (w / total) as f32).collect();
        LightSampler { map: CubeMap { res, data: radiance }, cdf, prob }
    }

    /// Probability of choosing texel `k`.
    pub fn texel_probability(&self, k: usize) -> f32 {
        self.prob[k]
    }

    /// Nearest-texel radiance along `dir` (the function this sampler represents).
    pub fn radiance(&self, dir: Vec3) -> Vec3 {
        self.map.lookup_nearest(dir)
    }

    /// Density P_k·|d|³/A_k at texel k and face coordinates (s, t).
    fn density(&self, k: usize, s: f32, t: f32) -> f32 {
        let plane_area = (2.0 / self.map.res as f32).powi(2);
        let q = 1.0 + s * s + t * t;
        let jacobian = q * q.sqrt(); // q^1.5 without powf (a hot path)
        self.prob[k] * jacobian / plane_area
    }

    /// Solid-angle density of [`Self::sample`] at `dir`.
    pub fn pdf(&self, dir: Vec3) -> f32 {
        let (_, s, t) = dir_to_face(dir);
        self.density(self.map.nearest_texel(dir), s, t)
    }

    /// Draw a direction from two uniform numbers in [0, 1).
    pub fn sample(&self, u: (f32, f32)) -> LightSample {
        let total = *self.cdf.last().unwrap_or(&1.0);
        let x = (u.0.clamp(0.0, 1.0) as f64) * total;
        // First texel whose cumulative weight exceeds x (zero-weight texels are never chosen).
        let mut k = self.cdf.partition_point(|&c| c <= x).min(self.cdf.len() - 1);
        while k > 0 && self.prob[k] == 0.0 {
            k -= 1; // x landed on total through rounding: step back to a texel with weight
        }
        let prev = if k == 0 { 0.0 } else { self.cdf[k - 1] };
        let width = self.cdf[k] - prev;
        // Reuse the leftover of u.0 inside the chosen texel's interval as the column offset.
        let fu = if width > 0.0 { (((x - prev) / width) as f32).clamp(0.0, 0.999_999) } else { 0.5 };
        let fv = u.1.clamp(0.0, 0.999_999);
        let res = self.map.res;
        let (face, i, j) = (k / (res * res), (k / res) % res, k % res);
        let s = 2.0 * (j as f32 + fu) / res as f32 - 1.0;
        let t = 2.0 * (i as f32 + fv) / res as f32 - 1.0;
        LightSample { dir: face_dir(face, s, t).normalize(), radiance: self.map.data[k], pdf: self.density(k, s, t) }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn samples_land_in_the_chosen_texel_with_consistent_pdf() {
        let mut map = CubeMap::constant(4, Vec3::splat(0.1));
        map.data[37] = Vec3::new(5.0, 1.0, 0.0);
        let sampler = LightSampler::new(&map);
        let mut hits = 0;
        for a in 0..64 {
            for b in 0..64 {
                let s = sampler.sample(((a as f32 + 0.5) / 64.0, (b as f32 + 0.5) / 64.0));
                assert!((s.pdf - sampler.pdf(s.dir)).abs() <= 1e-4 * s.pdf, "{} vs {}", s.pdf, sampler.pdf(s.dir));
                assert_eq!(s.radiance, sampler.radiance(s.dir));
                hits += (map.nearest_texel(s.dir) == 37) as usize;
            }
        }
        // P(37) = 5Ω/(5Ω + 95·0.1·Ω̄): about a third of the samples.
        let expect = sampler.texel_probability(37) * 4096.0;
        assert!((hits as f32 - expect).abs() < 0.02 * 4096.0, "{hits} vs {expect}");
    }

    #[test]
    fn black_and_invalid_maps_fall_back_to_uniform() {
        let mut map = CubeMap::constant(3, Vec3::ZERO);
        map.data[4] = Vec3::new(f32::NAN, -1.0, f32::INFINITY);
        let sampler = LightSampler::new(&map);
        let s = sampler.sample((0.3, 0.7));
        assert!(s.pdf.is_finite() && s.pdf > 0.0 && s.radiance == Vec3::ZERO);
        // Uniform over the sphere: pdf ≈ 1/4π on average.
        let mean: f32 = (0..100).map(|k| sampler.pdf(sampler.sample((k as f32 / 100.0, 0.5)).dir)).sum::<f32>() / 100.0;
        assert!((mean - 1.0 / (4.0 * std::f32::consts::PI)).abs() < 0.05 / (4.0 * std::f32::consts::PI) * 4.0);
    }
}

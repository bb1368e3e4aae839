//! Importance sampling of a cube-map light by texel (NVDiffRecMC): texel k is chosen with
//! probability P_k ∝ max(r, g, b)·Ω_k, then a point uniform on the texel's square of the cube face.
//! The texel is drawn in O(1) from an alias table (Walker; built by Vose's method): one uniform
//! slot of n, then the slot's own texel or its alias by a threshold. The light is rebuilt every
//! training step and sampled a few times per pixel, so the table replaces a binary search over
//! the n = 6·res² prefix sums (17 dependent, cache-missing steps at res 64) by two reads.
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

use crate::light::cubemap::{dir_to_face, face_dir, face_solid_angles, nearest_index, CubeMap};

/// One light sample: direction (world, unit), the texel it lies in (index into the cube map's
/// texels), its radiance, and its solid-angle pdf.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LightSample {
    pub dir: Vec3,
    pub texel: u32,
    pub radiance: Vec3,
    pub pdf: f32,
}

/// What the light is along a direction: its texel, radiance and the density of [`LightSampler::sample`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LightLookup {
    pub texel: u32,
    pub radiance: Vec3,
    pub pdf: f32,
}

/// A texel's sanitised radiance and probability side by side (one cache line serves both reads).
#[derive(Clone, Copy, Debug)]
struct Texel {
    radiance: Vec3,
    prob: f32,
}

/// One slot of the alias table: keep the slot's texel when the uniform offset is below
/// `threshold`, else take `alias`. The slot's own texel is copied in: the slot is a random read
/// (a cache miss on a large map), and with its texel beside it, keeping it costs no second miss;
/// aliases point at heavy texels, few and mostly cached.
#[derive(Clone, Copy, Debug)]
struct AliasSlot {
    threshold: f32,
    alias: u32,
    own: Texel,
}

#[derive(Clone, Debug)]
pub struct LightSampler {
    res: usize,
    texels: Vec<Texel>,
    slots: Vec<AliasSlot>,
    /// (2/res)²: a texel's area on the face plane at distance 1.
    plane_area: f32,
}

/// Vose's alias table for weights `w` (non-negative, positive sum). Slot i keeps texel i with
/// probability `threshold` and otherwise gives `alias`; P(k) = (threshold_k + Σ_{alias_i = k}
/// (1 − threshold_i)) / n = w_k / Σw up to rounding. Zero-weight entries have threshold 0 and an
/// alias of positive weight, so they are never drawn. f64 so that a 1e5 sun does not swamp the rest.
fn alias_table(w: &[f64], texels: &[Texel]) -> Vec<AliasSlot> {
    let n = w.len();
    let total: f64 = w.iter().sum();
    let mut scaled: Vec<f64> = w.iter().map(|x| x * n as f64 / total).collect();
    let mut slots: Vec<AliasSlot> = (0..n).map(|i| AliasSlot { threshold: 1.0, alias: i as u32, own: texels[i] }).collect();
    let (mut small, mut large): (Vec<usize>, Vec<usize>) = (0..n).partition(|&i| scaled[i] < 1.0);
    while let (Some(&s), Some(&l)) = (small.last(), large.last()) {
        small.pop();
        (slots[s].threshold, slots[s].alias) = (scaled[s] as f32, l as u32);
        scaled[l] -= 1.0 - scaled[s];
        if scaled[l] < 1.0 {
            large.pop();
            small.push(l);
        }
    }
    // What is left holds ≈ 1 each up to rounding: keep it whole (threshold 1, alias itself).
    let heaviest = (0..n).max_by(|&a, &b| w[a].total_cmp(&w[b])).unwrap_or(0) as u32;
    for (i, slot) in slots.iter_mut().enumerate() {
        if w[i] <= 0.0 {
            slot.threshold = 0.0; // never keep a zero-weight texel, whatever rounding left
            if w[slot.alias as usize] <= 0.0 {
                slot.alias = heaviest;
            }
        }
    }
    slots
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
        let texels: Vec<Texel> = radiance.iter().zip(&weights).map(|(&radiance, w)| Texel { radiance, prob: (w / total) as f32 }).collect();
        LightSampler { res, slots: alias_table(&weights, &texels), texels, plane_area: (2.0 / res as f32).powi(2) }
    }

    /// Probability of choosing texel `k`.
    pub fn texel_probability(&self, k: usize) -> f32 {
        self.texels[k].prob
    }

    /// Nearest-texel radiance along `dir` (the function this sampler represents).
    pub fn radiance(&self, dir: Vec3) -> Vec3 {
        self.lookup(dir).radiance
    }

    /// Density P_k·|d|³/A_k at texel k and face coordinates (s, t).
    fn density(&self, k: usize, s: f32, t: f32) -> f32 {
        Self::density_of(&self.texels[k], s, t, self.plane_area)
    }

    fn density_of(texel: &Texel, s: f32, t: f32, plane_area: f32) -> f32 {
        let q = 1.0 + s * s + t * t;
        let jacobian = q * q.sqrt(); // q^1.5 without powf (a hot path)
        texel.prob * jacobian / plane_area
    }

    /// Solid-angle density of [`Self::sample`] at `dir`.
    pub fn pdf(&self, dir: Vec3) -> f32 {
        self.lookup(dir).pdf
    }

    /// Texel, radiance and pdf along `dir`, from one face projection (what a BSDF-sampled
    /// direction needs for its radiance and its MIS weight).
    pub fn lookup(&self, dir: Vec3) -> LightLookup {
        let (face, s, t) = dir_to_face(dir);
        let k = nearest_index(self.res, face, s, t);
        LightLookup { texel: k as u32, radiance: self.texels[k].radiance, pdf: self.density(k, s, t) }
    }

    /// Draw a direction from two uniform numbers in [0, 1).
    pub fn sample(&self, u: (f32, f32)) -> LightSample {
        let n = self.slots.len();
        // u.0 picks a slot and, with what is left of it, the slot's texel or its alias, then the
        // column offset inside the texel (f64: u.0·n is exact, so the leftover keeps every bit).
        let x = u.0.clamp(0.0, 1.0) as f64 * n as f64;
        let slot = (x as usize).min(n - 1);
        let r = (x - slot as f64).min(1.0);
        let AliasSlot { threshold, alias, own } = self.slots[slot];
        let q = threshold as f64;
        let (k, texel, fu) = if r < q { (slot, own, r / q) } else { (alias as usize, self.texels[alias as usize], (r - q) / (1.0 - q)) };
        let fu = if fu.is_finite() { (fu as f32).clamp(0.0, 0.999_999) } else { 0.5 };
        let fv = u.1.clamp(0.0, 0.999_999);
        let res = self.res;
        let (face, i, j) = (k / (res * res), (k / res) % res, k % res);
        let s = 2.0 * (j as f32 + fu) / res as f32 - 1.0;
        let t = 2.0 * (i as f32 + fv) / res as f32 - 1.0;
        LightSample { dir: face_dir(face, s, t).normalize(), texel: k as u32, radiance: texel.radiance, pdf: Self::density_of(&texel, s, t, self.plane_area) }
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
        // A grid fine in u.0 (256 points per alias slot, so each slot's threshold is resolved to
        // 1/256) with u.1 spread over its range.
        let n = 96 * 256;
        let mut hits = 0;
        for a in 0..n {
            let b = (a * 37) % 64;
            let s = sampler.sample(((a as f32 + 0.5) / n as f32, (b as f32 + 0.5) / 64.0));
            assert!((s.pdf - sampler.pdf(s.dir)).abs() <= 1e-4 * s.pdf, "{} vs {}", s.pdf, sampler.pdf(s.dir));
            assert_eq!(s.radiance, sampler.radiance(s.dir));
            assert_eq!(s.texel as usize, map.nearest_texel(s.dir));
            hits += (map.nearest_texel(s.dir) == 37) as usize;
        }
        // P(37) = 5Ω/(5Ω + 95·0.1·Ω̄): about a third of the samples.
        let expect = sampler.texel_probability(37) * n as f32;
        assert!((hits as f32 - expect).abs() < 0.02 * n as f32, "{hits} vs {expect}");
    }

    /// The probabilities the alias table realises, summed slot by slot.
    fn realised(sampler: &LightSampler) -> Vec<f64> {
        let n = sampler.slots.len() as f64;
        let mut p = vec![0.0f64; sampler.slots.len()];
        for (i, s) in sampler.slots.iter().enumerate() {
            p[i] += s.threshold as f64 / n;
            p[s.alias as usize] += (1.0 - s.threshold as f64) / n;
        }
        p
    }

    #[test]
    fn alias_table_realises_the_texel_probabilities() {
        // Heavy-tailed map with black texels and a 1e5 sun.
        let mut map = CubeMap::constant(8, Vec3::ZERO);
        let mut x = 0.37f32;
        for (k, v) in map.data.iter_mut().enumerate() {
            x = (x * 997.0 + 0.123).fract();
            *v = if k % 7 == 0 { Vec3::ZERO } else { Vec3::new(x, 0.5 * x, 2.0 * x * x) };
        }
        map.data[100] = Vec3::new(1e5, 9e4, 8e4);
        let sampler = LightSampler::new(&map);
        let p = realised(&sampler);
        for (k, &pk) in p.iter().enumerate() {
            let want = sampler.texel_probability(k) as f64;
            assert!((pk - want).abs() <= 1e-6 * want.max(1e-3), "texel {k}: table gives {pk}, want {want}");
            if want == 0.0 {
                assert_eq!(pk, 0.0, "black texel {k} reachable");
            }
        }
        // Even u.0 = 1 and slot edges land on a texel with weight.
        for u0 in [0.0, 1.0, 0.5, 1.0 - f32::EPSILON] {
            let s = sampler.sample((u0, 0.5));
            assert!(sampler.texel_probability(s.texel as usize) > 0.0 && s.pdf > 0.0, "u0 {u0}: {s:?}");
        }
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

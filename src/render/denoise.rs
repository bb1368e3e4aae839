//! Cross-bilateral denoiser for Monte Carlo shading buffers (NVDiffRecMC's bilateral denoiser, an
//! SVGF-like filter without the temporal part), as a differentiable operator.
//!
//! out(p) = Σ_q w(p, q) · x(q) / W(p),  W(p) = Σ_q w(p, q), q in a (2r+1)² window around p, with
//!   w(p, q) = exp(−|p−q|²/(2σ²)) · clamp(n_p·n_q, 1e-4, 1)^128 · exp(−|z_q − z_p| / max(ζ_p·|p−q|, 1e-4))
//! where n is the shading normal, z the depth and ζ_p the depth's screen-space slope at p (largest
//! depth step to a 4-neighbour). The weights come from the guides only, never from the noisy image,
//! so the operator is linear in x and its adjoint is the transpose:
//!   ∂L/∂x(q) = Σ_p w(p, q) · g(p) / W(p).
//! The normalised weights are computed once per set of guides (`CrossBilateral::new`) and both
//! passes read them through the same window walk; the backward is a gather over q's window (the
//! window is symmetric), so it is as parallel and race-free as the forward.
//! Pixels without a surface pass through unchanged and never mix with covered ones. Taps whose
//! normal factor is below 1e-12 are dropped (exactly 0), which skips their exp.
//!
//! NVDiffRecMC uses σ = 2 and a 23×23 window (radius 2⌈2.5σ⌉+1 = 11); taps beyond 3σ weigh < 1.2 %
//! of the centre, so the default radius here is ⌈3σ⌉ = 6 (169 taps instead of 529).

use std::sync::Arc;

use anyhow::bail;
use candle_core::{Result, Tensor};
use glam::Vec3;
use rayon::prelude::*;

use crate::optim::tape::{apply, Kernel, Real};
use crate::render::gbuffer::GBuffer;

const FLT_EPS: f64 = 1e-4;

/// Filter settings.
#[derive(Clone, Copy, Debug)]
pub struct BilateralParams {
    /// Spatial standard deviation in pixels.
    pub sigma: f32,
    /// Window radius in pixels.
    pub radius: usize,
    /// Exponent of the normal similarity.
    pub normal_power: u32,
}

impl Default for BilateralParams {
    fn default() -> Self {
        BilateralParams { sigma: 2.0, radius: 6, normal_power: 128 }
    }
}

/// Per-pixel guide data, row-major, row 0 at the top.
#[derive(Clone, Debug)]
pub struct DenoiseGuides {
    pub width: usize,
    pub height: usize,
    pub normal: Vec<Vec3>,
    pub depth: Vec<f32>,
    /// Screen-space depth slope ζ (largest depth step to a covered 4-neighbour).
    pub depth_slope: Vec<f32>,
    pub covered: Vec<bool>,
}

impl DenoiseGuides {
    /// From normals, depths and coverage (each width·height long); normals are normalised.
    pub fn new(width: usize, height: usize, normal: Vec<Vec3>, depth: Vec<f32>, covered: Vec<bool>) -> anyhow::Result<Self> {
        let n = width * height;
        if normal.len() != n || depth.len() != n || covered.len() != n {
            bail!(
                "denoiser guides: {width}×{height} needs {n} values each, got {} normals, {} depths, {} coverage flags",
                normal.len(),
                depth.len(),
                covered.len()
            );
        }
        let normal: Vec<Vec3> = normal.into_iter().map(|v| v.normalize_or_zero()).collect();
        let depth_slope = (0..n)
            .into_par_iter()
            .map(|i| {
                if !covered[i] {
                    return 0.0;
                }
                let (x, y) = (i % width, i / width);
                let mut slope = 0.0f32;
                let mut visit = |j: usize| {
                    if covered[j] {
                        slope = slope.max((depth[j] - depth[i]).abs());
                    }
                };
                if x > 0 {
                    visit(i - 1);
                }
                if x + 1 < width {
                    visit(i + 1);
                }
                if y > 0 {
                    visit(i - width);
                }
                if y + 1 < height {
                    visit(i + width);
                }
                slope
            })
            .collect();
        Ok(DenoiseGuides { width, height, normal, depth, depth_slope, covered })
    }

    /// Shading normals, planar depths and coverage of a G-buffer.
    pub fn from_gbuffer(g: &GBuffer) -> anyhow::Result<Self> {
        let normal = g.surfels.iter().map(|s| s.map_or(Vec3::ZERO, |s| s.normal)).collect();
        let depth = g.surfels.iter().map(|s| s.map_or(0.0, |s| s.depth)).collect();
        let covered = g.surfels.iter().map(|s| s.is_some()).collect();
        Self::new(g.width, g.height, normal, depth, covered)
    }
}

/// The filter for one set of guides. The weights depend on the guides only, so they are computed
/// once here, already divided by W(p), and shared by every forward and backward: 4·(2r+1)² bytes
/// per covered pixel (169 taps: 22 MB for a 256² view half covered). A pixel without a surface
/// has no row: it passes through, and no covered pixel reads it (their weight is 0).
#[derive(Clone)]
pub struct CrossBilateral {
    width: usize,
    height: usize,
    radius: usize,
    /// Per pixel: its row in `weights`, or [`NO_ROW`] for a pixel without a surface.
    rows: Arc<Vec<u32>>,
    /// ŵ(p, p + d) = w(p, p + d) / W(p), one row per covered pixel p over the (2r+1)² offsets d;
    /// 0 outside the image and at uncovered taps.
    weights: Arc<Vec<f32>>,
}

/// The row index of a pixel without a surface.
const NO_ROW: u32 = u32::MAX;

/// Per-offset constants of the window.
struct WindowTables {
    side: usize,
    /// d²/(2σ²)
    spatial_exponent: Vec<f32>,
    /// |d|
    dist: Vec<f32>,
}

impl WindowTables {
    fn new(p: &BilateralParams) -> Self {
        let r = p.radius as i64;
        let var = (p.sigma * p.sigma).max(1e-12);
        let offsets: Vec<(i64, i64)> = (-r..=r).flat_map(|dy| (-r..=r).map(move |dx| (dx, dy))).collect();
        WindowTables {
            side: (2 * r + 1) as usize,
            spatial_exponent: offsets.iter().map(|&(dx, dy)| (dx * dx + dy * dy) as f32 / (2.0 * var)).collect(),
            dist: offsets.iter().map(|&(dx, dy)| ((dx * dx + dy * dy) as f32).sqrt()).collect(),
        }
    }
}

/// w(centre, tap) before normalisation; `off` indexes tap − centre in the window.
#[inline]
fn raw_weight(g: &DenoiseGuides, p: &BilateralParams, t: &WindowTables, centre: usize, tap: usize, off: usize) -> f32 {
    match (g.covered[centre], g.covered[tap]) {
        (false, false) => return if centre == tap { 1.0 } else { 0.0 },
        (true, true) => {}
        _ => return 0.0,
    }
    if centre == tap {
        return 1.0;
    }
    let cos = g.normal[centre].dot(g.normal[tap]).clamp(FLT_EPS as f32, 1.0);
    let w_normal = powi_by_squaring(cos, p.normal_power);
    if w_normal < 1e-12 {
        return 0.0; // below f32 resolution of any sum it joins; skips the exp
    }
    let dz = (g.depth[tap] - g.depth[centre]).abs();
    let depth_exponent = dz / (g.depth_slope[centre] * t.dist[off]).max(FLT_EPS as f32);
    // One exp for the spatial and the depth factor.
    w_normal * (-(t.spatial_exponent[off] + depth_exponent)).exp()
}

/// x^n for n ≥ 0, inlined (the generic `powi` is a library call per tap).
#[inline]
fn powi_by_squaring(mut x: f32, mut n: u32) -> f32 {
    let mut r = 1.0;
    while n > 0 {
        if n & 1 == 1 {
            r *= x;
        }
        x *= x;
        n >>= 1;
    }
    r
}

impl CrossBilateral {
    pub fn new(guides: Arc<DenoiseGuides>, params: BilateralParams) -> Self {
        let g = &*guides;
        let (w, h, r) = (g.width, g.height, params.radius);
        let tables = WindowTables::new(&params);
        let taps = tables.side * tables.side;
        let covered: Vec<usize> = (0..w * h).filter(|&p| g.covered[p]).collect();
        let mut rows = vec![NO_ROW; w * h];
        for (row, &p) in covered.iter().enumerate() {
            rows[p] = row as u32;
        }
        let mut weights = vec![0.0f32; covered.len() * taps];
        weights.par_chunks_mut(taps).zip(covered.par_iter()).for_each(|(row, &p)| {
            let mut sum = 0.0f64;
            for_each_in_window(w, h, r, p, |q, off| {
                let wt = raw_weight(g, &params, &tables, p, q, off);
                row[off] = wt;
                sum += wt as f64;
            });
            let inv = (1.0 / sum.max(FLT_EPS)) as f32;
            row.iter_mut().for_each(|v| *v *= inv);
        });
        CrossBilateral { width: w, height: h, radius: r, rows: Arc::new(rows), weights: Arc::new(weights) }
    }

    /// Denoises `image` [H, W, C] (any C), on the tape.
    pub fn apply(&self, image: &Tensor) -> Result<Tensor> {
        apply(self.clone(), &[image])
    }

    fn taps(&self) -> usize {
        (2 * self.radius + 1).pow(2)
    }

    fn check_dims(&self, shape: &[usize]) -> Result<usize> {
        match shape {
            [h, w, c] if *h == self.height && *w == self.width && *c > 0 => Ok(*c),
            _ => Err(candle_core::Error::Msg(format!(
                "denoiser: image {shape:?} does not match guides {}×{} (expected [H, W, C])",
                self.height, self.width
            ))),
        }
    }
}

/// Calls `f(q, offset_index)` for every pixel q in the window around `p` (clipped to the image);
/// the offset index is that of q − p. The window walk both passes share.
#[inline]
fn for_each_in_window(w: usize, h: usize, r: usize, p: usize, mut f: impl FnMut(usize, usize)) {
    let (w, h, r) = (w as i64, h as i64, r as i64);
    let (px, py) = (p as i64 % w, p as i64 / w);
    let side = 2 * r + 1;
    for dy in -r..=r {
        let y = py + dy;
        if y < 0 || y >= h {
            continue;
        }
        for dx in -r..=r {
            let x = px + dx;
            if x < 0 || x >= w {
                continue;
            }
            f((y * w + x) as usize, ((dy + r) * side + dx + r) as usize);
        }
    }
}

impl Kernel for CrossBilateral {
    fn name(&self) -> &'static str {
        "cross_bilateral"
    }

    fn output_shape(&self, shapes: &[&[usize]]) -> Result<Vec<usize>> {
        self.check_dims(shapes[0])?;
        Ok(shapes[0].to_vec())
    }

    fn forward<T: Real>(&self, x: &[&[T]], shapes: &[&[usize]], out: &mut [T]) -> Result<()> {
        let (x, c) = (x[0], self.check_dims(shapes[0])?);
        let taps = self.taps();
        out.par_chunks_mut(c).enumerate().for_each(|(p, o)| {
            let r = self.rows[p];
            if r == NO_ROW {
                o.copy_from_slice(&x[p * c..(p + 1) * c]);
                return;
            }
            let row = &self.weights[r as usize * taps..(r as usize + 1) * taps];
            for_each_in_window(self.width, self.height, self.radius, p, |q, off| {
                if row[off] == 0.0 {
                    return;
                }
                let w = T::from_f64(row[off] as f64);
                for k in 0..c {
                    o[k] += w * x[q * c + k];
                }
            });
        });
        Ok(())
    }

    fn backward<T: Real>(&self, _x: &[&[T]], shapes: &[&[usize]], g: &[T], grads: &mut [Option<&mut [T]>]) -> Result<()> {
        let Some(gx) = grads[0].as_deref_mut() else { return Ok(()) };
        let c = self.check_dims(shapes[0])?;
        let taps = self.taps();
        gx.par_chunks_mut(c).enumerate().for_each(|(q, o)| {
            if self.rows[q] == NO_ROW {
                // Passed through, and read by no covered pixel.
                for k in 0..c {
                    o[k] += g[q * c + k];
                }
                return;
            }
            // Transpose: q received ŵ(p, q) from every covered p in its window; the offset
            // q − p is the mirror of the walk's offset p − q.
            for_each_in_window(self.width, self.height, self.radius, q, |p, off_pq| {
                let r = self.rows[p];
                if r == NO_ROW {
                    return;
                }
                let w = self.weights[r as usize * taps + taps - 1 - off_pq];
                if w == 0.0 {
                    return;
                }
                let w = T::from_f64(w as f64);
                for k in 0..c {
                    o[k] += w * g[p * c + k];
                }
            });
        });
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Sampler;
    use candle_core::Device;

    fn flat_guides(w: usize, h: usize) -> DenoiseGuides {
        DenoiseGuides::new(w, h, vec![Vec3::Z; w * h], vec![2.0; w * h], vec![true; w * h]).expect("test setup")
    }

    #[test]
    fn reduces_variance_on_a_noisy_constant_patch() -> anyhow::Result<()> {
        let (w, h) = (32, 32);
        let f = CrossBilateral::new(Arc::new(flat_guides(w, h)), BilateralParams::default());
        let mut s = Sampler::from_seed(1);
        let noisy: Vec<f32> = (0..w * h).map(|_| 0.5 + (s.next_f32() - 0.5)).collect();
        let out = f.apply(&Tensor::from_vec(noisy.clone(), (h, w, 1), &Device::Cpu)?)?.flatten_all()?.to_vec1::<f32>()?;
        let var = |v: &[f32]| {
            let m = v.iter().sum::<f32>() / v.len() as f32;
            v.iter().map(|x| (x - m).powi(2)).sum::<f32>() / v.len() as f32
        };
        let (before, after) = (var(&noisy), var(&out));
        assert!(after < 0.1 * before, "variance {before} -> {after}");
        let mean = out.iter().sum::<f32>() / out.len() as f32;
        assert!((mean - 0.5).abs() < 0.02, "mean {mean}");
        Ok(())
    }

    #[test]
    fn preserves_an_edge_in_the_normals() -> anyhow::Result<()> {
        // Left half faces +z with value 1, right half faces +x with value 0: no mixing across.
        let (w, h) = (16, 8);
        let normal = (0..w * h).map(|i| if i % w < w / 2 { Vec3::Z } else { Vec3::X }).collect();
        let g = DenoiseGuides::new(w, h, normal, vec![1.0; w * h], vec![true; w * h])?;
        let f = CrossBilateral::new(Arc::new(g), BilateralParams::default());
        let img: Vec<f32> = (0..w * h).map(|i| if i % w < w / 2 { 1.0 } else { 0.0 }).collect();
        let out = f.apply(&Tensor::from_vec(img.clone(), (h, w, 1), &Device::Cpu)?)?.flatten_all()?.to_vec1::<f32>()?;
        for (o, i) in out.iter().zip(&img) {
            assert!((o - i).abs() < 1e-3, "{o} vs {i}");
        }
        // Without the normal edge the same image is blurred across the boundary.
        let f = CrossBilateral::new(Arc::new(flat_guides(w, h)), BilateralParams::default());
        let out = f.apply(&Tensor::from_vec(img, (h, w, 1), &Device::Cpu)?)?.flatten_all()?.to_vec1::<f32>()?;
        assert!(out[w / 2 - 1] < 0.9 && out[w / 2] > 0.1);
        Ok(())
    }

    #[test]
    fn uncovered_pixels_pass_through_and_stay_unmixed() -> anyhow::Result<()> {
        let (w, h) = (6, 5);
        let covered: Vec<bool> = (0..w * h).map(|i| i % 4 != 0).collect();
        let g = DenoiseGuides::new(w, h, vec![Vec3::Z; w * h], vec![1.0; w * h], covered.clone())?;
        let f = CrossBilateral::new(Arc::new(g), BilateralParams { radius: 2, ..Default::default() });
        let img: Vec<f32> = (0..w * h).map(|i| if covered[i] { 1.0 } else { 7.0 + i as f32 }).collect();
        let out = f.apply(&Tensor::from_vec(img.clone(), (h, w, 1), &Device::Cpu)?)?.flatten_all()?.to_vec1::<f32>()?;
        for i in 0..w * h {
            assert!((out[i] - img[i]).abs() < 1e-5, "pixel {i}: {} vs {}", out[i], img[i]);
        }
        Ok(())
    }

    #[test]
    fn mismatched_image_is_an_error() {
        let f = CrossBilateral::new(Arc::new(flat_guides(4, 4)), BilateralParams::default());
        let err = f.apply(&Tensor::zeros((4, 5, 3), candle_core::DType::F32, &Device::Cpu).expect("test setup")).unwrap_err();
        assert!(err.to_string().contains("does not match guides"), "{err}");
    }
}

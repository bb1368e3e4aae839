//! Cross-bilateral denoiser for Monte Carlo shading buffers (NVDiffRecMC's bilateral denoiser, an
//! SVGF-like filter without the temporal part), as a differentiable operator.
//!
//! out(p) = Σ_q w(p, q) · x(q) / W(p),  W(p) = Σ_q w(p, q), q in a (2r+1)² window around p, with
//!   w(p, q) = exp(−|p−q|²/(2σ²)) · clamp(n_p·n_q, 1e-4, 1)^128 · exp(−|z_q − z_p| / max(ζ_p·|p−q|, 1e-4))
//! where n is the shading normal, z the depth and ζ_p the depth's screen-space slope at p (largest
//! depth step to a 4-neighbour). The weights come from the guides only, never from the noisy image,
//! so the operator is linear in x and its adjoint is the transpose:
//!   ∂L/∂x(q) = Σ_p w(p, q) · g(p) / W(p).
//! The normalised weights are computed once per set of guides (`CrossBilateral::new`), eight
//! taps at a time (`wide`'s f32x8 and its exp), and both passes read them row by row through the
//! same window walk. The forward gathers over p's window; the backward scatters p's row into its
//! window, each band of image rows into its own buffer, and the bands are then summed in a fixed
//! order, so it reads the weights in order and stays race-free and deterministic.
//! Pixels without a surface pass through unchanged and never mix with covered ones. Taps whose
//! normal factor is below 1e-12 are dropped (exactly 0), and both passes skip them.
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

/// w(centre, tap) before normalisation; `off` indexes tap − centre in the window. The scalar
/// definition of the formula at the top of the file: the tests hold the vectorised evaluation in
/// [`WindowScratch::weights`] to it.
#[cfg(test)]
fn raw_weight(g: &DenoiseGuides, p: &BilateralParams, t: &WindowTables, centre: usize, tap: usize, off: usize) -> f32 {
    assert!(g.covered[centre], "only covered pixels have weights");
    if !g.covered[tap] {
        return 0.0;
    }
    if centre == tap {
        return 1.0;
    }
    let cos = g.normal[centre].dot(g.normal[tap]).clamp(FLT_EPS as f32, 1.0);
    let w_normal = powi_by_squaring(cos, p.normal_power, 1.0);
    if w_normal < NORMAL_CUTOFF {
        return 0.0;
    }
    let dz = (g.depth[tap] - g.depth[centre]).abs();
    let depth_exponent = dz / (g.depth_slope[centre] * t.dist[off]).max(FLT_EPS as f32);
    w_normal * (-(t.spatial_exponent[off] + depth_exponent)).exp()
}

/// Normal factors below this are dropped (weight exactly 0): below f32 resolution of any sum
/// the tap joins, since the centre's own weight is 1.
const NORMAL_CUTOFF: f32 = 1e-12;

/// x^n for n ≥ 0 by squaring (the generic `powi` is a library call per tap); generic so the
/// scalar reference and the eight-lane evaluation share it.
#[inline]
fn powi_by_squaring<F: Copy + std::ops::Mul<Output = F>>(mut x: F, mut n: u32, one: F) -> F {
    let mut r = one;
    while n > 0 {
        if n & 1 == 1 {
            r = r * x;
        }
        x = x * x;
        n >>= 1;
    }
    r
}

/// The guides of one window, gathered into contiguous per-tap arrays (padded to a multiple of
/// eight, out-of-image taps uncovered), so the weights are evaluated eight taps at a time.
struct WindowScratch {
    nx: Vec<f32>,
    ny: Vec<f32>,
    nz: Vec<f32>,
    depth: Vec<f32>,
    covered: Vec<f32>,
    /// The window's d²/(2σ²) and |d| per offset, padded with ones (the padding is uncovered).
    spatial_exponent: Vec<f32>,
    dist: Vec<f32>,
}

impl WindowScratch {
    fn new(t: &WindowTables) -> Self {
        let taps = t.side * t.side;
        let padded = taps.div_ceil(8) * 8;
        let pad = |v: &[f32]| {
            let mut p = v.to_vec();
            p.resize(padded, 1.0);
            p
        };
        WindowScratch {
            nx: vec![0.0; padded],
            ny: vec![0.0; padded],
            nz: vec![0.0; padded],
            depth: vec![0.0; padded],
            covered: vec![0.0; padded],
            spatial_exponent: pad(&t.spatial_exponent),
            dist: pad(&t.dist),
        }
    }

    /// Writes the raw weights w(p, p + d) of covered pixel `p` into `row` (one per offset, 0 outside
    /// the image, at uncovered taps and below the normal cut-off) and returns their sum.
    fn weights(&mut self, g: &DenoiseGuides, params: &BilateralParams, p: usize, row: &mut [f32]) -> f64 {
        use wide::f32x8;
        let (w, h, r) = (g.width, g.height, params.radius);
        self.covered.fill(0.0);
        for_each_span(w, h, r, p, |q0, off0, len| {
            for j in 0..len {
                let (q, o) = (q0 + j, off0 + j);
                let n = g.normal[q];
                (self.nx[o], self.ny[o], self.nz[o]) = (n.x, n.y, n.z);
                self.depth[o] = g.depth[q];
                self.covered[o] = if g.covered[q] { 1.0 } else { 0.0 };
            }
        });
        let (np, zp) = (g.normal[p], g.depth[p]);
        let (npx, npy, npz) = (f32x8::splat(np.x), f32x8::splat(np.y), f32x8::splat(np.z));
        let (zp8, slope) = (f32x8::splat(zp), f32x8::splat(g.depth_slope[p]));
        let (eps, one, zero, cutoff) = (f32x8::splat(FLT_EPS as f32), f32x8::ONE, f32x8::ZERO, f32x8::splat(NORMAL_CUTOFF));
        let load = |v: &[f32], i: usize| f32x8::new(v[i..i + 8].try_into().expect("chunk of eight"));
        let taps = row.len();
        for i in (0..self.covered.len()).step_by(8) {
            let cos = (npx * load(&self.nx, i) + npy * load(&self.ny, i) + npz * load(&self.nz, i)).fast_max(eps).fast_min(one);
            let w_normal = powi_by_squaring(cos, params.normal_power, one);
            let w_normal = w_normal.simd_ge(cutoff).select(w_normal, zero) * load(&self.covered, i);
            let depth_exponent = (load(&self.depth, i) - zp8).abs() / (slope * load(&self.dist, i)).fast_max(eps);
            let wt: [f32; 8] = (w_normal * (-(load(&self.spatial_exponent, i) + depth_exponent)).exp()).into();
            let n = (taps - i).min(8);
            row[i..i + n].copy_from_slice(&wt[..n]);
        }
        row[taps / 2] = 1.0; // the centre: exactly 1, whatever its normal
        row.iter().map(|&v| v as f64).sum()
    }
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
        weights.par_chunks_mut(taps).zip(covered.par_iter()).for_each_init(
            || WindowScratch::new(&tables),
            |scratch, (row, &p)| {
                let sum = scratch.weights(g, &params, p, row);
                let inv = (1.0 / sum.max(FLT_EPS)) as f32;
                row.iter_mut().for_each(|v| *v *= inv);
            },
        );
        CrossBilateral { width: w, height: h, radius: r, rows: Arc::new(rows), weights: Arc::new(weights) }
    }

    /// Denoises `image` [H, W, C] (any C), on the tape.
    pub fn apply(&self, image: &Tensor) -> Result<Tensor> {
        apply(self.clone(), &[image])
    }

    fn taps(&self) -> usize {
        (2 * self.radius + 1).pow(2)
    }

    /// Calls `f(q, ŵ(p, q))` for every tap q of covered pixel `p` (its weight row `r`) whose
    /// weight is not zero, in window order: the walk both passes share. Zero taps are skipped,
    /// not multiplied, so an uncovered tap's value (which may be anything) never leaks in.
    #[inline]
    fn for_each_tap(&self, p: usize, r: u32, mut f: impl FnMut(usize, f32)) {
        let taps = self.taps();
        let row = &self.weights[r as usize * taps..(r as usize + 1) * taps];
        for_each_span(self.width, self.height, self.radius, p, |q0, off0, len| {
            for (j, &w) in row[off0..off0 + len].iter().enumerate() {
                if w != 0.0 {
                    f(q0 + j, w);
                }
            }
        });
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

/// Calls `f(q0, offset0, len)` for each image row of the window around `p`, clipped to the
/// image: the pixels q0 .. q0 + len, whose offsets from p have indices offset0 .. offset0 + len.
/// The window walk the weights, the forward and the backward share.
#[inline]
fn for_each_span(w: usize, h: usize, r: usize, p: usize, mut f: impl FnMut(usize, usize, usize)) {
    let (px, py) = (p % w, p / w);
    let side = 2 * r + 1;
    let (x0, x1) = (px.saturating_sub(r), (px + r).min(w - 1));
    let (y0, y1) = (py.saturating_sub(r), (py + r).min(h - 1));
    for y in y0..=y1 {
        let off0 = (y + r - py) * side + (x0 + r - px);
        f(y * w + x0, off0, x1 - x0 + 1);
    }
}

/// Image rows per band of the backward's scatter; each band also writes `radius` rows above
/// and below it, so bands much taller than the window keep that overlap small, and 256-row views
/// still give every core several bands.
const BACKWARD_BAND_ROWS: usize = 32;

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
        out.par_chunks_mut(c).enumerate().for_each(|(p, o)| {
            let r = self.rows[p];
            if r == NO_ROW {
                o.copy_from_slice(&x[p * c..(p + 1) * c]);
                return;
            }
            self.for_each_tap(p, r, |q, w| {
                let (w, xq) = (T::from_f64(w as f64), &x[q * c..(q + 1) * c]);
                for k in 0..c {
                    o[k] += w * xq[k];
                }
            });
        });
        Ok(())
    }

    /// The transpose, as a scatter: each covered p adds ŵ(p, q)·g(p) to every q of its window,
    /// reading its weights in order. Bands of image rows scatter into their own buffers (the
    /// band plus `radius` rows either side), which are then summed row by row in a fixed
    /// order, so the result is race-free and the same on every run.
    fn backward<T: Real>(&self, _x: &[&[T]], shapes: &[&[usize]], g: &[T], grads: &mut [Option<&mut [T]>]) -> Result<()> {
        let Some(gx) = grads[0].as_deref_mut() else { return Ok(()) };
        let c = self.check_dims(shapes[0])?;
        let (w, h, r) = (self.width, self.height, self.radius);
        if w == 0 || h == 0 {
            return Ok(()); // an empty image has no gradient to pass
        }
        let bands: Vec<(usize, Vec<T>)> = (0..h.div_ceil(BACKWARD_BAND_ROWS))
            .into_par_iter()
            .map(|b| {
                let (y0, y1) = (b * BACKWARD_BAND_ROWS, ((b + 1) * BACKWARD_BAND_ROWS).min(h));
                let (top, bottom) = (y0.saturating_sub(r), (y1 + r).min(h));
                let mut acc = vec![T::default(); (bottom - top) * w * c];
                let base = top * w;
                for p in y0 * w..y1 * w {
                    let gp = &g[p * c..(p + 1) * c];
                    let rp = self.rows[p];
                    if rp == NO_ROW {
                        // Passed through, and read by no covered pixel.
                        for k in 0..c {
                            acc[(p - base) * c + k] += gp[k];
                        }
                        continue;
                    }
                    self.for_each_tap(p, rp, |q, wt| {
                        let (wt, a) = (T::from_f64(wt as f64), &mut acc[(q - base) * c..(q - base + 1) * c]);
                        for k in 0..c {
                            a[k] += wt * gp[k];
                        }
                    });
                }
                (top, acc)
            })
            .collect();
        gx.par_chunks_mut(w * c).enumerate().for_each(|(y, out_row)| {
            for (top, acc) in &bands {
                let rows_in = acc.len() / (w * c);
                if y >= *top && y < top + rows_in {
                    let src = &acc[(y - top) * w * c..(y - top + 1) * w * c];
                    out_row.iter_mut().zip(src).for_each(|(o, &s)| *o += s);
                }
            }
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

    /// Guides with two orientations, depth ramps and steps, holes and a zero normal, on an
    /// image taller than several backward bands.
    fn varied_guides(w: usize, h: usize, seed: u64) -> DenoiseGuides {
        let mut s = Sampler::from_seed(seed);
        let mut jitter = || 0.3 * (s.next_f32() - 0.5);
        let normal = (0..w * h)
            .map(|i| if i == 5 { Vec3::ZERO } else if (i % w) < w / 3 { Vec3::Z } else { Vec3::new(0.6 + jitter(), jitter(), 0.8) })
            .collect();
        let depth = (0..w * h).map(|i| 2.0 + 0.02 * (i % w) as f32 + if (i / w).is_multiple_of(9) { 0.5 } else { 0.0 }).collect();
        let covered = (0..w * h).map(|i| i % 13 != 4 && (i / w) % 17 != 16).collect();
        DenoiseGuides::new(w, h, normal, depth, covered).expect("test setup")
    }

    #[test]
    fn vectorised_weights_match_the_scalar_definition() {
        let (w, h) = (23, 19);
        let g = varied_guides(w, h, 3);
        for params in [BilateralParams::default(), BilateralParams { sigma: 1.0, radius: 2, normal_power: 5 }] {
            let t = WindowTables::new(&params);
            let mut scratch = WindowScratch::new(&t);
            let mut row = vec![0.0f32; t.side * t.side];
            for p in (0..w * h).filter(|&p| g.covered[p]) {
                let sum = scratch.weights(&g, &params, p, &mut row);
                let mut reference = vec![0.0f32; row.len()];
                for_each_span(w, h, params.radius, p, |q0, off0, len| {
                    for j in 0..len {
                        reference[off0 + j] = raw_weight(&g, &params, &t, p, q0 + j, off0 + j);
                    }
                });
                for (off, (a, b)) in row.iter().zip(&reference).enumerate() {
                    assert!((a - b).abs() <= 1e-6 * b.abs().max(1e-6), "pixel {p}, offset {off}: {a} vs {b}");
                }
                let ref_sum: f64 = reference.iter().map(|&v| v as f64).sum();
                assert!((sum - ref_sum).abs() <= 1e-5 * ref_sum, "pixel {p}: sum {sum} vs {ref_sum}");
            }
        }
    }

    #[test]
    fn banded_backward_is_the_adjoint_across_bands() -> anyhow::Result<()> {
        // ⟨f(x), y⟩ = ⟨x, fᵀ(y)⟩ on an image of three bands (with their overlaps), in f64.
        let (w, h, c) = (11, 2 * BACKWARD_BAND_ROWS + 7, 2);
        let f = CrossBilateral::new(Arc::new(varied_guides(w, h, 5)), BilateralParams { sigma: 1.5, radius: 3, normal_power: 16 });
        let mut s = Sampler::from_seed(9);
        let x: Vec<f64> = (0..w * h * c).map(|_| s.next_f32() as f64).collect();
        let y: Vec<f64> = (0..w * h * c).map(|_| s.next_f32() as f64 - 0.5).collect();
        let shape = [h, w, c];
        let mut fx = vec![0.0f64; x.len()];
        f.forward(&[&x], &[&shape], &mut fx)?;
        let mut fty = vec![0.0f64; x.len()];
        f.backward(&[&x], &[&shape], &y, &mut [Some(&mut fty)])?;
        let lhs: f64 = fx.iter().zip(&y).map(|(a, b)| a * b).sum();
        let rhs: f64 = x.iter().zip(&fty).map(|(a, b)| a * b).sum();
        assert!((lhs - rhs).abs() < 1e-9 * lhs.abs().max(1.0), "{lhs} vs {rhs}");
        // And the weights reach across a band boundary: a pulse just below the first band
        // spreads gradient into the band above.
        let mut pulse = vec![0.0f64; x.len()];
        let first_row_below = BACKWARD_BAND_ROWS * w;
        let q = (first_row_below..first_row_below + w).find(|&q| f.rows[q] != NO_ROW && f.rows[q - w] != NO_ROW).expect("a covered pair across the boundary");
        pulse[q * c] = 1.0;
        let mut gt = vec![0.0f64; x.len()];
        f.backward(&[&x], &[&shape], &pulse, &mut [Some(&mut gt)])?;
        assert!(gt[(q - w) * c] > 0.0, "no gradient across the band boundary");
        Ok(())
    }

    #[test]
    fn mismatched_image_is_an_error() {
        let f = CrossBilateral::new(Arc::new(flat_guides(4, 4)), BilateralParams::default());
        let err = f.apply(&Tensor::zeros((4, 5, 3), candle_core::DType::F32, &Device::Cpu).expect("test setup")).unwrap_err();
        assert!(err.to_string().contains("does not match guides"), "{err}");
    }
}

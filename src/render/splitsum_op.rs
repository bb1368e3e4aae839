//! Differentiable split-sum shading (docs/model.md, *Shading*): the forward of `render::splitsum::shade` as a
//! tape [`Kernel`], with gradients w.r.t. the per-pixel material and the base cube map of the light.
//!
//! Inputs (all f32 or all f64):
//! - `kd` [N, 3]: base colour;
//! - `ks` [N, 3]: (occlusion, roughness, metallic), NVDiffRec's ORM layout (occlusion is unused and
//!   gets a zero gradient);
//! - `light` [6, R, R, 3]: the base cube map (OpenGL face order, row-major texels, RGB).
//!
//! Output: linear radiance [N, 3]; zero (and no gradient) at pixels whose ray missed.
//!
//! The light is a parameter, so every call rebuilds the split-sum light from it: mip chain by 2×2
//! averaging, GGX-prefiltered specular levels, irradiance. All of these are fixed linear maps of the
//! base texels ([`LightMaps`]): either stored as sparse stencils with their transposes (f64, for
//! small bases and gradient checks) or recomputed each call by the prefilter's own culling and
//! weights (`LightMaps::matrix_free`, f32, no memory; the one to use for training). The backward is
//! the transpose of each step: scatter into level texels with the lookup tap weights, then the
//! transposed prefilter/irradiance, then the transpose of the 2×2 averaging. The backward recomputes
//! the light's forward (the kernel keeps no state between passes).
//! Measured (`cargo test --release --test diff_splitsum measure -- --ignored --nocapture`, 65 536
//! pixels, 2 cores shared with other jobs), matrix-free forward / backward: 6×128² 0.07 / 0.18 s,
//! 6×256² 0.36 / 1.0 s, 6×512² 2.7 / 7.6 s (`SplitSumLight::new` alone: 0.05, 0.32, 2.6 s).
//! Stored stencils ([`LightMaps::nnz`] entries of 8 bytes, forward and transpose): 68 M ≈ 0.54 GB
//! at 6×128² (built in 0.8 s), 530 M ≈ 4.2 GB at 6×256² (15 s): not for large bases.
//!
//! Per pixel (f64 inside whatever the tensor type, so gradient checks see smooth functions):
//!   out = kd(1−m)·E(n) + P(r_refl, ρ)·(F0·A(n·v, ρ) + B(n·v, ρ)),  F0 = 0.04 + (kd − 0.04)·m.
//! ∂/∂ρ goes through the linear interpolation between the two prefiltered levels that bracket the
//! fractional mip level (slope n₂/0.42 on (0.08, 0.5), 2 on (0.5, 1)) and through the LUT's bilinear
//! interpolation in roughness (slope = LUT size inside its texel-centre range): piecewise linear, so
//! the derivative is one-sided at level and LUT-centre kinks. Below the 0.08 roughness floor the
//! level is clamped (no gradient through P), but the LUT still varies down to its first texel
//! centre (ρ = ½/size), so ∂/∂ρ there is P·(F0·∂A/∂ρ + ∂B/∂ρ) only; at or above 1 it is zero.
//! Metallic is not clamped (as in `shade`), so its gradient is the plain product rule.

use std::sync::Arc;

use candle_core::{Result, Tensor};
use glam::Vec3;
use rayon::prelude::*;

use crate::light::brdf_lut::BrdfLut;
use crate::light::cubemap::{CubeMap, Taps};
use crate::light::prefilter::{
    irradiance, irradiance_adjoint, irradiance_stencil, level_roughness, mip_chain_res, prefilter_specular,
    prefilter_specular_adjoint, prefilter_specular_stencil, specular_sources, PrefilterOptions, Stencil, MAX_ROUGHNESS,
};
use crate::material::brdf::{self, MIN_ROUGHNESS};
use crate::optim::tape::{apply, scatter_add_banded, Kernel, Real};
use crate::render::effects::Effects;
use crate::render::gbuffer::GBuffer;

/// Dielectric F0 of the split-sum model (`Vec3::splat(0.04).lerp(kd, m)` in `shade_point`).
const F0_DIELECTRIC: f64 = 0.04;

/// out[o] = ∑ w·src[i] over the stencil row of o, for RGB texels stored flat (3 per texel).
fn apply_stencil(st: &Stencil, src: &[f64], out: &mut [f64]) {
    out.par_chunks_mut(3).enumerate().for_each(|(o, px)| {
        for (i, w) in st.row(o) {
            let w = w as f64;
            px[0] += w * src[3 * i];
            px[1] += w * src[3 * i + 1];
            px[2] += w * src[3 * i + 2];
        }
    });
}

/// The split-sum light of one base resolution as fixed linear maps, shared by every view and
/// iteration. Two ways to hold them:
/// - [`LightMaps::new`] stores each map and its transpose as sparse stencils (f64 arithmetic,
///   exact adjoint; memory about 0.54 GB at a 6×128² base and 4.2 GB at 6×256², so only for
///   small bases and for gradient checks);
/// - [`LightMaps::matrix_free`] recomputes the weights every call with the prefilter's own code
///   (f32 arithmetic, memory of a few cube maps; a forward costs about one `SplitSumLight::new`,
///   a backward about three).
pub struct LightMaps {
    /// Resolutions of the mip chain (level 0 = the base; a repeated resolution is a copy).
    pub chain_res: Vec<usize>,
    /// The GGX roughness of each specular level (level k has the resolution `chain_res[k]`).
    pub level_roughness: Vec<f32>,
    /// Per specular level, the chain level it is filtered from.
    sources: Vec<usize>,
    storage: Storage,
    /// Empty maps of each level's resolution, for `lookup_taps`.
    level_maps: Vec<CubeMap>,
}

enum Storage {
    /// Per specular level: its stencil and the transpose; then irradiance and its transpose.
    Stored { specular: Vec<(Stencil, Stencil)>, irradiance: (Stencil, Stencil) },
    MatrixFree { kernel_mass: f32 },
}

/// The split-sum light rebuilt from one base map, in f64, RGB texels flat.
pub struct LightLevels {
    pub specular: Vec<Vec<f64>>,
    pub diffuse: Vec<f64>,
}

fn to_cubemap(res: usize, flat: &[f64]) -> CubeMap {
    CubeMap { res, data: flat.chunks(3).map(|v| Vec3::new(v[0] as f32, v[1] as f32, v[2] as f32)).collect() }
}

fn from_cubemap(m: &CubeMap) -> Vec<f64> {
    m.data.iter().flat_map(|v| [v.x as f64, v.y as f64, v.z as f64]).collect()
}

impl LightMaps {
    /// Stored stencils (see the type doc).
    pub fn new(base_res: usize, opts: PrefilterOptions) -> Self {
        let mut maps = Self::matrix_free(base_res, opts);
        let specular = maps
            .sources
            .iter()
            .enumerate()
            .map(|(k, &src)| {
                let st = prefilter_specular_stencil(maps.chain_res[src], maps.chain_res[k], maps.level_roughness[k], opts.kernel_mass);
                let t = st.transpose();
                (st, t)
            })
            .collect();
        let irr = irradiance_stencil(maps.chain_res[maps.chain_res.len() - 1]);
        let irr_t = irr.transpose();
        maps.storage = Storage::Stored { specular, irradiance: (irr, irr_t) };
        maps
    }

    /// Weights recomputed every call (see the type doc).
    pub fn matrix_free(base_res: usize, opts: PrefilterOptions) -> Self {
        let chain_res = mip_chain_res(base_res);
        let level_roughness = level_roughness(chain_res.len());
        let sources = specular_sources(&chain_res, opts);
        let level_maps = chain_res.iter().map(|&r| CubeMap::constant(r, Vec3::ZERO)).collect();
        LightMaps { chain_res, level_roughness, sources, storage: Storage::MatrixFree { kernel_mass: opts.kernel_mass }, level_maps }
    }

    /// Number of stored stencil entries (forward and transpose), a measure of memory and cost.
    pub fn nnz(&self) -> usize {
        match &self.storage {
            Storage::Stored { specular, irradiance } => {
                specular.iter().map(|(a, b)| a.nnz() + b.nnz()).sum::<usize>() + irradiance.0.nnz() + irradiance.1.nnz()
            }
            Storage::MatrixFree { .. } => 0,
        }
    }

    pub fn base_res(&self) -> usize {
        self.chain_res[0]
    }

    fn texels(res: usize) -> usize {
        6 * res * res
    }

    /// Mip chain of `base` (flat RGB): 2×2 means, or a copy where the resolution repeats.
    fn chain(&self, base: &[f64]) -> Vec<Vec<f64>> {
        let mut chain = vec![base.to_vec()];
        for k in 1..self.chain_res.len() {
            let (prev, r) = (&chain[k - 1], self.chain_res[k]);
            if r == self.chain_res[k - 1] {
                chain.push(prev.clone());
                continue;
            }
            let pr = self.chain_res[k - 1];
            let mut next = vec![0.0; 3 * Self::texels(r)];
            next.par_chunks_mut(3).enumerate().for_each(|(t, px)| {
                let (face, i, j) = (t / (r * r), (t / r) % r, t % r);
                for (di, dj) in [(0, 0), (0, 1), (1, 0), (1, 1)] {
                    let s = (face * pr + 2 * i + di) * pr + 2 * j + dj;
                    for c in 0..3 {
                        px[c] += 0.25 * prev[3 * s + c];
                    }
                }
            });
            chain.push(next);
        }
        chain
    }

    /// The prefiltered specular levels and the diffuse map of `base`.
    pub fn forward(&self, base: &[f64]) -> LightLevels {
        let chain = self.chain(base);
        let last = chain.len() - 1;
        match &self.storage {
            Storage::Stored { specular, irradiance } => {
                let specular = specular
                    .iter()
                    .enumerate()
                    .map(|(k, (st, _))| {
                        let mut out = vec![0.0; 3 * Self::texels(self.chain_res[k])];
                        apply_stencil(st, &chain[self.sources[k]], &mut out);
                        out
                    })
                    .collect();
                let mut diffuse = vec![0.0; 3 * Self::texels(self.chain_res[last])];
                apply_stencil(&irradiance.0, &chain[last], &mut diffuse);
                LightLevels { specular, diffuse }
            }
            Storage::MatrixFree { kernel_mass } => {
                let maps: Vec<CubeMap> = chain.iter().zip(&self.chain_res).map(|(c, &r)| to_cubemap(r, c)).collect();
                let specular = (0..maps.len())
                    .map(|k| from_cubemap(&prefilter_specular(&maps[self.sources[k]], self.chain_res[k], self.level_roughness[k], *kernel_mass)))
                    .collect();
                LightLevels { specular, diffuse: from_cubemap(&irradiance(&maps[last])) }
            }
        }
    }

    /// Adjoint of [`forward`](Self::forward): ∂L/∂base from ∂L/∂(specular levels) and ∂L/∂diffuse.
    pub fn backward(&self, g_specular: &[Vec<f64>], g_diffuse: &[f64]) -> Vec<f64> {
        let mut g_chain: Vec<Vec<f64>> = self.chain_res.iter().map(|&r| vec![0.0; 3 * Self::texels(r)]).collect();
        let last = g_chain.len() - 1;
        match &self.storage {
            Storage::Stored { specular, irradiance } => {
                for (k, (_, st_t)) in specular.iter().enumerate() {
                    apply_stencil(st_t, &g_specular[k], &mut g_chain[self.sources[k]]);
                }
                apply_stencil(&irradiance.1, g_diffuse, &mut g_chain[last]);
            }
            Storage::MatrixFree { kernel_mass } => {
                let add = |acc: &mut Vec<f64>, m: &CubeMap| acc.iter_mut().zip(from_cubemap(m)).for_each(|(a, b)| *a += b);
                for (k, g) in g_specular.iter().enumerate() {
                    let src = self.sources[k];
                    let g = to_cubemap(self.chain_res[k], g);
                    add(&mut g_chain[src], &prefilter_specular_adjoint(&g, self.chain_res[src], self.level_roughness[k], *kernel_mass));
                }
                add(&mut g_chain[last], &irradiance_adjoint(&to_cubemap(self.chain_res[last], g_diffuse)));
            }
        }
        // Transpose of the chain, coarse to fine: each child texel gets ¼ of its parent's gradient.
        for k in (1..self.chain_res.len()).rev() {
            let (fine, coarse) = g_chain.split_at_mut(k);
            let (prev, g) = (&mut fine[k - 1], &coarse[0]);
            let (pr, r) = (self.chain_res[k - 1], self.chain_res[k]);
            if pr == r {
                prev.iter_mut().zip(g).for_each(|(a, b)| *a += b);
                continue;
            }
            prev.par_chunks_mut(3).enumerate().for_each(|(t, px)| {
                let (face, i, j) = (t / (pr * pr), (t / pr) % pr, t % pr);
                let parent = (face * r + i / 2) * r + j / 2;
                for c in 0..3 {
                    px[c] += 0.25 * g[3 * parent + c];
                }
            });
        }
        g_chain.swap_remove(0)
    }
}

/// Fixed per-pixel geometry of a covered pixel.
#[derive(Clone, Copy, Debug)]
pub struct PixelGeom {
    /// Clamped n·v (the LUT's column coordinate).
    pub nov: f32,
    /// Mirror direction of the view about the normal.
    pub refl: Vec3,
    /// Taps of the diffuse (irradiance) lookup along the normal.
    pub diffuse_taps: Taps,
}

impl PixelGeom {
    /// The same geometry as `splitsum::shade_point` derives from a normal and an outgoing direction.
    pub fn new(normal: Vec3, wo: Vec3, diffuse_map: &CubeMap) -> Self {
        PixelGeom {
            nov: brdf::clamp_cos(normal.dot(wo)),
            refl: (2.0 * normal.dot(wo) * normal - wo).normalize_or(normal),
            diffuse_taps: diffuse_map.lookup_taps(normal),
        }
    }
}

/// Fractional specular level for roughness `r` with `n` levels (`mip_level_for_roughness` in
/// f64) and its derivative (zero where the roughness is clamped).
fn mip_level(r: f64, n: usize) -> (f64, f64) {
    let (lo, mid) = (MIN_ROUGHNESS as f64, MAX_ROUGHNESS as f64);
    let r = if r.is_nan() { lo } else { r };
    let n2 = n.saturating_sub(2) as f64;
    if r < mid {
        let slope = if r > lo { n2 / (mid - lo) } else { 0.0 };
        ((r.clamp(lo, mid) - lo) / (mid - lo) * n2, slope)
    } else {
        let slope = if r < 1.0 { 1.0 / (1.0 - mid) } else { 0.0 };
        ((r.clamp(mid, 1.0) - mid) / (1.0 - mid) + n2, slope)
    }
}

/// The LUT's bilinear (A, B) at (n·v, ρ) in f64 (as `BrdfLut::lookup`) and ∂(A, B)/∂ρ.
fn lut_lookup(lut: &BrdfLut, nov: f32, rough: f64) -> ([f64; 2], [f64; 2]) {
    let n = lut.size;
    let coord = |v: f64| {
        let v = if v.is_nan() { 0.0 } else { v };
        let raw = v.clamp(0.0, 1.0) * n as f64 - 0.5;
        let slope = if v > 0.0 && v < 1.0 && raw > 0.0 && raw < (n - 1) as f64 { n as f64 } else { 0.0 };
        (raw.clamp(0.0, (n - 1) as f64), slope)
    };
    let (x, _) = coord(nov as f64);
    let (y, dy) = coord(rough);
    let (j0, i0) = (x.floor() as usize, y.floor() as usize);
    let (j1, i1) = ((j0 + 1).min(n - 1), (i0 + 1).min(n - 1));
    let (tx, ty) = (x - j0 as f64, y - i0 as f64);
    let at = |i: usize, j: usize| {
        let (a, b) = lut.data[i * n + j];
        [a as f64, b as f64]
    };
    let row = |i: usize| {
        let (p, q) = (at(i, j0), at(i, j1));
        [p[0] + (q[0] - p[0]) * tx, p[1] + (q[1] - p[1]) * tx]
    };
    let (r0, r1) = (row(i0), row(i1));
    (
        [r0[0] + (r1[0] - r0[0]) * ty, r0[1] + (r1[1] - r0[1]) * ty],
        [(r1[0] - r0[0]) * dy, (r1[1] - r0[1]) * dy],
    )
}

fn gather(taps: &Taps, map: &[f64]) -> [f64; 3] {
    let mut v = [0.0; 3];
    for (k, w) in taps.iter() {
        for c in 0..3 {
            v[c] += w as f64 * map[3 * k + c];
        }
    }
    v
}

/// Everything one pixel's forward computes that its adjoint reuses.
struct PixelEval {
    out: [f64; 3],
    /// Irradiance/π along the normal.
    e: [f64; 3],
    /// Prefiltered radiance, its ∂/∂ρ, the two levels blended (l0, l1) with weight t on l1, and their taps.
    p: [f64; 3],
    dp: [f64; 3],
    levels: (usize, usize, f64),
    taps: (Taps, Taps),
    ab: [f64; 2],
    dab: [f64; 2],
}

/// The differentiable split-sum shading operator for one view (see the module doc).
#[derive(Clone)]
pub struct SplitSumShading {
    pub pixels: Arc<[Option<PixelGeom>]>,
    pub light: Arc<LightMaps>,
    pub lut: Arc<BrdfLut>,
    pub effects: Effects,
}

impl SplitSumShading {
    /// `geometry[p]` = (normal, outgoing direction) of pixel p, `None` for a miss.
    pub fn new(geometry: &[Option<(Vec3, Vec3)>], light: Arc<LightMaps>, lut: Arc<BrdfLut>, effects: Effects) -> Self {
        let diffuse_map = &light.level_maps[light.level_maps.len() - 1];
        let pixels: Vec<Option<PixelGeom>> =
            geometry.par_iter().map(|g| g.map(|(n, wo)| PixelGeom::new(n, wo, diffuse_map))).collect();
        SplitSumShading { pixels: pixels.into(), light, lut, effects }
    }

    /// Every pixel of `gbuf` (N = width·height), with the outgoing direction toward its camera.
    pub fn from_gbuffer(gbuf: &GBuffer, light: Arc<LightMaps>, lut: Arc<BrdfLut>, effects: Effects) -> Self {
        let geometry: Vec<Option<(Vec3, Vec3)>> =
            gbuf.surfels.iter().map(|s| s.map(|s| (s.normal, (gbuf.origin - s.position).normalize()))).collect();
        Self::new(&geometry, light, lut, effects)
    }

    /// One pixel's forward in f64: the single code path of both passes.
    fn eval(&self, g: &PixelGeom, kd: [f64; 3], rough: f64, metal: f64, levels: &LightLevels) -> PixelEval {
        let e = gather(&g.diffuse_taps, &levels.diffuse);
        let mut out = [0.0; 3];
        for c in 0..3 {
            out[c] = kd[c] * (1.0 - metal) * e[c];
        }
        let n = levels.specular.len();
        let mut ev = PixelEval {
            out,
            e,
            p: [0.0; 3],
            dp: [0.0; 3],
            levels: (0, 0, 0.0),
            taps: (g.diffuse_taps, g.diffuse_taps),
            ab: [0.0; 2],
            dab: [0.0; 2],
        };
        if !self.effects.specular {
            return ev;
        }
        let (m, dm) = mip_level(rough, n);
        let m = m.clamp(0.0, (n - 1) as f64);
        let l0 = (m.floor() as usize).min(n - 1);
        let l1 = (l0 + 1).min(n - 1);
        let t = if l1 == l0 { 0.0 } else { m - l0 as f64 };
        let dt = if l1 == l0 { 0.0 } else { dm };
        let taps0 = self.light.level_maps[l0].lookup_taps(g.refl);
        let taps1 = self.light.level_maps[l1].lookup_taps(g.refl);
        let (p0, p1) = (gather(&taps0, &levels.specular[l0]), gather(&taps1, &levels.specular[l1]));
        let (ab, dab) = lut_lookup(&self.lut, g.nov, rough);
        for c in 0..3 {
            ev.p[c] = p0[c] * (1.0 - t) + p1[c] * t;
            ev.dp[c] = (p1[c] - p0[c]) * dt;
            let f0 = F0_DIELECTRIC + (kd[c] - F0_DIELECTRIC) * metal;
            ev.out[c] += ev.p[c] * (f0 * ab[0] + ab[1]);
        }
        ev.levels = (l0, l1, t);
        ev.taps = (taps0, taps1);
        ev.ab = ab;
        ev.dab = dab;
        ev
    }

    fn check_shapes(&self, shapes: &[&[usize]]) -> Result<()> {
        let n = self.pixels.len();
        let r = self.light.base_res();
        let ok = shapes.len() == 3 && shapes[0] == [n, 3] && shapes[1] == [n, 3] && shapes[2] == [6, r, r, 3];
        if ok {
            Ok(())
        } else {
            Err(candle_core::Error::Msg(format!(
                "split-sum shading: expected kd [{n}, 3], ks [{n}, 3] (occlusion, roughness, metallic) and light [6, {r}, {r}, 3], got {shapes:?}"
            )))
        }
    }
}

fn to_f64<T: Real>(x: &[T]) -> Vec<f64> {
    x.par_iter().map(|v| v.to_f64()).collect()
}

impl Kernel for SplitSumShading {
    fn name(&self) -> &'static str {
        "splitsum_shading"
    }

    fn output_shape(&self, shapes: &[&[usize]]) -> Result<Vec<usize>> {
        self.check_shapes(shapes)?;
        Ok(vec![self.pixels.len(), 3])
    }

    fn forward<T: Real>(&self, x: &[&[T]], _shapes: &[&[usize]], out: &mut [T]) -> Result<()> {
        let (kd, ks) = (x[0], x[1]);
        let levels = self.light.forward(&to_f64(x[2]));
        out.par_chunks_mut(3).zip(self.pixels.par_iter()).enumerate().for_each(|(p, (o, g))| {
            let Some(g) = g else { return };
            let kdp = [kd[3 * p].to_f64(), kd[3 * p + 1].to_f64(), kd[3 * p + 2].to_f64()];
            let ev = self.eval(g, kdp, ks[3 * p + 1].to_f64(), ks[3 * p + 2].to_f64(), &levels);
            for (o, &e) in o.iter_mut().zip(&ev.out) {
                *o = T::from_f64(e);
            }
        });
        Ok(())
    }

    fn backward<T: Real>(&self, x: &[&[T]], _shapes: &[&[usize]], g_out: &[T], grads: &mut [Option<&mut [T]>]) -> Result<()> {
        let (kd, ks) = (x[0], x[1]);
        let levels = self.light.forward(&to_f64(x[2]));
        let eval = |p: usize| -> Option<(PixelEval, [f64; 3], f64, [f64; 3])> {
            let g = self.pixels[p].as_ref()?;
            let kdp = [kd[3 * p].to_f64(), kd[3 * p + 1].to_f64(), kd[3 * p + 2].to_f64()];
            let metal = ks[3 * p + 2].to_f64();
            let ev = self.eval(g, kdp, ks[3 * p + 1].to_f64(), metal, &levels);
            let go = [g_out[3 * p].to_f64(), g_out[3 * p + 1].to_f64(), g_out[3 * p + 2].to_f64()];
            Some((ev, kdp, metal, go))
        };
        let spec = self.effects.specular;
        if let Some(gkd) = grads[0].as_deref_mut() {
            gkd.par_chunks_mut(3).enumerate().for_each(|(p, gp)| {
                let Some((ev, _, metal, go)) = eval(p) else { return };
                for c in 0..3 {
                    let spec_part = if spec { ev.p[c] * metal * ev.ab[0] } else { 0.0 };
                    gp[c] += T::from_f64(go[c] * ((1.0 - metal) * ev.e[c] + spec_part));
                }
            });
        }
        if let Some(gks) = grads[1].as_deref_mut() {
            gks.par_chunks_mut(3).enumerate().for_each(|(p, gp)| {
                let Some((ev, kdp, metal, go)) = eval(p) else { return };
                let (mut gr, mut gm) = (0.0, 0.0);
                for c in 0..3 {
                    gm -= go[c] * kdp[c] * ev.e[c];
                    if spec {
                        let f0 = F0_DIELECTRIC + (kdp[c] - F0_DIELECTRIC) * metal;
                        gm += go[c] * ev.p[c] * (kdp[c] - F0_DIELECTRIC) * ev.ab[0];
                        gr += go[c] * (ev.dp[c] * (f0 * ev.ab[0] + ev.ab[1]) + ev.p[c] * (f0 * ev.dab[0] + ev.dab[1]));
                    }
                }
                gp[1] += T::from_f64(gr);
                gp[2] += T::from_f64(gm);
            });
        }
        if let Some(glight) = grads[2].as_deref_mut() {
            // One flat buffer: the specular levels, then the diffuse map; pixels scatter into it
            // with their lookup taps (race-free bands), then the light's transpose takes over.
            let sizes: Vec<usize> = levels.specular.iter().map(Vec::len).chain([levels.diffuse.len()]).collect();
            let offsets: Vec<usize> = sizes.iter().scan(0, |acc, &s| Some(std::mem::replace(acc, *acc + s))).collect();
            let mut flat = vec![0.0f64; sizes.iter().sum()];
            let dif = offsets[offsets.len() - 1];
            scatter_add_banded(&mut flat, self.pixels.len(), |p, sink| {
                let Some((ev, kdp, metal, go)) = eval(p) else { return };
                let Some(geom) = self.pixels[p].as_ref() else { return };
                for (k, w) in geom.diffuse_taps.iter() {
                    for c in 0..3 {
                        sink.add(dif + 3 * k + c, w as f64 * go[c] * kdp[c] * (1.0 - metal));
                    }
                }
                if !spec {
                    return;
                }
                let (l0, l1, t) = ev.levels;
                for c in 0..3 {
                    let f0 = F0_DIELECTRIC + (kdp[c] - F0_DIELECTRIC) * metal;
                    let gp = go[c] * (f0 * ev.ab[0] + ev.ab[1]);
                    for (k, w) in ev.taps.0.iter() {
                        sink.add(offsets[l0] + 3 * k + c, (1.0 - t) * w as f64 * gp);
                    }
                    if t != 0.0 {
                        for (k, w) in ev.taps.1.iter() {
                            sink.add(offsets[l1] + 3 * k + c, t * w as f64 * gp);
                        }
                    }
                }
            });
            let g_spec: Vec<Vec<f64>> = (0..levels.specular.len()).map(|k| flat[offsets[k]..offsets[k] + sizes[k]].to_vec()).collect();
            let g_base = self.light.backward(&g_spec, &flat[dif..]);
            glight.par_iter_mut().zip(g_base.par_iter()).for_each(|(a, b)| *a += T::from_f64(*b));
        }
        Ok(())
    }
}

/// Split-sum radiance [N, 3] of `kd` [N, 3], `ks` [N, 3] = (occlusion, roughness, metallic) under
/// the base cube map `light` [6, R, R, 3], on the tape.
pub fn shade_splitsum(op: &SplitSumShading, kd: &Tensor, ks: &Tensor, light: &Tensor) -> Result<Tensor> {
    apply(op.clone(), &[kd, ks, light])
}

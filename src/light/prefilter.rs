//! The split-sum environment light (docs/model.md, *Shading*), following NVDiffRec's scheme:
//!
//! - a mip chain of the base cube map by 2×2 averaging, down to 16² texels;
//! - mip level k < n−1 is prefiltered with a GGX lobe of roughness 0.08 + k/(n−2)·(0.5 − 0.08), the
//!   last (16²) level with roughness 1; a lookup interpolates between the two levels around the
//!   roughness (NVDiffRec's `get_mip`);
//! - the lobe assumes n = v = r (the reflected direction), so a source direction L gets the weight
//!   (L·r)·D(h)/4 · Ω(L), h = (L + r)/|L + r| — the density of GGX-sampled L times Karis' n·l —
//!   normalised by the sum of the weights, so a constant light stays exactly constant;
//! - diffuse irradiance is the cosine-weighted mean of the 16² level (∫L cos dω/π, normalised by
//!   the discrete ∑cos·Ω ≈ π), so a white Lambert surface under a constant L receives L.
//!
//! Cost control (a 6×512² base would take minutes naively): the kernel is cut where the lobe holds
//! `kernel_mass` of its weight (NVDiffRec cuts at a similar cone, about 92 % of the mass for small
//! α), candidate source texels are found by hierarchical tile culling against the cone, the inner
//! loop runs branch-free over 4×4 texel tiles stored as 16 SIMD lanes, and each level reads the
//! coarsest mip whose texels still resolve the lobe core (`texels_per_core` texels across the angle
//! where D falls to ¼). The last point differs from NVDiffRec, which filters every level from
//! itself: e.g. with a 512² base the 256² level (roughness 0.185) reads the 64² mip, so its kernel
//! is GGX convolved with a box at most ¼ of the lobe core wide (tests compare with brute force).
//! Measured (`cargo test --release --test light_splitsum measure -- --ignored --nocapture`) on the
//! shared 2-core machine under a load of ~5 from other jobs, kernel mass 0.9 / 0.95 / 0.99:
//! 6×128² base 0.12 / 0.16 / 0.36 s, 6×256² 0.66 / 0.90 / 2.1 s, 6×512² 4.9 / 8.3 / 32 s — the
//! 512² case is dominated by the roughness-0.08 level filtered at full resolution (7.5 s of 8.3).
//!
//! Every step is a fixed linear map of the base texels (weights depend only on geometry and
//! roughness), so a backward pass is its transpose.

use glam::Vec3;
use rayon::prelude::*;

use crate::light::cubemap::{face_dir, face_solid_angles, texel_dir, CubeMap};
use crate::material::brdf::{alpha_from_roughness, MIN_ROUGHNESS};

/// The mip chain stops at this resolution (NVDiffRec's `LIGHT_MIN_RES`).
pub const LIGHT_MIN_RES: usize = 16;
/// Roughness of the second-to-last specular level.
pub const MAX_ROUGHNESS: f32 = 0.5;

/// Accuracy/cost knobs of the specular prefilter.
#[derive(Clone, Copy, Debug)]
pub struct PrefilterOptions {
    /// Fraction of the GGX lobe's weight inside the cut-off cone.
    pub kernel_mass: f32,
    /// Minimum number of source texels across the lobe core when picking a coarser source mip.
    pub texels_per_core: f32,
}

impl Default for PrefilterOptions {
    fn default() -> Self {
        PrefilterOptions { kernel_mass: 0.95, texels_per_core: 4.0 }
    }
}

/// Prefiltered specular levels and the diffuse irradiance map of one environment light.
#[derive(Clone, Debug)]
pub struct SplitSumLight {
    /// Level k has resolution base/2^k; the last one is 16² (or the base when it is that small).
    pub specular: Vec<CubeMap>,
    /// The GGX roughness each specular level was filtered with.
    pub level_roughness: Vec<f32>,
    /// Cosine-convolved radiance (irradiance/π) at the 16² level.
    pub diffuse: CubeMap,
}

/// The base map followed by 2×2 averages down to 16². A base of 16² or less (or of odd size)
/// gets a copy of itself as second level so there is always a level for roughness 1.
pub fn mip_chain(base: &CubeMap) -> Vec<CubeMap> {
    let mut chain = vec![base.clone()];
    loop {
        let last = &chain[chain.len() - 1];
        if last.res <= LIGHT_MIN_RES || last.res % 2 != 0 {
            break;
        }
        let next = last.downsample();
        chain.push(next);
    }
    if chain.len() == 1 {
        chain.push(base.clone());
    }
    chain
}

/// Roughness of each of `n` specular levels: 0.08 … 0.5 evenly, then 1.0 for the last.
pub fn level_roughness(n: usize) -> Vec<f32> {
    (0..n)
        .map(|k| {
            if k + 1 == n {
                1.0
            } else if n <= 2 {
                MIN_ROUGHNESS
            } else {
                MIN_ROUGHNESS + (k as f32 / (n - 2) as f32) * (MAX_ROUGHNESS - MIN_ROUGHNESS)
            }
        })
        .collect()
}

/// Fractional mip level for a roughness with `n` levels (NVDiffRec's `get_mip`).
pub fn mip_level_for_roughness(roughness: f32, n: usize) -> f32 {
    let r = if roughness.is_nan() { MIN_ROUGHNESS } else { roughness };
    let n2 = n.saturating_sub(2) as f32;
    if r < MAX_ROUGHNESS {
        (r.clamp(MIN_ROUGHNESS, MAX_ROUGHNESS) - MIN_ROUGHNESS) / (MAX_ROUGHNESS - MIN_ROUGHNESS) * n2
    } else {
        (r.clamp(MAX_ROUGHNESS, 1.0) - MAX_ROUGHNESS) / (1.0 - MAX_ROUGHNESS) + n2
    }
}

/// Prefilter weight of source direction `l` for lobe direction `r` (both unit): (l·r)·D(h)/4.
/// Written with s = sin²θ_h = |l − r|²/4, which stays accurate when l ≈ r and α is tiny.
pub fn ggx_lobe_weight(l: Vec3, r: Vec3, alpha: f32) -> f32 {
    let s = (l - r).length_squared() * 0.25;
    let cos_lr = 1.0 - 2.0 * s;
    if cos_lr <= 0.0 {
        return 0.0;
    }
    let a2 = alpha * alpha;
    let d = a2 * (1.0 - s) + s;
    cos_lr * a2 / (std::f32::consts::PI * d * d) * 0.25
}

/// sin²θ_h of the cut-off cone holding `mass` of the GGX lobe: the fraction of D(h)(n·h) inside
/// θ_h is tan²θ_h/(α² + tan²θ_h). Capped at ½ (l·r = 0, where the weight vanishes anyway).
pub fn lobe_cutoff_sin2(alpha: f32, mass: f32) -> f32 {
    let m = mass.clamp(0.0, 0.999_999);
    let tan2 = alpha * alpha * m / (1.0 - m);
    (tan2 / (1.0 + tan2)).min(0.5)
}

/// A block of texels on one face and the cone (centre, angular radius) that contains it.
struct Tile {
    face: usize,
    i0: usize,
    i1: usize,
    j0: usize,
    j1: usize,
    centre: Vec3,
    radius: f32,
}

fn make_tiles(res: usize, size: usize) -> Vec<Tile> {
    let size = size.min(res).max(1);
    let edge = |k: usize| 2.0 * k as f32 / res as f32 - 1.0;
    let mut tiles = Vec::new();
    for face in 0..6 {
        for i0 in (0..res).step_by(size) {
            for j0 in (0..res).step_by(size) {
                let (i1, j1) = ((i0 + size).min(res), (j0 + size).min(res));
                let (s0, s1, t0, t1) = (edge(j0), edge(j1), edge(i0), edge(i1));
                let centre = face_dir(face, 0.5 * (s0 + s1), 0.5 * (t0 + t1)).normalize();
                // The tile is a convex spherical quadrilateral: its farthest point is a corner.
                let radius = [(s0, t0), (s0, t1), (s1, t0), (s1, t1)]
                    .iter()
                    .map(|&(s, t)| centre.dot(face_dir(face, s, t).normalize()).clamp(-1.0, 1.0).acos())
                    .fold(0.0f32, f32::max);
                tiles.push(Tile { face, i0, i1, j0, j1, centre, radius });
            }
        }
    }
    tiles
}

/// Side of the source tiles and the number of texels (lanes) in one.
const TILE_SIDE: usize = 4;
const LANES: usize = TILE_SIDE * TILE_SIDE;

/// One source tile's texels: directions, solid angles, flat texel indices and RGB values, lane k =
/// texel k of the tile (padding lanes have zero solid angle, hence zero weight).
struct TileLanes {
    x: [f32; LANES],
    y: [f32; LANES],
    z: [f32; LANES],
    area: [f32; LANES],
    index: [u32; LANES],
    value: [[f32; LANES]; 3],
}

/// Source tiles packed as structure-of-arrays lanes so the inner loops vectorise; `values` may be
/// absent when only the weights are wanted (stencils).
fn pack_tiles(sres: usize, src_tiles: &[Tile], values: Option<&[Vec3]>) -> Vec<TileLanes> {
    let src_area = face_solid_angles(sres);
    src_tiles
        .iter()
        .map(|st| {
            let mut lanes = TileLanes {
                x: [0.0; LANES],
                y: [0.0; LANES],
                z: [1.0; LANES],
                area: [0.0; LANES],
                index: [0; LANES],
                value: [[0.0; LANES]; 3],
            };
            for (k, (i, j)) in (st.i0..st.i1).flat_map(|i| (st.j0..st.j1).map(move |j| (i, j))).enumerate() {
                let d = texel_dir(sres, st.face, i, j);
                let idx = (st.face * sres + i) * sres + j;
                (lanes.x[k], lanes.y[k], lanes.z[k]) = (d.x, d.y, d.z);
                lanes.area[k] = src_area[i * sres + j];
                lanes.index[k] = idx as u32;
                if let Some(v) = values {
                    (lanes.value[0][k], lanes.value[1][k], lanes.value[2][k]) = (v[idx].x, v[idx].y, v[idx].z);
                }
            }
            lanes
        })
        .collect()
}

/// The culling shared by the filter and its stencils: for every output texel of an `out_res` map,
/// `row(r, fine)` gets the texel's direction r and the ids of the 4×4 source tiles (of
/// `make_tiles(sres, TILE_SIDE)`) that can reach it within `cone_angle`. Returns the rows in
/// output-texel order.
///
/// Culling is hierarchical: 8×8 output tiles keep the 32×32 and then the 4×4 source tiles that can
/// reach any of their texels, then each output texel keeps those that reach its own cone.
fn filter_rows<R: Send>(sres: usize, out_res: usize, cone_angle: f32, src_tiles: &[Tile], row: impl Fn(Vec3, &[usize]) -> R + Sync) -> Vec<R> {
    let per_tile = fold_rows(
        sres,
        out_res,
        cone_angle,
        src_tiles,
        |_| true,
        Vec::new,
        |acc: &mut Vec<(usize, R)>, o, r, fine| acc.push((o, row(r, fine))),
        |mut a, mut b| {
            a.append(&mut b);
            a
        },
    );
    let mut rows: Vec<Option<R>> = (0..6 * out_res * out_res).map(|_| None).collect();
    for (k, v) in per_tile {
        rows[k] = Some(v);
    }
    rows.into_iter().map(|r| r.expect("every output texel belongs to one output tile")).collect()
}

/// Parts the output tiles are folded in (one accumulator each): fixed, so results do not depend on
/// the thread count; 16 keeps 2–16 threads busy while the adjoint's source-sized buffers stay few
/// (16 × 6·64²·3 floats ≈ 5 MB at the default light resolution).
const FOLD_PARTS: usize = 16;

/// The culling core: visits every output texel that `wanted` names (flat index o, direction r,
/// candidate source tiles) in parallel over 8×8 output tiles, folding into accumulators made by
/// `init` and combined in order by `reduce` ([`FOLD_PARTS`] contiguous parts: deterministic). An
/// output tile with no wanted texel is skipped before its culling.
#[allow(clippy::too_many_arguments)] // the culling's inputs, then the fold's three closures
fn fold_rows<A: Send>(
    sres: usize,
    out_res: usize,
    cone_angle: f32,
    src_tiles: &[Tile],
    wanted: impl Fn(usize) -> bool + Sync + Send,
    init: impl Fn() -> A + Sync + Send,
    visit: impl Fn(&mut A, usize, Vec3, &[usize]) + Sync + Send,
    reduce: impl Fn(A, A) -> A + Sync + Send,
) -> A {
    use std::f32::consts::PI;
    let out_tiles = make_tiles(out_res, 8);
    // cos of the reach of each source tile, per texel and (with the widest output tile) per tile.
    let cos_reach = |a: f32| if a >= PI { -2.0 } else { a.cos() };
    let widest_out = out_tiles.iter().map(|t| t.radius).fold(0.0f32, f32::max);
    let texel_reach: Vec<f32> = src_tiles.iter().map(|st| cos_reach(cone_angle + st.radius)).collect();
    let tile_reach: Vec<f32> = src_tiles.iter().map(|st| cos_reach(cone_angle + st.radius + widest_out)).collect();
    // 32×32 super-tiles group the 4×4 tiles so the per-output-tile culling does not grow as res⁴.
    const SUPER: usize = 32;
    let super_tiles = make_tiles(sres, SUPER);
    let supers_per_side = sres.div_ceil(SUPER);
    let mut groups = vec![Vec::new(); super_tiles.len()];
    for (t, st) in src_tiles.iter().enumerate() {
        groups[(st.face * supers_per_side + st.i0 / SUPER) * supers_per_side + st.j0 / SUPER].push(t);
    }
    let super_reach: Vec<f32> = super_tiles.iter().map(|st| cos_reach(cone_angle + st.radius + widest_out)).collect();
    // Fixed contiguous parts folded in parallel, then combined in order: the sums come out the same
    // bit for bit on every run and any thread count (rayon's `fold` splits where work is stolen,
    // so the adjoint's overlapping scatters would be summed in a varying order).
    let part_len = out_tiles.len().div_ceil(FOLD_PARTS).max(1);
    let parts: Vec<A> = out_tiles
        .par_chunks(part_len)
        .map(|part| part.iter().fold(init(), |mut acc, ot| {
            let texel = |i: usize, j: usize| (ot.face * out_res + i) * out_res + j;
            if !(ot.i0..ot.i1).any(|i| (ot.j0..ot.j1).any(|j| wanted(texel(i, j)))) {
                return acc;
            }
            let coarse: Vec<usize> = (0..super_tiles.len())
                .filter(|&g| ot.centre.dot(super_tiles[g].centre) >= super_reach[g])
                .flat_map(|g| groups[g].iter().copied())
                .filter(|&t| ot.centre.dot(src_tiles[t].centre) >= tile_reach[t])
                .collect();
            let mut fine = Vec::with_capacity(coarse.len());
            for i in ot.i0..ot.i1 {
                for j in ot.j0..ot.j1 {
                    if !wanted(texel(i, j)) {
                        continue;
                    }
                    let r = texel_dir(out_res, ot.face, i, j);
                    fine.clear();
                    fine.extend(coarse.iter().copied().filter(|&t| r.dot(src_tiles[t].centre) >= texel_reach[t]));
                    visit(&mut acc, texel(i, j), r, &fine);
                }
            }
            acc
        }))
        .collect();
    parts.into_iter().reduce(reduce).unwrap_or_else(init)
}

/// Adjoint of [`kernel_filter`] without storing its matrix: every output texel's normalised row is
/// recomputed (same culling, same weights) and `g_out` scattered through it into a source-sized
/// buffer per parallel job; the buffers are summed. Output texels with a zero gradient scatter
/// nothing, so their rows are not built: a training view's lookups reach only the part of each
/// level around its reflection directions (the skipped terms are exact zeros).
fn kernel_filter_adjoint(g_out: &CubeMap, sres: usize, cone_angle: f32, weight: impl Fn(Vec3, Vec3, f32) -> f32 + Sync) -> CubeMap {
    let src_tiles = make_tiles(sres, TILE_SIDE);
    let packed = pack_tiles(sres, &src_tiles, None);
    let n_src = 6 * sres * sres;
    let data = fold_rows(
        sres,
        g_out.res,
        cone_angle,
        &src_tiles,
        |o| g_out.data[o] != Vec3::ZERO,
        || (vec![Vec3::ZERO; n_src], Vec::<[f32; LANES]>::new()),
        |(acc, row_w), o, r, fine| {
            // The row's weights once (lanes, vectorised), then normalise and scatter.
            row_w.clear();
            let mut wsum = [0.0f32; LANES];
            for &t in fine {
                let p = &packed[t];
                let mut w = [0.0f32; LANES];
                for k in 0..LANES {
                    w[k] = weight(Vec3::new(p.x[k], p.y[k], p.z[k]), r, p.area[k]);
                    wsum[k] += w[k];
                }
                row_w.push(w);
            }
            let wsum: f32 = wsum.iter().sum();
            if wsum <= 0.0 {
                return;
            }
            let g = g_out.data[o] / wsum;
            for (&t, w) in fine.iter().zip(row_w.iter()) {
                let p = &packed[t];
                for k in 0..LANES {
                    if w[k] > 0.0 {
                        acc[p.index[k] as usize] += g * w[k];
                    }
                }
            }
        },
        |(mut a, buf), (b, _)| {
            a.iter_mut().zip(b).for_each(|(x, y)| *x += y);
            (a, buf)
        },
    )
    .0;
    CubeMap { res: sres, data }
}

/// Normalised kernel filter: output texel r of an `out_res` map gets ∑ w(l, r)·src(l) / ∑ w(l, r)
/// over source texels l, where `weight(l, r, Ω_l)` already includes the solid angle and vanishes
/// beyond `cone_angle` from r.
fn kernel_filter(src: &CubeMap, out_res: usize, cone_angle: f32, weight: impl Fn(Vec3, Vec3, f32) -> f32 + Sync) -> CubeMap {
    let src_tiles = make_tiles(src.res, TILE_SIDE);
    let packed = pack_tiles(src.res, &src_tiles, Some(&src.data));
    let data = filter_rows(src.res, out_res, cone_angle, &src_tiles, |r, fine| {
        // Per-lane accumulators: a float sum across lanes would block vectorisation.
        let (mut aw, mut ar, mut ag, mut ab) = ([0.0f32; LANES], [0.0f32; LANES], [0.0f32; LANES], [0.0f32; LANES]);
        for &t in fine {
            let p = &packed[t];
            for k in 0..LANES {
                // Branch-free: about half the candidates lie outside the cone, and a
                // mispredicted branch costs more than the multiply-adds.
                let w = weight(Vec3::new(p.x[k], p.y[k], p.z[k]), r, p.area[k]);
                aw[k] += w;
                ar[k] += w * p.value[0][k];
                ag[k] += w * p.value[1][k];
                ab[k] += w * p.value[2][k];
            }
        }
        let wsum: f32 = aw.iter().sum();
        let sum = Vec3::new(ar.iter().sum(), ag.iter().sum(), ab.iter().sum());
        if wsum > 0.0 {
            sum / wsum
        } else {
            Vec3::ZERO
        }
    });
    CubeMap { res: out_res, data }
}

/// A fixed linear map between two cube maps in sparse row form: output texel o (flat index) is
/// ∑ weight[e]·src[index[e]] over e ∈ offsets[o]..offsets[o+1], the same for each RGB channel.
/// The weights are the normalised ones of [`kernel_filter`], so applying the stencil reproduces
/// the filter (up to float summation order), and its transpose is the filter's adjoint.
#[derive(Clone, Debug)]
pub struct Stencil {
    pub src_res: usize,
    pub out_res: usize,
    pub offsets: Vec<usize>,
    pub index: Vec<u32>,
    pub weight: Vec<f32>,
}

impl Stencil {
    /// Entries (source texel, weight) of output texel `o`.
    pub fn row(&self, o: usize) -> impl Iterator<Item = (usize, f32)> + '_ {
        let (a, b) = (self.offsets[o], self.offsets[o + 1]);
        self.index[a..b].iter().zip(&self.weight[a..b]).map(|(&i, &w)| (i as usize, w))
    }

    pub fn nnz(&self) -> usize {
        self.index.len()
    }

    /// The transposed map (source ↔ output), entries of each row in increasing output order.
    pub fn transpose(&self) -> Stencil {
        let n_src = 6 * self.src_res * self.src_res;
        let mut counts = vec![0usize; n_src + 1];
        for &i in &self.index {
            counts[i as usize + 1] += 1;
        }
        for k in 0..n_src {
            counts[k + 1] += counts[k];
        }
        let offsets = counts.clone();
        let mut fill = counts;
        let mut index = vec![0u32; self.nnz()];
        let mut weight = vec![0.0f32; self.nnz()];
        for o in 0..self.offsets.len() - 1 {
            for (i, w) in self.row(o) {
                index[fill[i]] = o as u32;
                weight[fill[i]] = w;
                fill[i] += 1;
            }
        }
        Stencil { src_res: self.out_res, out_res: self.src_res, offsets, index, weight }
    }
}

/// The stencil of [`kernel_filter`] for a `sres`² source: same culling, same weights (zero ones
/// dropped), normalised per row.
fn kernel_stencil(sres: usize, out_res: usize, cone_angle: f32, weight: impl Fn(Vec3, Vec3, f32) -> f32 + Sync) -> Stencil {
    let src_tiles = make_tiles(sres, TILE_SIDE);
    let packed = pack_tiles(sres, &src_tiles, None);
    let rows = filter_rows(sres, out_res, cone_angle, &src_tiles, |r, fine| {
        let mut row: Vec<(u32, f32)> = Vec::new();
        for &t in fine {
            let p = &packed[t];
            // Weights of all lanes first (branch-free, vectorises), then keep the non-zero ones.
            let w: [f32; LANES] = std::array::from_fn(|k| weight(Vec3::new(p.x[k], p.y[k], p.z[k]), r, p.area[k]));
            row.extend((0..LANES).filter(|&k| w[k] > 0.0).map(|k| (p.index[k], w[k])));
        }
        let wsum: f32 = row.iter().map(|e| e.1).sum();
        row.iter_mut().for_each(|e| e.1 /= wsum);
        row
    });
    let mut offsets = Vec::with_capacity(rows.len() + 1);
    offsets.push(0);
    let (mut index, mut weight) = (Vec::new(), Vec::new());
    for row in rows {
        for (i, w) in row {
            index.push(i);
            weight.push(w);
        }
        offsets.push(index.len());
    }
    Stencil { src_res: sres, out_res, offsets, index, weight }
}

/// The GGX prefilter kernel of `roughness` for `kernel_mass`: its cut-off cone angle and weight.
fn specular_kernel(roughness: f32, kernel_mass: f32) -> (f32, impl Fn(Vec3, Vec3, f32) -> f32 + Sync) {
    let alpha = alpha_from_roughness(roughness);
    let sin2_cut = lobe_cutoff_sin2(alpha, kernel_mass);
    // θ_l = 2θ_h; a small slack covers the texel-centre test at the cone's rim.
    let cone = 2.0 * sin2_cut.sqrt().asin() + 1e-4;
    let a2 = alpha * alpha;
    let weight = move |l: Vec3, r: Vec3, area: f32| {
        // ggx_lobe_weight inlined without branches (s ≤ sin2_cut ≤ ½ implies l·r ≥ 0).
        let s = (l - r).length_squared() * 0.25;
        let d = a2 * (1.0 - s) + s;
        let w = (1.0 - 2.0 * s) * a2 / (std::f32::consts::PI * d * d) * 0.25 * area;
        if s <= sin2_cut {
            w
        } else {
            0.0
        }
    };
    (cone, weight)
}

/// Cone and weight of the cosine (irradiance) kernel.
const IRRADIANCE_CONE: f32 = std::f32::consts::FRAC_PI_2 + 1e-3;
fn irradiance_weight(l: Vec3, n: Vec3, area: f32) -> f32 {
    l.dot(n).max(0.0) * area
}

/// `src` convolved with the GGX lobe of `roughness` (n = v = r), sampled at `out_res`².
pub fn prefilter_specular(src: &CubeMap, out_res: usize, roughness: f32, kernel_mass: f32) -> CubeMap {
    let (cone, weight) = specular_kernel(roughness, kernel_mass);
    kernel_filter(src, out_res, cone, weight)
}

/// The linear map of [`prefilter_specular`] from a `src_res`² map, as a stencil.
pub fn prefilter_specular_stencil(src_res: usize, out_res: usize, roughness: f32, kernel_mass: f32) -> Stencil {
    let (cone, weight) = specular_kernel(roughness, kernel_mass);
    kernel_stencil(src_res, out_res, cone, weight)
}

/// Adjoint of [`prefilter_specular`] from a `src_res`² source: ∂L/∂src from ∂L/∂out, matrix-free.
pub fn prefilter_specular_adjoint(g_out: &CubeMap, src_res: usize, roughness: f32, kernel_mass: f32) -> CubeMap {
    let (cone, weight) = specular_kernel(roughness, kernel_mass);
    kernel_filter_adjoint(g_out, src_res, cone, weight)
}

/// Adjoint of [`irradiance`], matrix-free.
pub fn irradiance_adjoint(g_out: &CubeMap) -> CubeMap {
    kernel_filter_adjoint(g_out, g_out.res, IRRADIANCE_CONE, irradiance_weight)
}

/// Cosine-weighted mean of the radiance over each output texel's hemisphere (= irradiance/π),
/// at the resolution of `src`.
pub fn irradiance(src: &CubeMap) -> CubeMap {
    kernel_filter(src, src.res, IRRADIANCE_CONE, irradiance_weight)
}

/// The linear map of [`irradiance`] on a `res`² map, as a stencil.
pub fn irradiance_stencil(res: usize) -> Stencil {
    kernel_stencil(res, res, IRRADIANCE_CONE, irradiance_weight)
}

/// Resolutions of [`mip_chain`] for a `base_res`² base (a repeated resolution is a copy).
pub fn mip_chain_res(base_res: usize) -> Vec<usize> {
    let mut res = vec![base_res];
    while let Some(&last) = res.last() {
        if last <= LIGHT_MIN_RES || last % 2 != 0 {
            break;
        }
        res.push(last / 2);
    }
    if res.len() == 1 {
        res.push(base_res);
    }
    res
}

/// Index of the coarsest chain level (not finer than `level`) whose texels still put
/// `texels_per_core` texels across the lobe core of `roughness`.
fn source_level(chain_res: &[usize], level: usize, roughness: f32, texels_per_core: f32) -> usize {
    let alpha = alpha_from_roughness(roughness);
    // L-angle where tanθ_h = α (D has fallen to ¼ of its peak), on both sides of the centre.
    let core = 4.0 * alpha.atan();
    let mut best = level;
    for (k, &res) in chain_res.iter().enumerate().skip(level) {
        let texel_angle = 2.0 / res as f32;
        if texel_angle * texels_per_core <= core {
            best = k;
        }
    }
    best
}

/// For each specular level of a chain with resolutions `chain_res`: the chain level it is
/// filtered from (see the module doc).
pub fn specular_sources(chain_res: &[usize], opts: PrefilterOptions) -> Vec<usize> {
    let roughness = level_roughness(chain_res.len());
    (0..chain_res.len()).map(|k| source_level(chain_res, k, roughness[k], opts.texels_per_core)).collect()
}

impl SplitSumLight {
    pub fn new(base: &CubeMap) -> Self {
        Self::with_options(base, PrefilterOptions::default())
    }

    pub fn with_options(base: &CubeMap, opts: PrefilterOptions) -> Self {
        let chain = mip_chain(base);
        let roughness = level_roughness(chain.len());
        let diffuse = irradiance(&chain[chain.len() - 1]);
        let chain_res: Vec<usize> = chain.iter().map(|m| m.res).collect();
        let specular = specular_sources(&chain_res, opts)
            .into_iter()
            .enumerate()
            .map(|(k, src)| prefilter_specular(&chain[src], chain[k].res, roughness[k], opts.kernel_mass))
            .collect();
        SplitSumLight { specular, level_roughness: roughness, diffuse }
    }

    /// Fractional specular level used for `roughness`.
    pub fn mip_level(&self, roughness: f32) -> f32 {
        mip_level_for_roughness(roughness, self.specular.len())
    }

    /// Prefiltered radiance around the reflected direction, interpolated between the two levels
    /// that bracket the roughness (bilinear within each level).
    pub fn specular(&self, refl_dir: Vec3, roughness: f32) -> Vec3 {
        let m = self.mip_level(roughness).clamp(0.0, (self.specular.len() - 1) as f32);
        let l0 = m.floor() as usize;
        let t = m - l0 as f32;
        let a = self.specular[l0].lookup(refl_dir);
        if t <= 0.0 || l0 + 1 >= self.specular.len() {
            return a;
        }
        a * (1.0 - t) + self.specular[l0 + 1].lookup(refl_dir) * t
    }

    /// Irradiance/π around `normal`: multiply by the diffuse albedo to get outgoing radiance.
    pub fn diffuse(&self, normal: Vec3) -> Vec3 {
        self.diffuse.lookup(normal)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn chain_and_level_roughness_follow_nvdiffrec() {
        let chain = mip_chain(&CubeMap::constant(128, Vec3::ONE));
        assert_eq!(chain.iter().map(|m| m.res).collect::<Vec<_>>(), vec![128, 64, 32, 16]);
        let r = level_roughness(4);
        assert!((r[0] - 0.08).abs() < 1e-6 && (r[1] - 0.29).abs() < 1e-6 && (r[2] - 0.5).abs() < 1e-6 && r[3] == 1.0);
        // get_mip inverts the level roughness, and is monotone.
        for (k, &rk) in r.iter().enumerate() {
            assert!((mip_level_for_roughness(rk, 4) - k as f32).abs() < 1e-5);
        }
        assert_eq!(mip_level_for_roughness(0.0, 4), 0.0);
        assert_eq!(mip_level_for_roughness(7.0, 4), 3.0);
        assert_eq!(mip_chain(&CubeMap::constant(8, Vec3::ONE)).len(), 2);
    }

    #[test]
    fn cutoff_cone_holds_the_requested_mass() {
        // Quadrature of D(h)(n·h) over θ_h ∈ [0, θ_cut] vs the closed form.
        let alpha = 0.2f32;
        let s2 = lobe_cutoff_sin2(alpha, 0.9);
        let cut = s2.sqrt().asin() as f64;
        let n = 200000;
        let a2 = (alpha * alpha) as f64;
        let mut inside = 0.0;
        for k in 0..n {
            let th = cut * (k as f64 + 0.5) / n as f64;
            let c = th.cos();
            let d = a2 * c * c + th.sin().powi(2);
            inside += a2 / (std::f64::consts::PI * d * d) * c * th.sin() * 2.0 * std::f64::consts::PI * cut / n as f64;
        }
        assert!((inside - 0.9).abs() < 1e-3, "{inside}");
    }

    #[test]
    fn the_adjoint_of_a_sparse_gradient_equals_the_transpose() {
        // A view's lookups touch a few texels of each level: the adjoint skips the rest (whole
        // output tiles and single texels), which must change nothing.
        use crate::rng::Sampler;
        let mut rng = Sampler::from_seed(21);
        let st = prefilter_specular_stencil(32, 16, 0.2, 0.95);
        let t = st.transpose();
        let mut g = CubeMap::constant(16, Vec3::ZERO);
        for (o, v) in g.data.iter_mut().enumerate() {
            // One face and a scatter of single texels elsewhere.
            if o / 256 == 2 || rng.next_f32() < 0.03 {
                *v = Vec3::new(rng.next_f32() - 0.5, rng.next_f32(), 2.0 * rng.next_f32());
            }
        }
        let adjoint = prefilter_specular_adjoint(&g, 32, 0.2, 0.95);
        let via_t: Vec<Vec3> = (0..6 * 32 * 32).map(|i| t.row(i).map(|(o, w)| g.data[o] * w).sum()).collect();
        let scale = via_t.iter().map(|v| v.abs().max_element()).fold(0.0f32, f32::max);
        assert!(scale > 0.0);
        for (a, b) in adjoint.data.iter().zip(&via_t) {
            assert!((*a - *b).abs().max_element() < 1e-5 * scale, "{a} vs {b}");
        }
        let zero = prefilter_specular_adjoint(&CubeMap::constant(16, Vec3::ZERO), 32, 0.2, 0.95);
        assert!(zero.data.iter().all(|v| *v == Vec3::ZERO));
    }

    #[test]
    fn stencils_reproduce_the_filters_and_transpose_exactly() {
        use crate::rng::Sampler;
        let mut rng = Sampler::from_seed(9);
        let mut src = CubeMap::constant(16, Vec3::ZERO);
        for v in src.data.iter_mut() {
            *v = Vec3::new(rng.next_f32(), rng.next_f32(), 4.0 * rng.next_f32());
        }
        let apply = |st: &Stencil, m: &CubeMap| -> Vec<Vec3> {
            (0..6 * st.out_res * st.out_res).map(|o| st.row(o).map(|(i, w)| m.data[i] * w).sum()).collect()
        };
        for (st, reference) in [
            (prefilter_specular_stencil(16, 8, 0.3, 0.95), prefilter_specular(&src, 8, 0.3, 0.95)),
            (irradiance_stencil(16), irradiance(&src)),
        ] {
            let got = apply(&st, &src);
            for (a, b) in got.iter().zip(&reference.data) {
                assert!((*a - *b).abs().max_element() < 1e-5 * b.abs().max_element().max(1.0), "{a} vs {b}");
            }
            // Transpose: the same entries, seen from the source side; the matrix-free adjoint agrees.
            let t = st.transpose();
            let mut g = CubeMap::constant(st.out_res, Vec3::ZERO);
            for v in g.data.iter_mut() {
                *v = Vec3::new(rng.next_f32() - 0.5, rng.next_f32(), 2.0 * rng.next_f32());
            }
            let adjoint = if st.out_res == 8 { prefilter_specular_adjoint(&g, 16, 0.3, 0.95) } else { irradiance_adjoint(&g) };
            let via_t = apply(&t, &g);
            let scale = via_t.iter().map(|v| v.abs().max_element()).fold(0.0f32, f32::max);
            for (a, b) in adjoint.data.iter().zip(&via_t) {
                assert!((*a - *b).abs().max_element() < 1e-5 * scale, "{a} vs {b}");
            }
            assert_eq!(t.nnz(), st.nnz());
            let mut rng = Sampler::from_seed(4);
            for _ in 0..50 {
                let o = (rng.next_f32() * (6 * st.out_res * st.out_res) as f32) as usize;
                for (i, w) in st.row(o) {
                    assert!(t.row(i).any(|(o2, w2)| o2 == o && w2 == w));
                }
            }
        }
        assert_eq!(mip_chain_res(128), vec![128, 64, 32, 16]);
        assert_eq!(mip_chain_res(8), vec![8, 8]);
        assert_eq!(mip_chain_res(24), vec![24, 12]);
        assert_eq!(mip_chain(&CubeMap::constant(24, Vec3::ONE)).iter().map(|m| m.res).collect::<Vec<_>>(), vec![24, 12]);
    }
}

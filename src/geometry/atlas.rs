//! A UV atlas for one shared kd/ks texture pair over the whole mesh.
//!
//! The mesh's own UVs serve when every part has them, they stay inside [0,1]² and no two
//! triangles cover the same texel. Otherwise (the hotdog: parts without UVs, several parts on the
//! same UV square) an atlas is generated: charts of connected triangles with similar normals,
//! each projected onto the plane of its average normal, scaled to one common texel density and
//! packed on shelves with padding so that bilinear lookups never reach a neighbouring chart.
//! A chart whose projection flips a triangle is halved; one that folds over itself (a
//! reconstructed mesh's small creases) hands the triangles that land on its own earlier ones to a
//! chart of their own; both repeat until no texel is covered twice.

use std::collections::HashMap;

use anyhow::{bail, Result};
use glam::{Vec2, Vec3};
use rayon::prelude::*;

use crate::geometry::Mesh;
use crate::math::Frame;

/// Grid on which `own_uvs_problem` looks for texels covered twice.
const OVERLAP_GRID: usize = 1024;
/// A texel centre closer than this (in texels) to a triangle edge counts for neither side, so
/// triangles that merely share an edge never count as overlapping.
const EDGE_TOLERANCE: f32 = 1e-3;
/// Normal cone of a chart around its seed triangle (degrees). With the projection normal inside
/// the same cone, no triangle is tilted more than twice this against the projection plane.
const CHART_CONE_DEGREES: f32 = 35.0;
/// Charts larger than this are cut (large charts pack badly and drift in curvature).
const MAX_CHART_TRIANGLES: usize = 3000;
/// Rounds of projecting, splitting and packing before the atlas gives up. A chart whose
/// projection flips is halved per round, so log2(MAX_CHART_TRIANGLES) ≈ 12 rounds bring it down to
/// single triangles; a fold of k layers sheds one layer per round, and detaching layers changes
/// the packing's texel size, which can reveal a fold too small to cover a texel before (the
/// default scene's reconstructed mesh needed 9 rounds). Twice the halving's count leaves room for both.
const SPLIT_ROUNDS: usize = 24;
/// Empty texels around every chart's content; two neighbours are 2·PADDING apart.
pub const PADDING: usize = 2;
/// Fraction of the atlas the charts' triangles should cover when the packing allows it.
const TARGET_FILL: f32 = 0.68;

#[derive(Clone, Debug, PartialEq)]
pub enum AtlasSource {
    /// The mesh's own UVs (valid and non-overlapping) are used unchanged.
    OwnUvs,
    /// Charts were built and packed by this module; `reason` says why the own UVs could not serve.
    Generated { reason: String, charts: usize },
}

/// Measured properties of an atlas (generated or own).
#[derive(Clone, Debug, Default)]
pub struct AtlasStats {
    /// Fraction of the atlas square covered by triangles.
    pub utilisation: f32,
    /// Over charts with non-zero 3D area: max / min of (UV area / 3D area). 1 = uniform density.
    pub area_ratio_spread: f32,
    /// Triangles with non-zero 3D area whose UV area is zero.
    pub zero_uv_area_triangles: usize,
    /// Texels per unit length (generated atlases only; 0 for own UVs).
    pub texels_per_unit: f32,
}

#[derive(Clone, Debug)]
pub struct Atlas {
    /// Same triangles in the same order and the same corner positions as the input; vertices are
    /// duplicated where a vertex lies on several charts; `uvs` are atlas UVs (OBJ convention).
    pub mesh: Mesh,
    pub source: AtlasSource,
    pub resolution: usize,
    pub stats: AtlasStats,
}

/// Why the mesh's own UVs cannot address one shared texture, or `None` when they can.
pub fn own_uvs_problem(mesh: &Mesh) -> Option<String> {
    if let Some(p) = mesh.parts.iter().find(|p| !p.has_uv) {
        return Some(format!("part {} has no UVs", p.name));
    }
    if let Some((i, uv)) = mesh.uvs.iter().enumerate().find(|(_, uv)| !uv.is_finite() || uv.min_element() < -1e-4 || uv.max_element() > 1.0 + 1e-4) {
        let part = mesh.triangles.iter().position(|t| t.contains(&(i as u32))).map(|t| mesh.parts[mesh.triangle_part[t] as usize].name.as_str());
        return Some(format!("UV {uv} of part {} lies outside [0,1]² (tiling)", part.unwrap_or("?")));
    }
    let flat = mesh.triangles.iter().enumerate().filter(|(t, tri)| mesh.face_normal_scaled(*t).length() > 0.0 && uv_area2(&mesh.uvs, **tri) == 0.0).count();
    if flat * 100 > mesh.triangles.len() {
        return Some(format!("{flat} of {} triangles have zero UV area", mesh.triangles.len()));
    }
    let owner: Vec<u32> = mesh.triangle_part.clone();
    let report = overlap_report(mesh, &owner, OVERLAP_GRID);
    let tolerance = 4 + report.covered / 10_000;
    if report.overlapping > tolerance {
        let (a, b) = report.first_pair.unwrap_or((0, 0));
        let (na, nb) = (&mesh.parts[a as usize].name, &mesh.parts[b as usize].name);
        let what = if a == b { format!("triangles of part {na} overlap each other") } else { format!("parts {na} and {nb} share UV space") };
        return Some(format!(
            "{what}: {} of {} covered texels (on a {OVERLAP_GRID}² grid) are covered twice",
            report.overlapping, report.covered
        ));
    }
    None
}

/// Twice the signed UV area of a triangle.
fn uv_area2(uvs: &[Vec2], [a, b, c]: [u32; 3]) -> f32 {
    let (a, b, c) = (uvs[a as usize], uvs[b as usize], uvs[c as usize]);
    (b - a).perp_dot(c - a)
}

struct OverlapReport {
    covered: usize,
    overlapping: usize,
    /// Owners involved in overlaps (each pair once, first owner, second owner).
    pairs: Vec<(u32, u32)>,
    first_pair: Option<(u32, u32)>,
    /// Triangles that cover a texel another triangle of the same owner covered first (in triangle
    /// order within a band): removing them leaves every owner free of overlaps with itself.
    self_overlapping: Vec<u32>,
}

/// Rasterise the UV triangles on a `res`² grid (texel centres strictly inside, by more than
/// EDGE_TOLERANCE) and count texels covered more than once. `owner[t]` labels triangle `t`
/// (part or chart) so that the report can name who overlaps whom.
fn overlap_report(mesh: &Mesh, owner: &[u32], res: usize) -> OverlapReport {
    let texel = |uv: Vec2| Vec2::new(uv.x * res as f32, (1.0 - uv.y) * res as f32);
    let tris: Vec<[Vec2; 3]> = mesh.triangles.iter().map(|t| t.map(|i| texel(mesh.uvs[i as usize]))).collect();
    let bands = band_lists(&tris, res, 0.0);
    // Per band: (covered texels, overlapping texels, owner pairs that overlap, later triangles of
    // overlaps within one owner).
    type BandCount = (usize, usize, Vec<(u32, u32)>, Vec<u32>);
    let results: Vec<BandCount> = bands
        .par_iter()
        .enumerate()
        .map(|(band, list)| {
            let y0 = band * BAND;
            let rows = BAND.min(res - y0);
            // The first triangle covering each texel.
            let mut first = vec![u32::MAX; rows * res];
            // A texel covered three times is one overlapping texel, not two.
            let mut counted = vec![false; rows * res];
            let (mut covered, mut overlapping, mut pairs, mut later) = (0, 0, Vec::new(), Vec::new());
            for &t in list {
                let [a, b, c] = tris[t as usize];
                let area2 = (b - a).perp_dot(c - a);
                if area2.abs() < 1e-12 {
                    continue;
                }
                let (lo, hi) = (a.min(b).min(c), a.max(b).max(c));
                let (x_lo, x_hi) = (lo.x.floor().max(0.0) as usize, (hi.x.ceil() as usize).min(res));
                let (y_lo, y_hi) = ((lo.y.floor().max(y0 as f32) as usize).max(y0), (hi.y.ceil() as usize).min(y0 + rows));
                let edges = [(b, c), (c, a), (a, b)].map(|(p, q)| (p, q, (q - p).length()));
                for y in y_lo..y_hi {
                    for x in x_lo..x_hi {
                        let p = Vec2::new(x as f32 + 0.5, y as f32 + 0.5);
                        // Signed distance to each edge, positive inside whatever the winding.
                        let inside = edges.iter().all(|&(e0, e1, len)| (e1 - e0).perp_dot(p - e0) * area2.signum() > EDGE_TOLERANCE * len);
                        if !inside {
                            continue;
                        }
                        let idx = (y - y0) * res + x;
                        let slot = &mut first[idx];
                        if *slot == u32::MAX {
                            *slot = t;
                            covered += 1;
                        } else {
                            if !counted[idx] {
                                counted[idx] = true;
                                overlapping += 1;
                            }
                            let pair = (owner[*slot as usize], owner[t as usize]);
                            if !pairs.contains(&pair) {
                                pairs.push(pair);
                            }
                            if pair.0 == pair.1 && *slot != t && later.last() != Some(&t) {
                                later.push(t);
                            }
                        }
                    }
                }
            }
            (covered, overlapping, pairs, later)
        })
        .collect();
    let mut report = OverlapReport { covered: 0, overlapping: 0, pairs: Vec::new(), first_pair: None, self_overlapping: Vec::new() };
    for (c, o, pairs, later) in results {
        report.covered += c;
        report.overlapping += o;
        for p in pairs {
            if !report.pairs.contains(&p) {
                report.pairs.push(p);
            }
        }
        report.self_overlapping.extend(later);
    }
    report.self_overlapping.sort_unstable();
    report.self_overlapping.dedup();
    report.first_pair = report.pairs.first().copied();
    report
}

/// Rows per band of the band-parallel rasterisers.
const BAND: usize = 16;

/// For each band of BAND rows, the triangles whose bounding box (grown by `reach` texels) meets it.
fn band_lists(tris: &[[Vec2; 3]], res: usize, reach: f32) -> Vec<Vec<u32>> {
    let n_bands = res.div_ceil(BAND);
    let mut bands = vec![Vec::new(); n_bands];
    for (t, [a, b, c]) in tris.iter().enumerate() {
        let (lo, hi) = (a.y.min(b.y).min(c.y) - reach, a.y.max(b.y).max(c.y) + reach);
        if !lo.is_finite() || !hi.is_finite() || hi < 0.0 || lo > res as f32 {
            continue;
        }
        let b0 = (lo.max(0.0) as usize / BAND).min(n_bands - 1);
        let b1 = (hi.max(0.0) as usize / BAND).min(n_bands - 1);
        for band in &mut bands[b0..=b1] {
            band.push(t as u32);
        }
    }
    bands
}

/// The surface point a texel shows: triangle, barycentrics of the closest point of that triangle
/// to the texel centre (in atlas UV space), and the distance in texels (0 inside).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TexelHit {
    pub triangle: u32,
    pub bary: Vec3,
    pub distance: f32,
}

/// For every texel of a `res`² atlas (row 0 at the top), the closest triangle within `reach`
/// texels (0 = only texel centres inside triangles). A `reach` of about 1.5 makes every texel
/// that a bilinear lookup inside a chart touches belong to that chart (conservative coverage).
pub fn texel_hits(mesh: &Mesh, res: usize, reach: f32) -> Vec<Option<TexelHit>> {
    let texel = |uv: Vec2| Vec2::new(uv.x * res as f32, (1.0 - uv.y) * res as f32);
    let tris: Vec<[Vec2; 3]> = mesh.triangles.iter().map(|t| t.map(|i| texel(mesh.uvs[i as usize]))).collect();
    let bands = band_lists(&tris, res, reach);
    let mut out = vec![None; res * res];
    out.par_chunks_mut(BAND * res).zip(bands.par_iter()).enumerate().for_each(|(band, (rows, list))| {
        let y0 = band * BAND;
        let n_rows = rows.len() / res;
        for &t in list {
            let [a, b, c] = tris[t as usize];
            let (lo, hi) = (a.min(b).min(c) - Vec2::splat(reach), a.max(b).max(c) + Vec2::splat(reach));
            let (x_lo, x_hi) = (lo.x.floor().max(0.0) as usize, (hi.x.ceil().max(0.0) as usize).min(res));
            let (y_lo, y_hi) = ((lo.y.floor().max(0.0) as usize).max(y0), (hi.y.ceil().max(0.0) as usize).min(y0 + n_rows));
            for y in y_lo..y_hi {
                for x in x_lo..x_hi {
                    let p = Vec2::new(x as f32 + 0.5, y as f32 + 0.5);
                    let (distance, bary) = closest_on_triangle(p, a, b, c);
                    if distance > reach {
                        continue;
                    }
                    let slot = &mut rows[(y - y0) * res + x];
                    if slot.is_none_or(|h: TexelHit| distance < h.distance) {
                        *slot = Some(TexelHit { triangle: t, bary, distance });
                    }
                }
            }
        }
    });
    out
}

/// Distance from `p` to triangle (a, b, c) and the barycentrics of the closest point.
/// Degenerate triangles are handled through their edges.
fn closest_on_triangle(p: Vec2, a: Vec2, b: Vec2, c: Vec2) -> (f32, Vec3) {
    let area2 = (b - a).perp_dot(c - a);
    if area2.abs() > 1e-12 {
        let wa = (c - b).perp_dot(p - b) / area2;
        let wb = (a - c).perp_dot(p - c) / area2;
        let wc = 1.0 - wa - wb;
        if wa >= 0.0 && wb >= 0.0 && wc >= 0.0 {
            return (0.0, Vec3::new(wa, wb, wc));
        }
    }
    let mut best = (f32::INFINITY, Vec3::X);
    for (i, j, e0, e1) in [(0, 1, a, b), (1, 2, b, c), (2, 0, c, a)] {
        let d = e1 - e0;
        let len2 = d.length_squared();
        let s = if len2 > 0.0 { ((p - e0).dot(d) / len2).clamp(0.0, 1.0) } else { 0.0 };
        let dist = (e0 + s * d - p).length();
        if dist < best.0 {
            let mut w = [0.0f32; 3];
            w[i] = 1.0 - s;
            w[j] = s;
            best = (dist, Vec3::from_array(w));
        }
    }
    best
}

/// The mesh with atlas UVs for a `resolution`² texture: its own UVs when they are valid,
/// otherwise a generated atlas.
pub fn build(mesh: &Mesh, resolution: usize) -> Result<Atlas> {
    if let Err(e) = mesh.validate() {
        bail!("cannot build a UV atlas for an invalid mesh: {e}");
    }
    if resolution < 16 {
        bail!("atlas resolution {resolution} is too small (need at least 16 texels)");
    }
    match own_uvs_problem(mesh) {
        None => {
            let stats = measure(mesh, &charts_of_parts(mesh), 0.0);
            Ok(Atlas { mesh: mesh.clone(), source: AtlasSource::OwnUvs, resolution, stats })
        }
        Some(reason) => generate(mesh, resolution, reason),
    }
}

fn charts_of_parts(mesh: &Mesh) -> Vec<Vec<u32>> {
    let mut charts = vec![Vec::new(); mesh.parts.len()];
    for (t, &p) in mesh.triangle_part.iter().enumerate() {
        charts[p as usize].push(t as u32);
    }
    charts
}

/// Utilisation, density spread and zero-area count of `mesh`'s UVs with the given charts.
fn measure(mesh: &Mesh, charts: &[Vec<u32>], texels_per_unit: f32) -> AtlasStats {
    let mut uv_total = 0.0f64;
    let (mut lo, mut hi) = (f32::INFINITY, 0.0f32);
    let mut zero = 0;
    for chart in charts {
        let (mut uv_area, mut area) = (0.0f64, 0.0f64);
        for &t in chart {
            let a3 = 0.5 * mesh.face_normal_scaled(t as usize).length() as f64;
            let a2 = 0.5 * uv_area2(&mesh.uvs, mesh.triangles[t as usize]).abs() as f64;
            if a3 > 0.0 && a2 == 0.0 {
                zero += 1;
            }
            uv_area += a2;
            area += a3;
        }
        uv_total += uv_area;
        if area > 0.0 && uv_area > 0.0 {
            let ratio = (uv_area / area) as f32;
            lo = lo.min(ratio);
            hi = hi.max(ratio);
        }
    }
    AtlasStats {
        utilisation: uv_total as f32,
        area_ratio_spread: if lo.is_finite() { hi / lo } else { 1.0 },
        zero_uv_area_triangles: zero,
        texels_per_unit,
    }
}

/// One chart after projection: 2D coordinates of its triangles' corners (same order as `tris`).
struct Projected {
    tris: Vec<u32>,
    corners: Vec<[Vec2; 3]>,
    size: Vec2,
}

fn generate(mesh: &Mesh, res: usize, reason: String) -> Result<Atlas> {
    let normals: Vec<Vec3> = (0..mesh.triangles.len()).map(|t| mesh.face_normal_scaled(t)).collect();
    let scale = mesh.bounds().map(|(lo, hi)| (hi - lo).length()).unwrap_or(1.0).max(1e-30);
    // Faces whose cross product vanishes relative to the mesh size have no usable normal.
    let degenerate: Vec<bool> = normals.iter().map(|n| n.length().is_nan() || n.length() <= 1e-12 * scale * scale).collect();
    let unit: Vec<Vec3> = normals.iter().zip(&degenerate).map(|(n, &d)| if d { Vec3::ZERO } else { n.normalize() }).collect();
    let neighbours = edge_neighbours(mesh);
    let mut charts = grow_charts(mesh, &unit, &degenerate, &neighbours);

    // Project, split charts whose projection flips or folds over itself, pack; repeat until clean.
    for _round in 0..SPLIT_ROUNDS {
        let projected: Vec<Projected> = charts.par_iter().map(|c| project(mesh, c, &normals, &degenerate)).collect();
        let flipped: Vec<usize> = projected
            .iter()
            .enumerate()
            .filter(|(_, p)| p.tris.iter().zip(&p.corners).any(|(&t, [a, b, c])| !degenerate[t as usize] && (*b - *a).perp_dot(*c - *a) <= 0.0))
            .map(|(i, _)| i)
            .collect();
        if !flipped.is_empty() {
            charts = split_charts(charts, &flipped);
            continue;
        }
        let area: f64 = normals.iter().map(|n| 0.5 * n.length() as f64).sum();
        let (texels_per_unit, origins) = pack(&projected, res, area)?;
        let out = assemble(mesh, &projected, &origins, texels_per_unit, res);
        let owner = {
            let mut owner = vec![0u32; mesh.triangles.len()];
            for (i, c) in charts.iter().enumerate() {
                for &t in c {
                    owner[t as usize] = i as u32;
                }
            }
            owner
        };
        let report = overlap_report(&out, &owner, res);
        if report.overlapping > 0 {
            // A chart that folds over itself gives the triangles that land on its own earlier
            // ones a chart of their own (the fold's upper layer, typically a few triangles), so
            // the rest stays whole; charts that overlap others (which packing should never cause)
            // are halved.
            let mut bad: Vec<usize> = report.pairs.iter().filter(|(a, b)| a != b).flat_map(|&(a, b)| [a as usize, b as usize]).collect();
            bad.sort_unstable();
            bad.dedup();
            charts = detach(split_charts(charts, &bad), &report.self_overlapping);
            continue;
        }
        let stats = measure(&out, &charts, texels_per_unit);
        return Ok(Atlas { mesh: out, source: AtlasSource::Generated { reason, charts: charts.len() }, resolution: res, stats });
    }
    bail!("UV atlas: charts still overlap after {SPLIT_ROUNDS} rounds of splitting (mesh with self-intersecting folds?)")
}

/// Triangles across each welded (by exact position) edge, for manifold edges of one part.
fn edge_neighbours(mesh: &Mesh) -> Vec<[u32; 3]> {
    let mut weld: HashMap<[u32; 3], u32> = HashMap::with_capacity(mesh.positions.len());
    let welded: Vec<u32> = mesh
        .positions
        .iter()
        .map(|p| {
            let n = weld.len() as u32;
            *weld.entry(p.to_array().map(f32::to_bits)).or_insert(n)
        })
        .collect();
    let mut edges: Vec<(u64, u32)> = Vec::with_capacity(mesh.triangles.len() * 3);
    for (t, tri) in mesh.triangles.iter().enumerate() {
        for k in 0..3 {
            let (a, b) = (welded[tri[k] as usize], welded[tri[(k + 1) % 3] as usize]);
            if a != b {
                edges.push((((a.min(b) as u64) << 32) | a.max(b) as u64, t as u32));
            }
        }
    }
    edges.par_sort_unstable();
    let mut neighbours = vec![[u32::MAX; 3]; mesh.triangles.len()];
    let mut add = |t: u32, n: u32| {
        if let Some(slot) = neighbours[t as usize].iter_mut().find(|s| **s == u32::MAX) {
            *slot = n;
        }
    };
    let mut i = 0;
    while i < edges.len() {
        let mut j = i + 1;
        while j < edges.len() && edges[j].0 == edges[i].0 {
            j += 1;
        }
        // Only manifold edges inside one part join charts.
        if j - i == 2 {
            let (s, t) = (edges[i].1, edges[i + 1].1);
            if s != t && mesh.triangle_part[s as usize] == mesh.triangle_part[t as usize] {
                add(s, t);
                add(t, s);
            }
        }
        i = j;
    }
    neighbours
}

/// Flood fill over shared edges while a face stays within the normal cone of the chart's seed.
/// Growth is best-first by distance from the seed and stops once the nearest candidate lies
/// farther than `COMPACTNESS`·√(chart area): charts stay disc-like instead of long wavy strips
/// (a tube's top strip stays inside the cone for its whole length), which fill their boxes well.
/// Degenerate faces join whichever chart reaches them; leftovers share one point-sized chart.
fn grow_charts(mesh: &Mesh, unit: &[Vec3], degenerate: &[bool], neighbours: &[[u32; 3]]) -> Vec<Vec<u32>> {
    use std::cmp::Reverse;
    use std::collections::BinaryHeap;
    const COMPACTNESS: f32 = 1.0;
    let cos_cone = CHART_CONE_DEGREES.to_radians().cos();
    let centroid = |t: usize| mesh.triangle_positions(t).iter().sum::<Vec3>() / 3.0;
    let mut chart_of = vec![u32::MAX; mesh.triangles.len()];
    let mut charts: Vec<Vec<u32>> = Vec::new();
    let mut heap: BinaryHeap<(Reverse<u32>, u32)> = BinaryHeap::new();
    for seed in 0..mesh.triangles.len() {
        if chart_of[seed] != u32::MAX || degenerate[seed] {
            continue;
        }
        let id = charts.len() as u32;
        let (seed_normal, seed_centre) = (unit[seed], centroid(seed));
        let [p0, p1, p2] = mesh.triangle_positions(seed);
        // Slack of a few seed edges so that slivers can start a chart.
        let slack = 2.0 * (p1 - p0).length().max((p2 - p1).length()).max((p0 - p2).length());
        let mut members = vec![seed as u32];
        let mut area = 0.5 * mesh.face_normal_scaled(seed).length();
        chart_of[seed] = id;
        heap.clear();
        let push = |heap: &mut BinaryHeap<(Reverse<u32>, u32)>, t: usize| {
            for &n in &neighbours[t] {
                if n != u32::MAX {
                    // Non-negative f32 order equals the order of their bit patterns.
                    heap.push((Reverse((centroid(n as usize) - seed_centre).length().to_bits()), n));
                }
            }
        };
        push(&mut heap, seed);
        while let Some((Reverse(dist_bits), n)) = heap.pop() {
            if members.len() >= MAX_CHART_TRIANGLES || f32::from_bits(dist_bits) > COMPACTNESS * area.sqrt() + slack {
                break;
            }
            let n = n as usize;
            if chart_of[n] != u32::MAX {
                continue;
            }
            if degenerate[n] || unit[n].dot(seed_normal) >= cos_cone {
                chart_of[n] = id;
                members.push(n as u32);
                area += 0.5 * mesh.face_normal_scaled(n).length();
                push(&mut heap, n);
            }
        }
        charts.push(members);
    }
    let leftovers: Vec<u32> = (0..mesh.triangles.len() as u32).filter(|&t| chart_of[t as usize] == u32::MAX).collect();
    if !leftovers.is_empty() {
        charts.push(leftovers);
    }
    charts
}

/// Moves the triangles `moving` (sorted) out of their charts: those of each chart form a new chart
/// beside it. A chart left empty disappears.
fn detach(charts: Vec<Vec<u32>>, moving: &[u32]) -> Vec<Vec<u32>> {
    let mut out = Vec::with_capacity(charts.len() + moving.len().min(charts.len()));
    for c in charts {
        let (moved, kept): (Vec<u32>, Vec<u32>) = c.into_iter().partition(|t| moving.binary_search(t).is_ok());
        out.extend([kept, moved].into_iter().filter(|c| !c.is_empty()));
    }
    out
}

/// Cut each listed chart in two halves of its flood-fill order: a disc around the seed, and the
/// ring around that disc, whose bounding box is still the whole chart's (which is why folds are
/// detached, not halved: halving them again and again cost the default scene 3.5× in texel density).
fn split_charts(charts: Vec<Vec<u32>>, which: &[usize]) -> Vec<Vec<u32>> {
    let mut out = Vec::with_capacity(charts.len() + which.len());
    for (i, mut c) in charts.into_iter().enumerate() {
        if which.contains(&i) && c.len() > 1 {
            let rest = c.split_off(c.len() / 2);
            out.push(c);
            out.push(rest);
        } else {
            out.push(c);
        }
    }
    out
}

/// Planar projection onto the plane of the chart's area-weighted normal, translated to start at
/// the origin and turned so that it is at least as wide as it is tall (shelves pack better).
fn project(mesh: &Mesh, chart: &[u32], normals: &[Vec3], degenerate: &[bool]) -> Projected {
    let sum: Vec3 = chart.iter().map(|&t| normals[t as usize]).sum();
    let all_degenerate = chart.iter().all(|&t| degenerate[t as usize]);
    let mut corners: Vec<[Vec2; 3]> = if all_degenerate {
        // Faces without area get no texels: collapse them to one point.
        vec![[Vec2::ZERO; 3]; chart.len()]
    } else {
        let n = sum.try_normalize().unwrap_or(Vec3::Z);
        let s = Frame::from_normal(n).s;
        let t = n.cross(s);
        chart.iter().map(|&f| mesh.triangle_positions(f as usize).map(|p| Vec2::new(p.dot(s), p.dot(t)))).collect()
    };
    // Turn the chart so that its bounding box has minimal area (one side along a hull edge).
    let hull = convex_hull(corners.iter().flatten().copied().collect());
    let mut best = (f32::INFINITY, Vec2::X);
    for i in 0..hull.len() {
        let Some(dir) = (hull[(i + 1) % hull.len()] - hull[i]).try_normalize() else { continue };
        let (mut lo, mut hi) = (Vec2::splat(f32::INFINITY), Vec2::splat(f32::NEG_INFINITY));
        for p in &hull {
            let q = Vec2::new(p.dot(dir), dir.perp_dot(*p));
            lo = lo.min(q);
            hi = hi.max(q);
        }
        let area = (hi - lo).x * (hi - lo).y;
        if area < best.0 {
            best = (area, dir);
        }
    }
    let dir = best.1;
    // A rotation (x, y) -> (x·d + y·d⊥) keeps the winding.
    for tri in &mut corners {
        for p in tri.iter_mut() {
            *p = Vec2::new(p.dot(dir), dir.perp_dot(*p));
        }
    }
    let lo = corners.iter().flatten().fold(Vec2::splat(f32::INFINITY), |m, p| m.min(*p));
    let hi = corners.iter().flatten().fold(Vec2::splat(f32::NEG_INFINITY), |m, p| m.max(*p));
    let mut size = hi - lo;
    let turn = size.y > size.x;
    for tri in &mut corners {
        for p in tri.iter_mut() {
            let q = *p - lo;
            // A quarter turn keeps the winding: (x, y) -> (size.y - y, x).
            *p = if turn { Vec2::new(size.y - q.y, q.x) } else { q };
        }
    }
    if turn {
        size = Vec2::new(size.y, size.x);
    }
    Projected { tris: chart.to_vec(), corners, size }
}

/// Convex hull (Andrew's monotone chain), counter-clockwise, without collinear points.
fn convex_hull(mut points: Vec<Vec2>) -> Vec<Vec2> {
    points.retain(|p| p.is_finite());
    points.sort_by(|a, b| a.x.total_cmp(&b.x).then(a.y.total_cmp(&b.y)));
    points.dedup();
    if points.len() < 3 {
        return points;
    }
    let mut hull: Vec<Vec2> = Vec::with_capacity(points.len() + 1);
    for pass in 0..2 {
        let start = hull.len();
        let iter: Box<dyn Iterator<Item = &Vec2>> = if pass == 0 { Box::new(points.iter()) } else { Box::new(points.iter().rev()) };
        for &p in iter {
            while hull.len() >= start + 2 && (hull[hull.len() - 1] - hull[hull.len() - 2]).perp_dot(p - hull[hull.len() - 2]) <= 0.0 {
                hull.pop();
            }
            hull.push(p);
        }
        hull.pop();
    }
    hull
}

/// Choose a common texel density and shelf-pack the charts' padded boxes into `res`².
/// Returns texels per unit length and each chart's content origin in texels (row-down).
fn pack(charts: &[Projected], res: usize, total_area: f64) -> Result<(f32, Vec<Vec2>)> {
    let mut density = ((TARGET_FILL as f64 * (res * res) as f64 / total_area.max(1e-30)).sqrt()) as f32;
    let mut order: Vec<usize> = (0..charts.len()).collect();
    for _ in 0..200 {
        let boxes: Vec<(usize, usize)> = charts
            .iter()
            .map(|c| {
                let w = (c.size.x * density).ceil() as usize + 2 * PADDING;
                let h = (c.size.y * density).ceil() as usize + 2 * PADDING;
                (w, h)
            })
            .collect();
        order.sort_by_key(|&i| std::cmp::Reverse((boxes[i].1, boxes[i].0)));
        if let Some(origins) = skyline_pack(&boxes, &order, res) {
            return Ok((density, origins));
        }
        density *= 0.97;
    }
    bail!("UV atlas: {} charts do not fit a {res}² atlas even at low texel density", charts.len())
}

/// Skyline bottom-left packing: each box goes where its top edge ends lowest (then leftmost),
/// resting on the skyline of the boxes below. Returns content origins (box corner + PADDING).
fn skyline_pack(boxes: &[(usize, usize)], order: &[usize], res: usize) -> Option<Vec<Vec2>> {
    // Segments (x, height) in increasing x; segment i spans [x_i, x_{i+1}) (the last one to res).
    let mut sky: Vec<(usize, usize)> = vec![(0, 0)];
    let mut origins = vec![Vec2::ZERO; boxes.len()];
    for &i in order {
        let (w, h) = boxes[i];
        if w > res || h > res {
            return None;
        }
        let mut best: Option<(usize, usize, usize)> = None; // (top, x, first segment)
        for start in 0..sky.len() {
            let x = sky[start].0;
            if x + w > res {
                break;
            }
            let mut y = 0;
            let mut k = start;
            while k < sky.len() && sky[k].0 < x + w {
                y = y.max(sky[k].1);
                k += 1;
            }
            if y + h <= res && best.is_none_or(|(top, bx, _)| (y + h, x) < (top, bx)) {
                best = Some((y + h, x, start));
            }
        }
        let (top, x, start) = best?;
        origins[i] = Vec2::new((x + PADDING) as f32, (top - h + PADDING) as f32);
        // Replace the covered span [x, x + w) by one segment at `top`.
        let end_x = x + w;
        let mut k = start;
        let mut tail_height = None;
        while k < sky.len() && sky[k].0 < end_x {
            tail_height = Some(sky[k].1);
            k += 1;
        }
        let next_x = sky.get(k).map(|s| s.0).unwrap_or(res);
        let mut replacement = vec![(x, top)];
        if end_x < next_x {
            if let Some(th) = tail_height {
                replacement.push((end_x, th));
            }
        }
        sky.splice(start..k, replacement);
        sky.dedup_by(|b, a| a.1 == b.1);
    }
    Some(origins)
}

/// Shelf packing (kept as the simple reference the skyline packer is compared with in tests).
#[cfg(test)]
fn shelf_pack(boxes: &[(usize, usize)], order: &[usize], res: usize) -> Option<Vec<Vec2>> {
    let mut origins = vec![Vec2::ZERO; boxes.len()];
    let (mut x, mut y, mut shelf) = (0usize, 0usize, 0usize);
    for &i in order {
        let (w, h) = boxes[i];
        if w > res {
            return None;
        }
        if x + w > res {
            y += shelf;
            x = 0;
            shelf = 0;
        }
        if y + h > res {
            return None;
        }
        origins[i] = Vec2::new((x + PADDING) as f32, (y + PADDING) as f32);
        x += w;
        shelf = shelf.max(h);
    }
    Some(origins)
}

/// The output mesh: one vertex per (input vertex, chart) pair, atlas UVs in the OBJ convention.
fn assemble(mesh: &Mesh, charts: &[Projected], origins: &[Vec2], density: f32, res: usize) -> Mesh {
    let mut out = Mesh {
        positions: Vec::with_capacity(mesh.positions.len()),
        normals: Vec::with_capacity(mesh.positions.len()),
        uvs: Vec::with_capacity(mesh.positions.len()),
        triangles: mesh.triangles.clone(),
        triangle_part: mesh.triangle_part.clone(),
        parts: mesh.parts.iter().map(|p| crate::geometry::Part { has_uv: true, ..p.clone() }).collect(),
        materials: mesh.materials.clone(),
    };
    let mut remap: HashMap<(u32, u32), u32> = HashMap::with_capacity(mesh.positions.len() * 5 / 4);
    let r = res as f32;
    for (c, chart) in charts.iter().enumerate() {
        for (&t, corners) in chart.tris.iter().zip(&chart.corners) {
            for (k, corner) in corners.iter().enumerate() {
                let v = mesh.triangles[t as usize][k];
                let idx = *remap.entry((v, c as u32)).or_insert_with(|| {
                    let texel = origins[c] + *corner * density;
                    out.positions.push(mesh.positions[v as usize]);
                    out.normals.push(mesh.normals[v as usize]);
                    out.uvs.push(Vec2::new(texel.x / r, 1.0 - texel.y / r));
                    (out.positions.len() - 1) as u32
                });
                out.triangles[t as usize][k] = idx;
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn closest_point_inside_on_edge_and_outside() {
        let (a, b, c) = (Vec2::ZERO, Vec2::new(4.0, 0.0), Vec2::new(0.0, 4.0));
        let (d, w) = closest_on_triangle(Vec2::new(1.0, 1.0), a, b, c);
        assert_eq!(d, 0.0);
        assert!((w - Vec3::new(0.5, 0.25, 0.25)).abs().max_element() < 1e-6);
        // Below edge ab: closest point (2, 0), halfway between a and b.
        let (d, w) = closest_on_triangle(Vec2::new(2.0, -1.5), a, b, c);
        assert!((d - 1.5).abs() < 1e-6 && (w - Vec3::new(0.5, 0.5, 0.0)).abs().max_element() < 1e-6);
        // Degenerate triangle (a segment) still gives a distance.
        let (d, _) = closest_on_triangle(Vec2::new(1.0, 1.0), a, b, b);
        assert!((d - 1.0).abs() < 1e-6);
    }

    #[test]
    fn shelf_packing_never_overlaps_boxes() {
        let boxes: Vec<(usize, usize)> = (0..60).map(|i| (5 + (i * 7) % 23, 4 + (i * 11) % 17)).collect();
        let mut order: Vec<usize> = (0..boxes.len()).collect();
        order.sort_by_key(|&i| std::cmp::Reverse(boxes[i].1));
        let origins = shelf_pack(&boxes, &order, 128).expect("fits");
        let rect = |i: usize| {
            let o = origins[i] - Vec2::splat(PADDING as f32);
            (o.x as usize, o.y as usize, o.x as usize + boxes[i].0, o.y as usize + boxes[i].1)
        };
        for i in 0..boxes.len() {
            let (x0, y0, x1, y1) = rect(i);
            assert!(x1 <= 128 && y1 <= 128);
            for j in 0..i {
                let (u0, v0, u1, v1) = rect(j);
                assert!(x1 <= u0 || u1 <= x0 || y1 <= v0 || v1 <= y0, "boxes {i} and {j} overlap");
            }
        }
        assert!(shelf_pack(&boxes, &order, 32).is_none());
        // The skyline packer obeys the same rules, and refuses what cannot fit.
        let sky = skyline_pack(&boxes, &order, 128).expect("fits");
        assert!(skyline_pack(&boxes, &order, 32).is_none());
        for i in 0..boxes.len() {
            let r = |j: usize| {
                let o = sky[j] - Vec2::splat(PADDING as f32);
                (o.x as usize, o.y as usize, o.x as usize + boxes[j].0, o.y as usize + boxes[j].1)
            };
            let (x0, y0, x1, y1) = r(i);
            assert!(x1 <= 128 && y1 <= 128);
            for j in 0..i {
                let (u0, v0, u1, v1) = r(j);
                assert!(x1 <= u0 || u1 <= x0 || y1 <= v0 || v1 <= y0, "skyline boxes {i} and {j} overlap");
            }
        }
    }
}

//! A cube-map environment light (linear RGB radiance).
//!
//! Face order and orientation are OpenGL's (+x, −x, +y, −y, +z, −z), as NVDiffRec uses them. Texel
//! (i, j) of a face is row i, column j; its centre has face coordinates s = 2(j+½)/res − 1 (column)
//! and t = 2(i+½)/res − 1 (row), and looks along
//!
//! | face | direction ∝ |
//! |---|---|
//! | +x | ( 1, −t, −s) |
//! | −x | (−1, −t,  s) |
//! | +y | ( s,  1,  t) |
//! | −y | ( s, −1, −t) |
//! | +z | ( s, −t,  1) |
//! | −z | (−s, −t, −1) |
//!
//! Bilinear lookups blend across face seams: a tap that falls off a face is the adjacent face's
//! texel, and the one tap that falls off a cube corner is the mean of the three texels that meet
//! there, so the lookup is continuous everywhere. [`CubeMap::lookup_taps`] exposes the texels and
//! weights so a backward pass can scatter gradients with the same code path.

use glam::Vec3;
use rayon::prelude::*;

use crate::image::Image;
use crate::light::latlong;
use crate::math::floor_f32;

/// Face resolution of the cube map a given lat-long probe (a test probe, a dataset's training
/// probe) is converted to for rendering: the render job, the relighting evaluation and the
/// synthetic datasets' renders. 64² per face is the resolution of the learned light
/// (`FitConfig::light_res`), so a relit render and a training render filter light alike, and it
/// has 6 × 64² = 24 576 texels, 48 times the 32 × 16 of the NeRFactor test probes: the conversion
/// keeps all a probe holds.
pub const PROBE_CUBE_RES: usize = 64;

/// Six square faces of `res`² texels, face-major then row-major. Face order and orientation are
/// OpenGL's (+x, −x, +y, −y, +z, −z), in the dataset's world frame.
#[derive(Clone, Debug)]
pub struct CubeMap {
    pub res: usize,
    pub data: Vec<Vec3>,
}

/// Unnormalised direction of face coordinates (s, t) ∈ [−1, 1]² (may lie outside, on the face plane).
pub fn face_dir(face: usize, s: f32, t: f32) -> Vec3 {
    match face {
        0 => Vec3::new(1.0, -t, -s),
        1 => Vec3::new(-1.0, -t, s),
        2 => Vec3::new(s, 1.0, t),
        3 => Vec3::new(s, -1.0, -t),
        4 => Vec3::new(s, -t, 1.0),
        _ => Vec3::new(-s, -t, -1.0),
    }
}

/// The face a direction hits and its face coordinates (s, t) ∈ [−1, 1]².
/// Ties go to x, then y, then z. A zero or non-finite direction maps to the centre of +z, so a
/// stray NaN normal cannot index outside the map.
pub fn dir_to_face(d: Vec3) -> (usize, f32, f32) {
    if !d.is_finite() {
        return (4, 0.0, 0.0);
    }
    let a = d.abs();
    if a.x >= a.y && a.x >= a.z && a.x > 0.0 {
        if d.x > 0.0 {
            (0, -d.z / a.x, -d.y / a.x)
        } else {
            (1, d.z / a.x, -d.y / a.x)
        }
    } else if a.y >= a.z && a.y > 0.0 {
        if d.y > 0.0 {
            (2, d.x / a.y, d.z / a.y)
        } else {
            (3, d.x / a.y, -d.z / a.y)
        }
    } else if a.z > 0.0 {
        if d.z > 0.0 {
            (4, d.x / a.z, -d.y / a.z)
        } else {
            (5, -d.x / a.z, -d.y / a.z)
        }
    } else {
        (4, 0.0, 0.0)
    }
}

/// The face a direction hits and its texture coordinates (u, v) ∈ [0, 1]² (u along columns, v
/// along rows): u = (s+1)/2, v = (t+1)/2 of [`dir_to_face`].
pub fn dir_to_face_uv(d: Vec3) -> (usize, f32, f32) {
    let (face, s, t) = dir_to_face(d);
    (face, 0.5 * (s + 1.0), 0.5 * (t + 1.0))
}

/// Unit direction of texture coordinates (u, v) on `face` (inverse of [`dir_to_face_uv`]).
pub fn face_uv_to_dir(face: usize, u: f32, v: f32) -> Vec3 {
    face_dir(face, 2.0 * u - 1.0, 2.0 * v - 1.0).normalize()
}

/// Face coordinate of a texel centre.
fn texel_coord(k: usize, res: usize) -> f32 {
    2.0 * (k as f32 + 0.5) / res as f32 - 1.0
}

/// Unit direction through the centre of texel (row i, column j) of `face` at resolution `res`.
pub fn texel_dir(res: usize, face: usize, i: usize, j: usize) -> Vec3 {
    face_dir(face, texel_coord(j, res), texel_coord(i, res)).normalize()
}

/// Exact solid angle of texel (i, j) (the same on every face): the gnomonic rectangle
/// [s0, s1]×[t0, t1] on the plane at distance 1 subtends F(s1,t1) − F(s0,t1) − F(s1,t0) + F(s0,t0)
/// with F(s, t) = atan(s·t / √(1 + s² + t²)).
pub fn texel_solid_angle(res: usize, i: usize, j: usize) -> f32 {
    let f = |s: f64, t: f64| (s * t).atan2((1.0 + s * s + t * t).sqrt());
    let edge = |k: usize| 2.0 * k as f64 / res as f64 - 1.0;
    let (s0, s1, t0, t1) = (edge(j), edge(j + 1), edge(i), edge(i + 1));
    (f(s1, t1) - f(s0, t1) - f(s1, t0) + f(s0, t0)) as f32
}

/// Solid angles of one face's texels, row-major (identical for all six faces).
pub fn face_solid_angles(res: usize) -> Vec<f32> {
    (0..res * res).map(|k| texel_solid_angle(res, k / res, k % res)).collect()
}

/// Texel index of the texel containing (s, t) on `face`, clamped to the face.
pub(crate) fn nearest_index(res: usize, face: usize, s: f32, t: f32) -> usize {
    let to_k = |c: f32| (floor_f32(((c + 1.0) * 0.5) * res as f32).max(0.0) as usize).min(res - 1);
    face * res * res + to_k(t) * res + to_k(s)
}

/// Texels and weights of one bilinear lookup (at most 6 entries: 3 plain taps and a corner tap
/// spread over 3 texels). Weights sum to 1.
#[derive(Clone, Copy, Debug)]
pub struct Taps {
    pub index: [usize; 6],
    pub weight: [f32; 6],
    pub len: usize,
}

impl Taps {
    fn push(&mut self, index: usize, weight: f32) {
        self.index[self.len] = index;
        self.weight[self.len] = weight;
        self.len += 1;
    }

    pub fn iter(&self) -> impl Iterator<Item = (usize, f32)> + '_ {
        (0..self.len).map(|k| (self.index[k], self.weight[k]))
    }
}

impl CubeMap {
    /// A map of `res`² texels per face, all equal to `value`.
    pub fn constant(res: usize, value: Vec3) -> Self {
        assert!(res >= 1, "cube map resolution must be at least 1");
        CubeMap { res, data: vec![value; 6 * res * res] }
    }

    /// A map whose texels hold `f` at their centre directions.
    pub fn from_fn(res: usize, f: impl Fn(Vec3) -> Vec3 + Sync) -> Self {
        let data = (0..6 * res * res)
            .into_par_iter()
            .map(|k| {
                let (face, i, j) = (k / (res * res), (k / res) % res, k % res);
                f(texel_dir(res, face, i, j))
            })
            .collect();
        CubeMap { res, data }
    }

    pub fn texel_index(&self, face: usize, i: usize, j: usize) -> usize {
        (face * self.res + i) * self.res + j
    }

    /// Unit direction of a texel centre.
    pub fn texel_dir(&self, face: usize, i: usize, j: usize) -> Vec3 {
        texel_dir(self.res, face, i, j)
    }

    /// Index of the texel containing `dir`.
    pub fn nearest_texel(&self, dir: Vec3) -> usize {
        let (face, s, t) = dir_to_face(dir);
        nearest_index(self.res, face, s, t)
    }

    /// Value of the texel containing `dir` (piecewise-constant radiance).
    pub fn lookup_nearest(&self, dir: Vec3) -> Vec3 {
        self.data[self.nearest_texel(dir)]
    }

    /// Resolve tap (i, j) of `face`, which may lie one texel off the face, into texel indices.
    fn push_tap(&self, taps: &mut Taps, face: usize, i: i64, j: i64, weight: f32) {
        let n = self.res as i64;
        let inside = |k: i64| (0..n).contains(&k);
        if weight == 0.0 {
            return;
        }
        match (inside(i), inside(j)) {
            (true, true) => taps.push(self.texel_index(face, i as usize, j as usize), weight),
            (false, false) => {
                // Off a cube corner: only three texels meet there; use their mean.
                let (ic, jc) = (i.clamp(0, n - 1), j.clamp(0, n - 1));
                taps.push(self.texel_index(face, ic as usize, jc as usize), weight / 3.0);
                taps.push(self.off_face_texel(face, i, jc), weight / 3.0);
                taps.push(self.off_face_texel(face, ic, j), weight / 3.0);
            }
            _ => taps.push(self.off_face_texel(face, i, j), weight),
        }
    }

    /// The texel of the adjacent face that the centre of the off-face texel (i, j) projects into.
    fn off_face_texel(&self, face: usize, i: i64, j: i64) -> usize {
        let c = |k: i64| 2.0 * (k as f32 + 0.5) / self.res as f32 - 1.0;
        let (f2, s, t) = dir_to_face(face_dir(face, c(j), c(i)));
        nearest_index(self.res, f2, s, t)
    }

    /// Texels and weights of the seam-aware bilinear lookup along `dir`.
    pub fn lookup_taps(&self, dir: Vec3) -> Taps {
        let (face, s, t) = dir_to_face(dir);
        let x = (s + 1.0) * 0.5 * self.res as f32 - 0.5;
        let y = (t + 1.0) * 0.5 * self.res as f32 - 0.5;
        let (x0, y0) = (x.floor(), y.floor());
        let (tx, ty) = (x - x0, y - y0);
        let (j0, i0) = (x0 as i64, y0 as i64);
        let mut taps = Taps { index: [0; 6], weight: [0.0; 6], len: 0 };
        self.push_tap(&mut taps, face, i0, j0, (1.0 - tx) * (1.0 - ty));
        self.push_tap(&mut taps, face, i0, j0 + 1, tx * (1.0 - ty));
        self.push_tap(&mut taps, face, i0 + 1, j0, (1.0 - tx) * ty);
        self.push_tap(&mut taps, face, i0 + 1, j0 + 1, tx * ty);
        taps
    }

    /// Bilinear radiance along `dir`, continuous across face seams and corners.
    pub fn lookup(&self, dir: Vec3) -> Vec3 {
        self.lookup_taps(dir).iter().map(|(k, w)| self.data[k] * w).sum()
    }

    /// Next mip level: 2×2 texel averages (resolution halves; `res` must be even).
    pub fn downsample(&self) -> CubeMap {
        assert!(self.res >= 2 && self.res.is_multiple_of(2), "cannot halve a cube map of resolution {}", self.res);
        let r = self.res / 2;
        let data = (0..6 * r * r)
            .into_par_iter()
            .map(|k| {
                let (face, i, j) = (k / (r * r), (k / r) % r, k % r);
                let at = |di: usize, dj: usize| self.data[self.texel_index(face, 2 * i + di, 2 * j + dj)];
                (at(0, 0) + at(0, 1) + at(1, 0) + at(1, 1)) * 0.25
            })
            .collect();
        CubeMap { res: r, data }
    }

    /// Resample a lat-long probe (Blender convention, see [`latlong`]) into a cube map. Each texel
    /// is the solid-angle-weighted mean of n×n bilinear probe lookups spread over the texel, with n
    /// chosen so the sub-samples are at least as dense as the probe's texels.
    pub fn from_latlong(img: &Image, res: usize) -> CubeMap {
        assert!(res >= 1 && img.width >= 1 && img.height >= 1);
        // A face spans 90° = width/4 probe texels; sample at least twice per probe texel.
        let n = ((img.width as f32 / 4.0 / res as f32) * 2.0).ceil().clamp(2.0, 16.0) as usize;
        let data = (0..6 * res * res)
            .into_par_iter()
            .map(|k| {
                let (face, i, j) = (k / (res * res), (k / res) % res, k % res);
                let mut sum = Vec3::ZERO;
                let mut wsum = 0.0f32;
                for a in 0..n {
                    for b in 0..n {
                        let s = 2.0 * (j as f32 + (b as f32 + 0.5) / n as f32) / res as f32 - 1.0;
                        let t = 2.0 * (i as f32 + (a as f32 + 0.5) / n as f32) / res as f32 - 1.0;
                        let d = face_dir(face, s, t);
                        // dω/dA on the unit-distance plane is |d|⁻³.
                        let w = d.length_squared().powf(-1.5);
                        sum += latlong::lookup(img, d) * w;
                        wsum += w;
                    }
                }
                sum / wsum
            })
            .collect();
        CubeMap { res, data }
    }

    /// A `width`×`height` lat-long image (3 channels) of bilinear lookups at the texel centres.
    pub fn to_latlong(&self, width: usize, height: usize) -> Image {
        let mut img = Image::new(width, height, 3);
        let values: Vec<Vec3> = (0..width * height)
            .into_par_iter()
            .map(|k| self.lookup(latlong::texel_dir(width, height, k / width, k % width)))
            .collect();
        for (k, v) in values.into_iter().enumerate() {
            img.set_rgb(k, v);
        }
        img
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Sampler;

    fn random_dir(rng: &mut Sampler) -> Vec3 {
        let z = 2.0 * rng.next_f32() - 1.0;
        let phi = 2.0 * std::f32::consts::PI * rng.next_f32();
        let r = (1.0 - z * z).max(0.0).sqrt();
        Vec3::new(r * phi.cos(), r * phi.sin(), z)
    }

    #[test]
    fn faces_follow_opengl_order() {
        let res = 4;
        let centre = |f: usize| face_dir(f, 0.0, 0.0);
        assert_eq!([centre(0), centre(1), centre(2), centre(3), centre(4), centre(5)], [Vec3::X, -Vec3::X, Vec3::Y, -Vec3::Y, Vec3::Z, -Vec3::Z]);
        // OpenGL: on +x the column coordinate runs along −z and the row coordinate along −y.
        assert!(texel_dir(res, 0, 0, 0).z > 0.0 && texel_dir(res, 0, 0, 0).y > 0.0);
        assert!(texel_dir(res, 4, 0, res - 1).x > 0.0 && texel_dir(res, 4, 0, res - 1).y > 0.0);
    }

    #[test]
    fn dir_face_round_trip() {
        let mut rng = Sampler::from_seed(1);
        for _ in 0..10000 {
            let d = random_dir(&mut rng);
            let (f, s, t) = dir_to_face(d);
            assert!(s.abs() <= 1.0 && t.abs() <= 1.0);
            assert!(face_dir(f, s, t).normalize().distance(d) < 1e-5);
            let (f2, u, v) = dir_to_face_uv(d);
            assert!(f2 == f && (0.0..=1.0).contains(&u) && (0.0..=1.0).contains(&v));
            assert!(face_uv_to_dir(f2, u, v).distance(d) < 1e-5);
        }
        for res in [1, 3, 8] {
            let map = CubeMap::constant(res, Vec3::ZERO);
            for f in 0..6 {
                for i in 0..res {
                    for j in 0..res {
                        assert_eq!(map.nearest_texel(map.texel_dir(f, i, j)), map.texel_index(f, i, j));
                    }
                }
            }
        }
    }

    #[test]
    fn solid_angles_sum_to_four_pi_and_match_quadrature() {
        for res in [1usize, 2, 7, 64] {
            let total: f64 = face_solid_angles(res).iter().map(|&a| a as f64).sum::<f64>() * 6.0;
            assert!((total - 4.0 * std::f64::consts::PI).abs() < 1e-4, "res {res}: {total}");
        }
        // A corner texel against a fine midpoint quadrature of |d|⁻³ over the texel's plane patch.
        let (res, n) = (8usize, 400usize);
        let h = 2.0 / res as f64;
        let mut q = 0.0;
        for a in 0..n {
            for b in 0..n {
                let s = -1.0 + h * (a as f64 + 0.5) / n as f64;
                let t = -1.0 + h * (b as f64 + 0.5) / n as f64;
                q += (1.0 + s * s + t * t).powf(-1.5) * (h / n as f64).powi(2);
            }
        }
        assert!((texel_solid_angle(res, 0, 0) as f64 - q).abs() < 1e-6 * q.max(1.0) + 1e-7);
    }

    #[test]
    fn constant_lookup_is_constant_everywhere() {
        let map = CubeMap::constant(5, Vec3::new(0.5, 1.0, 2.0));
        let mut rng = Sampler::from_seed(2);
        for _ in 0..5000 {
            let taps = map.lookup_taps(random_dir(&mut rng));
            assert!((taps.iter().map(|(_, w)| w).sum::<f32>() - 1.0).abs() < 1e-5);
            assert!((map.lookup(random_dir(&mut rng)) - Vec3::new(0.5, 1.0, 2.0)).abs().max_element() < 1e-5);
        }
    }

    #[test]
    fn lookup_is_continuous_across_every_seam_and_corner() {
        // Random texels: any jump at a seam would be of the order of the texel differences (~1).
        let res = 6;
        let mut rng = Sampler::from_seed(3);
        let mut map = CubeMap::constant(res, Vec3::ZERO);
        for v in map.data.iter_mut() {
            *v = Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32());
        }
        let eps = 1e-4f32;
        // Bilinear slope ≤ (max texel difference) / (texel angular size ≥ (2/res)/3^{3/2}·...);
        // a crude bound: Δ ≤ slope·distance with slope ≤ 1 per (1/res·0.3) rad.
        let bound = 4.0 * eps * res as f32 / 0.3;
        let mut worst = 0.0f32;
        for face in 0..6 {
            for k in 0..=200 {
                let along = -1.0 + 2.0 * k as f32 / 200.0;
                // Points on all four edges of the face, stepped just off and just on the face.
                for (s, t) in [(1.0, along), (-1.0, along), (along, 1.0), (along, -1.0)] {
                    let on_edge = face_dir(face, s, t).normalize();
                    let inward = (face_dir(face, s * (1.0 - eps), t * (1.0 - eps)).normalize() - on_edge).normalize_or_zero();
                    let a = map.lookup((on_edge + inward * eps).normalize());
                    let b = map.lookup((on_edge - inward * eps).normalize());
                    worst = worst.max((a - b).abs().max_element());
                }
            }
        }
        assert!(worst < bound, "largest jump across a seam {worst} (bound {bound})");
        // The exact corner direction gives the mean of its three texels from every side.
        let corner = Vec3::ONE.normalize();
        let expect = (map.data[map.nearest_texel(Vec3::new(1.0, 0.999, 0.998))]
            + map.data[map.nearest_texel(Vec3::new(0.999, 1.0, 0.998))]
            + map.data[map.nearest_texel(Vec3::new(0.998, 0.999, 1.0))])
            / 3.0;
        assert!((map.lookup(corner) - expect).abs().max_element() < 1e-3, "{} vs {}", map.lookup(corner), expect);
    }

    #[test]
    fn downsample_averages_2x2_blocks() {
        let map = CubeMap::constant(8, Vec3::splat(0.7));
        let half = map.downsample();
        assert_eq!(half.res, 4);
        assert!(half.data.iter().all(|v| (*v - Vec3::splat(0.7)).abs().max_element() < 1e-6));
        let mut m = CubeMap::constant(4, Vec3::ZERO);
        let k = m.texel_index(2, 1, 1);
        m.data[k] = Vec3::splat(4.0);
        let half = m.downsample();
        assert_eq!(half.data[half.texel_index(2, 0, 0)], Vec3::ONE);
        assert_eq!(half.data.iter().filter(|v| **v != Vec3::ZERO).count(), 1);
    }

    #[test]
    fn latlong_round_trip_of_a_smooth_map() {
        let f = |d: Vec3| Vec3::new(1.0 + 0.5 * d.x, 1.0 + 0.3 * d.y * d.z, 0.5 + 0.5 * d.z * d.z);
        let (w, h) = (64, 32);
        let mut img = Image::new(w, h, 3);
        for i in 0..h {
            for j in 0..w {
                img.set_rgb(i * w + j, f(latlong::texel_dir(w, h, i, j)));
            }
        }
        let cube = CubeMap::from_latlong(&img, 32);
        // Cube texels agree with the function at their centres (up to bilinear and averaging error).
        for (k, v) in cube.data.iter().enumerate() {
            let d = texel_dir(32, k / 1024, (k / 32) % 32, k % 32);
            assert!((*v - f(d)).abs().max_element() < 0.02, "texel {k}: {v} vs {}", f(d));
        }
        let back = cube.to_latlong(w, h);
        let mut worst = 0.0f32;
        for i in 1..h - 1 {
            for j in 0..w {
                worst = worst.max((back.rgb(i * w + j) - img.rgb(i * w + j)).abs().max_element());
            }
        }
        assert!(worst < 0.02, "round trip error {worst}");
    }

    #[test]
    fn from_latlong_preserves_the_mean_radiance_of_a_coarse_probe() {
        // A 16×32 probe with one bright texel: the cube's integral of radiance must match the probe's.
        let (w, h) = (32, 16);
        let mut img = Image::filled(w, h, &[0.1, 0.1, 0.1]);
        img.set_rgb(5 * w, Vec3::splat(100.0));
        let cube = CubeMap::from_latlong(&img, 32);
        let areas = face_solid_angles(32);
        let cube_int: f64 = cube.data.iter().enumerate().map(|(k, v)| v.x as f64 * areas[k % 1024] as f64).sum();
        // The probe integral of the bilinear function: fine quadrature in (u, v).
        let n = 800;
        let mut probe_int = 0.0f64;
        for a in 0..n / 2 {
            for b in 0..n {
                let (u, v) = ((b as f32 + 0.5) / n as f32, (a as f32 + 0.5) / (n / 2) as f32);
                let theta = v as f64 * std::f64::consts::PI;
                let dw = theta.sin() * (std::f64::consts::PI / (n / 2) as f64) * (2.0 * std::f64::consts::PI / n as f64);
                probe_int += latlong::lookup_uv(&img, u, v).x as f64 * dw;
            }
        }
        assert!((cube_int - probe_int).abs() < 0.01 * probe_int, "cube {cube_int} probe {probe_int}");
    }
}

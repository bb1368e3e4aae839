//! The signed distance, in pixels, from each pixel of a coverage mask to the mask's outline:
//! negative inside (coverage ≥ threshold), positive outside. The visual hull (hull.rs) lifts it to
//! a distance from each view's silhouette cone.
//!
//! Built from two exact Euclidean distance transforms (Felzenszwalb & Huttenlocher 2012, "Distance
//! transforms of sampled functions": a lower envelope of parabolas per row, then per column), one to
//! the inside pixels and one to the outside pixels. The outline is taken half way between an inside
//! and an outside pixel centre, so neighbours across it read ±0.5. It is written here (about thirty
//! lines) rather than taken from `imageproc`, whose current releases would bring a second `nalgebra`
//! and `rand` into a build that is already the machine's bottleneck.

/// A mask's signed distance field over its pixel grid (row-major, `width × height`).
#[derive(Clone, Debug)]
pub struct MaskDistance {
    pub width: usize,
    pub height: usize,
    /// Signed distance in pixels from each pixel centre to the outline (positive outside).
    pub distance: Vec<f32>,
}

/// Stands for "no feature pixel on this line yet": far beyond any squared pixel distance of an image.
const FAR: f64 = 1e20;

impl MaskDistance {
    /// The signed distance of a mask given as inside flags (`inside.len() == width * height`).
    /// A mask with no inside or no outside pixel gives distances near ±1e10 (callers reject it first).
    pub fn new(inside: &[bool], width: usize, height: usize) -> MaskDistance {
        assert_eq!(inside.len(), width * height, "mask size");
        let to_inside = squared_distance_to(inside, width, height, true);
        let to_outside = squared_distance_to(inside, width, height, false);
        let distance = inside
            .iter()
            .enumerate()
            .map(|(i, &is_in)| {
                if is_in {
                    -(to_outside[i].sqrt() - 0.5) as f32
                } else {
                    (to_inside[i].sqrt() - 0.5) as f32
                }
            })
            .collect();
        MaskDistance { width, height, distance }
    }

    /// Bilinear sample at continuous pixel coordinates (pixel (i, j) has its centre at
    /// (i + 0.5, j + 0.5)). Outside the image the value is that at the nearest point of the image plus
    /// the pixel distance to it, a continuous extension that grows like a distance. Returns the value
    /// and whether the point was inside the image.
    pub fn sample(&self, x: f32, y: f32) -> (f32, bool) {
        let (u, v) = (x - 0.5, y - 0.5);
        let (umax, vmax) = ((self.width - 1) as f32, (self.height - 1) as f32);
        let (cu, cv) = (u.clamp(0.0, umax), v.clamp(0.0, vmax));
        let (i0, j0) = (cu.floor() as usize, cv.floor() as usize);
        let (i1, j1) = ((i0 + 1).min(self.width - 1), (j0 + 1).min(self.height - 1));
        let (fu, fv) = (cu - i0 as f32, cv - j0 as f32);
        let at = |i: usize, j: usize| self.distance[j * self.width + i];
        let top = at(i0, j0) * (1.0 - fu) + at(i1, j0) * fu;
        let bottom = at(i0, j1) * (1.0 - fu) + at(i1, j1) * fu;
        let value = top * (1.0 - fv) + bottom * fv;
        let off = ((u - cu).powi(2) + (v - cv).powi(2)).sqrt();
        (value + off, off == 0.0)
    }
}

/// Squared Euclidean distance from each pixel centre to the nearest pixel whose flag equals `target`.
fn squared_distance_to(flags: &[bool], width: usize, height: usize, target: bool) -> Vec<f64> {
    let mut grid: Vec<f64> = flags.iter().map(|&f| if f == target { 0.0 } else { FAR }).collect();
    let n = width.max(height);
    let (mut line, mut out) = (vec![0.0; n], vec![0.0; n]);
    let (mut sites, mut bounds) = (vec![0usize; n], vec![0.0f64; n + 1]);
    for y in 0..height {
        line[..width].copy_from_slice(&grid[y * width..(y + 1) * width]);
        lower_envelope(&line[..width], &mut out[..width], &mut sites, &mut bounds);
        grid[y * width..(y + 1) * width].copy_from_slice(&out[..width]);
    }
    for x in 0..width {
        for y in 0..height {
            line[y] = grid[y * width + x];
        }
        lower_envelope(&line[..height], &mut out[..height], &mut sites, &mut bounds);
        for y in 0..height {
            grid[y * width + x] = out[y];
        }
    }
    grid
}

/// One-dimensional squared distance transform: `out[q] = min_p (q − p)² + f[p]`, by the lower
/// envelope of the parabolas rooted at each `p` (linear time).
fn lower_envelope(f: &[f64], out: &mut [f64], sites: &mut [usize], bounds: &mut [f64]) {
    let n = f.len();
    let meet = |p: usize, q: usize| ((f[q] + (q * q) as f64) - (f[p] + (p * p) as f64)) / (2.0 * (q as f64 - p as f64));
    let mut k = 0;
    sites[0] = 0;
    bounds[0] = f64::NEG_INFINITY;
    bounds[1] = f64::INFINITY;
    for q in 1..n {
        let mut s = meet(sites[k], q);
        while s <= bounds[k] {
            k -= 1;
            s = meet(sites[k], q);
        }
        k += 1;
        sites[k] = q;
        bounds[k] = s;
        bounds[k + 1] = f64::INFINITY;
    }
    k = 0;
    for (q, o) in out.iter_mut().enumerate() {
        while bounds[k + 1] < q as f64 {
            k += 1;
        }
        let d = q as f64 - sites[k] as f64;
        *o = d * d + f[sites[k]];
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Brute force: distance from each pixel centre to the nearest centre of the other kind, minus half a pixel.
    fn brute(inside: &[bool], w: usize, h: usize) -> Vec<f32> {
        (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f32, (i / w) as f32);
                let nearest = (0..w * h)
                    .filter(|&j| inside[j] != inside[i])
                    .map(|j| (((j % w) as f32 - x).powi(2) + ((j / w) as f32 - y).powi(2)).sqrt())
                    .fold(f32::INFINITY, f32::min);
                if inside[i] {
                    -(nearest - 0.5)
                } else {
                    nearest - 0.5
                }
            })
            .collect()
    }

    #[test]
    fn matches_brute_force_on_random_blobs() {
        let (w, h) = (23, 17);
        let mut state = 12345u32;
        for _ in 0..5 {
            let mut inside = vec![false; w * h];
            for _ in 0..4 {
                state = state.wrapping_mul(1664525).wrapping_add(1013904223);
                let (cx, cy, r) = ((state % w as u32) as f32, ((state >> 8) % h as u32) as f32, 1.0 + ((state >> 16) % 5) as f32);
                for (i, v) in inside.iter_mut().enumerate() {
                    let (x, y) = ((i % w) as f32, (i / w) as f32);
                    *v |= (x - cx).powi(2) + (y - cy).powi(2) <= r * r;
                }
            }
            let fast = MaskDistance::new(&inside, w, h);
            for (a, b) in fast.distance.iter().zip(brute(&inside, w, h)) {
                assert!((a - b).abs() < 1e-4, "{a} vs {b}");
            }
        }
    }

    #[test]
    fn samples_extend_outside_the_image_like_a_distance() {
        // A single inside column at x = 2 of a 5×3 image.
        let inside: Vec<bool> = (0..15).map(|i| i % 5 == 2).collect();
        let d = MaskDistance::new(&inside, 5, 3);
        // On the column centre: -0.5; one pixel to the right: +0.5; half way: 0 (the outline).
        assert!((d.sample(2.5, 1.5).0 + 0.5).abs() < 1e-6);
        assert!((d.sample(3.5, 1.5).0 - 0.5).abs() < 1e-6);
        assert!(d.sample(3.0, 1.5).0.abs() < 1e-6);
        // Three pixels beyond the right edge (last centre at x = 4.5, value 1.5): 1.5 + 3.
        let (v, in_image) = d.sample(7.5, 1.5);
        assert!((v - 4.5).abs() < 1e-5 && !in_image);
    }
}

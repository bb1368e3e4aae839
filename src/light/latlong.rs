//! Lat-long (equirectangular) probes in Blender's convention, as the NeRFactor probes use it
//! (docs/model.md, *Light*):
//! d = (sinθ cosφ, sinθ sinφ, cosθ) with θ = v·π, φ = 2π(0.5 − u); u runs left to right, v top to
//! bottom; texel (i, j) has its centre at ((j+0.5)/W, (i+0.5)/H); lookups are bilinear with
//! periodic wrap in both axes, like Cycles' Environment Texture node.

use std::f32::consts::PI;

use glam::Vec3;

use crate::image::Image;

/// The world direction that (u, v) looks along.
pub fn dir_from_uv(u: f32, v: f32) -> Vec3 {
    let theta = v * PI;
    let phi = 2.0 * PI * (0.5 - u);
    let (st, ct) = theta.sin_cos();
    let (sp, cp) = phi.sin_cos();
    Vec3::new(st * cp, st * sp, ct)
}

/// (u, v) ∈ [0, 1)×[0, 1] of a direction (need not be unit length). At the poles φ = atan2(0, 0) = 0,
/// i.e. u = 0.5, as Blender computes it.
pub fn uv_from_dir(d: Vec3) -> (f32, f32) {
    let d = d.normalize_or(Vec3::Z);
    let theta = d.z.clamp(-1.0, 1.0).acos();
    let phi = d.y.atan2(d.x);
    let u = 0.5 - phi / (2.0 * PI);
    let u = if u >= 1.0 { u - 1.0 } else { u };
    (u, theta / PI)
}

/// Centre direction of texel (row i, column j) of a W×H probe.
pub fn texel_dir(width: usize, height: usize, i: usize, j: usize) -> Vec3 {
    dir_from_uv((j as f32 + 0.5) / width as f32, (i as f32 + 0.5) / height as f32)
}

/// The four texels and bilinear weights of a lookup at (u, v), periodic in both axes.
/// Returned as (row-major pixel index, weight); the weights sum to 1.
pub fn bilinear_taps(width: usize, height: usize, u: f32, v: f32) -> [(usize, f32); 4] {
    let x = u * width as f32 - 0.5;
    let y = v * height as f32 - 0.5;
    let (fx, fy) = (x.floor(), y.floor());
    let (tx, ty) = (x - fx, y - fy);
    let wrap = |k: f32, n: usize| (k as i64).rem_euclid(n as i64) as usize;
    let (j0, i0) = (wrap(fx, width), wrap(fy, height));
    let (j1, i1) = ((j0 + 1) % width, (i0 + 1) % height);
    [
        (i0 * width + j0, (1.0 - tx) * (1.0 - ty)),
        (i0 * width + j1, tx * (1.0 - ty)),
        (i1 * width + j0, (1.0 - tx) * ty),
        (i1 * width + j1, tx * ty),
    ]
}

/// Bilinear, periodically wrapped value of the probe at (u, v) (first three channels).
pub fn lookup_uv(img: &Image, u: f32, v: f32) -> Vec3 {
    bilinear_taps(img.width, img.height, u, v).iter().map(|&(k, w)| img.rgb(k) * w).sum()
}

/// Radiance of the probe seen along `dir`.
pub fn lookup(img: &Image, dir: Vec3) -> Vec3 {
    let (u, v) = uv_from_dir(dir);
    lookup_uv(img, u, v)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn readme_orientation() {
        assert!(dir_from_uv(0.5, 0.5).distance(Vec3::X) < 1e-6);
        assert!(dir_from_uv(0.25, 0.5).distance(Vec3::Y) < 1e-6);
        assert!(dir_from_uv(0.0, 0.5).distance(-Vec3::X) < 1e-6);
        assert!(dir_from_uv(0.75, 0.5).distance(-Vec3::Y) < 1e-6);
        assert!(dir_from_uv(0.3, 0.0).distance(Vec3::Z) < 1e-6);
        // Texel row 5, column 0 of a 16×32 probe: toward −x, about 30° above the horizon.
        let d = texel_dir(32, 16, 5, 0);
        let elevation = d.z.asin().to_degrees();
        let azimuth_x = d.x / (d.x * d.x + d.y * d.y).sqrt();
        assert!(azimuth_x < -0.99 && (elevation - 28.125).abs() < 1e-3, "{d} {elevation}");
    }

    #[test]
    fn uv_round_trip() {
        for i in 0..37 {
            for j in 0..50 {
                let (u, v) = ((j as f32 + 0.3) / 50.0, (i as f32 + 0.6) / 37.5);
                let (u2, v2) = uv_from_dir(dir_from_uv(u, v));
                assert!((u - u2).abs() < 1e-5 && (v - v2).abs() < 1e-5, "{u},{v} -> {u2},{v2}");
            }
        }
    }

    #[test]
    fn lookup_hits_texel_centres_and_wraps() {
        let mut img = Image::new(4, 2, 3);
        for k in 0..8 {
            img.set_rgb(k, Vec3::splat(k as f32));
        }
        assert_eq!(lookup(&img, texel_dir(4, 2, 1, 2)), Vec3::splat(6.0));
        // Halfway between column 3 and column 0 (periodic in u).
        let v = lookup_uv(&img, 0.0, 0.25);
        assert!((v.x - 1.5).abs() < 1e-6, "{v}");
        // Periodic in v too: the top edge blends row 0 with the last row.
        let v = lookup_uv(&img, 0.125, 0.0);
        assert!((v.x - 2.0).abs() < 1e-6, "{v}");
    }
}

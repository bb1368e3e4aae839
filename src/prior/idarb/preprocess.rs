//! Input and output framing as the official loader (`CustomMVDataset.load_image`) does it:
//! longest side resized to the target with bicubic filtering (PIL: on premultiplied RGBA, 8-bit
//! results), centred zero padding to target×target, mask = alpha > 0.5, white background.
//! The outputs are mapped back to each view's original framing by the inverse crop and resize.
use crate::image::Image;
use anyhow::{bail, Result};
use glam::Vec3;

/// Where a view's pixels sit inside the square network input.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Framing {
    pub original_width: usize,
    pub original_height: usize,
    pub resized_width: usize,
    pub resized_height: usize,
    pub pad_left: usize,
    pub pad_top: usize,
    pub target: usize,
}

impl Framing {
    /// The official rule: the longer side becomes `target`, the other `int(short/long · target)`
    /// (truncated); a square input takes the height branch. Padding puts ⌊(target − size)/2⌋ first.
    pub fn new(width: usize, height: usize, target: usize) -> Self {
        let (rw, rh) = if width > height {
            (target, (height as f64 / width as f64 * target as f64) as usize)
        } else {
            ((width as f64 / height as f64 * target as f64) as usize, target)
        };
        let (rw, rh) = (rw.max(1), rh.max(1));
        Framing { original_width: width, original_height: height, resized_width: rw, resized_height: rh, pad_left: (target - rw) / 2, pad_top: (target - rh) / 2, target }
    }
}

/// PIL's bicubic kernel (a = −0.5).
fn bicubic(x: f64) -> f64 {
    let a = -0.5;
    let x = x.abs();
    if x < 1.0 {
        ((a + 2.0) * x - (a + 3.0)) * x * x + 1.0
    } else if x < 2.0 {
        (((x - 5.0) * x + 8.0) * x - 4.0) * a
    } else {
        0.0
    }
}

/// Normalised filter taps for resampling `n_in` samples to `n_out`, widened when downscaling
/// (antialiasing), with PIL's window rounding.
fn resample_taps(n_in: usize, n_out: usize) -> Vec<(usize, Vec<f64>)> {
    let scale = n_in as f64 / n_out as f64;
    let fscale = scale.max(1.0);
    let support = 2.0 * fscale;
    (0..n_out)
        .map(|i| {
            let center = (i as f64 + 0.5) * scale;
            let lo = ((center - support + 0.5).floor().max(0.0)) as usize;
            let hi = ((center + support + 0.5).floor() as usize).min(n_in);
            let mut w: Vec<f64> = (lo..hi).map(|j| bicubic((j as f64 - center + 0.5) / fscale)).collect();
            let sum: f64 = w.iter().sum();
            if sum != 0.0 {
                w.iter_mut().for_each(|x| *x /= sum);
            }
            (lo, w)
        })
        .collect()
}

/// Separable bicubic resize of every channel (horizontal pass, then vertical).
pub fn resize_bicubic(img: &Image, width: usize, height: usize) -> Image {
    if img.width == width && img.height == height {
        return img.clone();
    }
    let c = img.channels;
    let taps_x = resample_taps(img.width, width);
    let mut tmp = vec![0f64; width * img.height * c];
    for y in 0..img.height {
        for (x, (lo, w)) in taps_x.iter().enumerate() {
            for (k, wk) in w.iter().enumerate() {
                let src = img.pixel(lo + k, y);
                for ch in 0..c {
                    tmp[(y * width + x) * c + ch] += wk * src[ch] as f64;
                }
            }
        }
    }
    let taps_y = resample_taps(img.height, height);
    let mut out = Image::new(width, height, c);
    for (y, (lo, w)) in taps_y.iter().enumerate() {
        for x in 0..width {
            for ch in 0..c {
                let v: f64 = w.iter().enumerate().map(|(k, wk)| wk * tmp[((lo + k) * width + x) * c + ch]).sum();
                out.data[(y * width + x) * c + ch] = v as f32;
            }
        }
    }
    out
}

fn quantize_u8(v: f32) -> f32 {
    (v.clamp(0.0, 1.0) * 255.0).round() / 255.0
}

/// Resize RGBA as PIL does: premultiply, resample, un-premultiply, 8-bit values.
pub fn resize_rgba(img: &Image, width: usize, height: usize) -> Image {
    if img.width == width && img.height == height {
        return img.map_channels(4, quantize_u8);
    }
    let mut pre = img.clone();
    for p in pre.data.chunks_exact_mut(4) {
        let a = p[3];
        p[0] *= a;
        p[1] *= a;
        p[2] *= a;
    }
    let mut out = resize_bicubic(&pre, width, height);
    for p in out.data.chunks_exact_mut(4) {
        let a = quantize_u8(p[3]);
        for v in p.iter_mut().take(3) {
            *v = if a > 0.0 { quantize_u8(*v / a) } else { 0.0 };
        }
        p[3] = a;
    }
    out
}

/// One view ready for the network.
#[derive(Debug, Clone)]
pub struct PreparedView {
    /// target×target RGB on white, planar [3, T, T], values in [0, 1].
    pub rgb_planar: Vec<f32>,
    /// target×target 0/1 mask (alpha > 0.5).
    pub mask: Vec<f32>,
    pub framing: Framing,
}

/// `rgba`: sRGB-encoded RGBA in [0, 1] (what a PNG holds). Resize, pad, mask, white background.
pub fn prepare_view(rgba: &Image, target: usize) -> Result<PreparedView> {
    if rgba.channels != 4 {
        bail!("IDArb input must be RGBA (4 channels), got {} channels", rgba.channels);
    }
    if rgba.width == 0 || rgba.height == 0 || target == 0 || !target.is_multiple_of(8) {
        bail!("IDArb input {}×{} or target {target} invalid (target must be a positive multiple of 8)", rgba.width, rgba.height);
    }
    let framing = Framing::new(rgba.width, rgba.height, target);
    let resized = resize_rgba(rgba, framing.resized_width, framing.resized_height);
    let t = target;
    // padding is transparent black, so padded pixels become white background
    let mut rgb_planar = vec![1f32; 3 * t * t];
    let mut mask = vec![0f32; t * t];
    for y in 0..framing.resized_height {
        for x in 0..framing.resized_width {
            let p = resized.pixel(x, y);
            let i = (y + framing.pad_top) * t + x + framing.pad_left;
            if p[3] > 0.5 {
                mask[i] = 1.0;
                for c in 0..3 {
                    rgb_planar[c * t * t + i] = p[c];
                }
            }
        }
    }
    Ok(PreparedView { rgb_planar, mask, framing })
}

/// Cut a target×target planar map (`channels` planes) back to the view's original framing.
pub fn unframe(planar: &[f32], channels: usize, framing: &Framing) -> Image {
    let t = framing.target;
    let mut crop = Image::new(framing.resized_width, framing.resized_height, channels);
    for y in 0..framing.resized_height {
        for x in 0..framing.resized_width {
            let i = (y + framing.pad_top) * t + x + framing.pad_left;
            let p = crop.pixel_mut(x, y);
            for (c, v) in p.iter_mut().enumerate() {
                *v = planar[c * t * t + i];
            }
        }
    }
    resize_bicubic(&crop, framing.original_width, framing.original_height).map_channels(channels, |v| v.clamp(0.0, 1.0))
}

/// The official pose when no camera is used: [0, 0, (ln 1.5 − ln 1.2)/(ln 2.2 − ln 1.2)·π, 0].
pub fn default_pose() -> [f32; 4] {
    [0.0, 0.0, ((1.5f64.ln() - 1.2f64.ln()) / (2.2f64.ln() - 1.2f64.ln()) * std::f64::consts::PI) as f32, 0.0]
}

/// The official camera pose (`CustomMVDataset.get_pose`) from a camera-to-world origin:
/// [polar angle from +z, azimuth atan2(y, x), log-radius clipped to [1.2, 2.2] mapped to [0, π], 0].
pub fn pose_from_camera_origin(origin: Vec3) -> [f32; 4] {
    let (x, y, z) = (origin.x as f64, origin.y as f64, origin.z as f64);
    let xy = x * x + y * y;
    let r = (xy + z * z).sqrt().clamp(1.2, 2.2);
    let theta = xy.sqrt().atan2(z);
    let azimuth = y.atan2(x);
    let radius = (r.ln() - 1.2f64.ln()) / (2.2f64.ln() - 1.2f64.ln()) * std::f64::consts::PI;
    [theta as f32, azimuth as f32, radius as f32, 0.0]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn framing_follows_the_official_rule() {
        // landscape 640×480 → 512×384 (int(480/640·512) = 384), padded 64 top, 64 bottom
        let f = Framing::new(640, 480, 512);
        assert_eq!((f.resized_width, f.resized_height, f.pad_left, f.pad_top), (512, 384, 0, 64));
        // portrait 300×701 → int(300/701·512) = int(219.11) = 219 wide; left pad ⌊293/2⌋ = 146
        let f = Framing::new(300, 701, 512);
        assert_eq!((f.resized_width, f.resized_height, f.pad_left, f.pad_top), (219, 512, 146, 0));
        // odd leftover: 100×37 at 64 → 64 × int(23.68) = 23; top pad ⌊41/2⌋ = 20 (21 below)
        let f = Framing::new(100, 37, 64);
        assert_eq!((f.resized_width, f.resized_height, f.pad_left, f.pad_top), (64, 23, 0, 20));
        // square takes the height branch and is unchanged at the target size
        let f = Framing::new(512, 512, 512);
        assert_eq!((f.resized_width, f.resized_height, f.pad_left, f.pad_top), (512, 512, 0, 0));
    }

    #[test]
    fn padding_is_white_and_unmasked_and_content_is_centred() -> Result<()> {
        // 16×8 opaque red view into a 16×16 input: rows 4..12 hold the view
        let img = Image::filled(16, 8, &[1.0, 0.0, 0.0, 1.0]);
        let p = prepare_view(&img, 16)?;
        let t = 16;
        for y in 0..t {
            let inside = (4..12).contains(&y);
            assert_eq!(p.mask[y * t + 3], if inside { 1.0 } else { 0.0 }, "row {y}");
            let g = p.rgb_planar[t * t + y * t + 3];
            assert_eq!(g, if inside { 0.0 } else { 1.0 }, "row {y}");
        }
        Ok(())
    }

    #[test]
    fn alpha_threshold_and_white_background() -> Result<()> {
        let mut img = Image::filled(8, 8, &[0.2, 0.4, 0.6, 0.4]);
        img.pixel_mut(1, 1)[3] = 0.6;
        let p = prepare_view(&img, 8)?;
        assert_eq!(p.mask[9], 1.0);
        assert_eq!(p.mask[0], 0.0);
        assert_eq!(p.rgb_planar[9], quantize_u8(0.2));
        assert_eq!(p.rgb_planar[0], 1.0);
        Ok(())
    }

    #[test]
    fn bicubic_resize_preserves_constants_and_round_trips_unframe() {
        // constant images stay constant (weights normalised), up and down
        let img = Image::filled(7, 5, &[0.25, 0.75]);
        for (w, h) in [(3, 2), (16, 11)] {
            let r = resize_bicubic(&img, w, h);
            assert!(r.data.iter().enumerate().all(|(i, v)| (v - if i % 2 == 0 { 0.25 } else { 0.75 }).abs() < 1e-6));
        }
        // unframe of a map that is 1 inside the view's box and 0 in the padding gives all ones
        let f = Framing::new(40, 20, 32);
        let t = 32;
        let mut planar = vec![0f32; t * t];
        for y in f.pad_top..f.pad_top + f.resized_height {
            for x in f.pad_left..f.pad_left + f.resized_width {
                planar[y * t + x] = 1.0;
            }
        }
        let back = unframe(&planar, 1, &f);
        assert_eq!((back.width, back.height), (40, 20));
        assert!(back.data.iter().all(|v| (v - 1.0).abs() < 1e-6));
    }

    #[test]
    fn pose_matches_official_constants() {
        let p = default_pose();
        assert!((p[2] - 1.1565497).abs() < 1e-6);
        // camera on +x at radius 1.5 → theta π/2, azimuth 0, same radius code as the default
        let q = pose_from_camera_origin(Vec3::new(1.5, 0.0, 0.0));
        assert!((q[0] - std::f32::consts::FRAC_PI_2).abs() < 1e-6 && q[1].abs() < 1e-6 && (q[2] - p[2]).abs() < 1e-6);
        // far cameras clip to radius 2.2 → π
        assert!((pose_from_camera_origin(Vec3::new(0.0, 4.0, 0.0))[2] - std::f32::consts::PI).abs() < 1e-6);
    }
}

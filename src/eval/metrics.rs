//! Image metrics of the NeRFactor evaluation protocol: MSE / PSNR, per-channel albedo scale,
//! normal angular error, mask IoU, and compositing over white for relighting comparisons.
//!
//! Conventions: metrics compare the *colour* channels (grey, or the first three); alpha is never
//! compared — turn it into a mask with [`mask_from_alpha`]. Masks are one `bool` per pixel;
//! `None` means every pixel. Values are compared as given (peak 1 for PSNR).
//! Images of different sizes or colour-channel counts, or a mask of the wrong length, are a
//! programming error and panic with a message (the dataset loader checks sizes of files).

use glam::DVec3;

use crate::color::linear_to_srgb;
use crate::image::Image;

/// Pixels whose alpha is strictly above `threshold`. Alpha is the last channel of a 2- or
/// 4-channel image, or the only channel of a 1-channel one.
pub fn mask_from_alpha(img: &Image, threshold: f32) -> Vec<bool> {
    let c = match img.channels {
        1 => 0,
        2 | 4 => img.channels - 1,
        n => panic!("mask_from_alpha: a {n}-channel image has no alpha channel"),
    };
    img.data.chunks_exact(img.channels).map(|p| p[c] > threshold).collect()
}

fn check_pair(a: &Image, b: &Image, mask: Option<&[bool]>) -> usize {
    assert_eq!((a.width, a.height), (b.width, b.height), "metric on images of different sizes");
    assert_eq!(a.colour_channels(), b.colour_channels(), "metric on images with different colour channels");
    if let Some(m) = mask {
        assert_eq!(m.len(), a.pixel_count(), "mask length differs from the pixel count");
    }
    a.colour_channels()
}

fn selected(mask: Option<&[bool]>, i: usize) -> bool {
    mask.is_none_or(|m| m[i])
}

/// Mean squared error over the colour channels of the selected pixels (NaN if none is selected).
pub fn mse(pred: &Image, target: &Image, mask: Option<&[bool]>) -> f64 {
    let n = check_pair(pred, target, mask);
    let (mut sum, mut count) = (0.0f64, 0usize);
    for i in 0..pred.pixel_count() {
        if !selected(mask, i) {
            continue;
        }
        let (p, t) = (&pred.data[i * pred.channels..], &target.data[i * target.channels..]);
        for c in 0..n {
            let d = p[c] as f64 - t[c] as f64;
            sum += d * d;
        }
        count += n;
    }
    if count == 0 {
        f64::NAN
    } else {
        sum / count as f64
    }
}

/// PSNR in dB with peak value 1: −10·log10(MSE) (infinite for identical images).
pub fn psnr(pred: &Image, target: &Image, mask: Option<&[bool]>) -> f64 {
    -10.0 * mse(pred, target, mask).log10()
}

/// Per-channel least-squares scale s minimising Σ (s·pred − target)² over the mask
/// (NeRFactor protocol: linear values, alpha > 0.9): s = Σ pred·target / Σ pred².
/// A channel with no signal in `pred` gets scale 1. Grey images give the same scale 3 times.
pub fn albedo_scale(pred: &Image, target: &Image, mask: Option<&[bool]>) -> [f64; 3] {
    check_pair(pred, target, mask);
    let (mut pt, mut pp) = (DVec3::ZERO, DVec3::ZERO);
    for i in 0..pred.pixel_count() {
        if selected(mask, i) {
            let (p, t) = (pred.rgb(i).as_dvec3(), target.rgb(i).as_dvec3());
            pt += p * t;
            pp += p * p;
        }
    }
    std::array::from_fn(|c| if pp[c] > 0.0 { pt[c] / pp[c] } else { 1.0 })
}

/// Multiply the colour channels by per-channel scales (alpha untouched).
pub fn scale_colour(img: &Image, scale: [f64; 3]) -> Image {
    let mut out = img.clone();
    let n = img.colour_channels();
    for p in out.data.chunks_exact_mut(img.channels) {
        for c in 0..n {
            p[c] = (p[c] as f64 * scale[c]) as f32;
        }
    }
    out
}

/// Mean angle in degrees between two normal maps (first three channels, normalised here) over the
/// selected pixels. Pixels where either normal has zero length (background) are skipped;
/// NaN when no pixel is left.
pub fn mean_angular_error_deg(a: &Image, b: &Image, mask: Option<&[bool]>) -> f64 {
    assert!(a.channels >= 3 && b.channels >= 3, "normal maps need 3 channels");
    check_pair(a, b, mask);
    let (mut sum, mut count) = (0.0f64, 0usize);
    for i in 0..a.pixel_count() {
        if !selected(mask, i) {
            continue;
        }
        let (na, nb) = (a.rgb(i).as_dvec3(), b.rgb(i).as_dvec3());
        if na.length_squared() == 0.0 || nb.length_squared() == 0.0 {
            continue;
        }
        let cos = na.normalize().dot(nb.normalize()).clamp(-1.0, 1.0);
        sum += cos.acos().to_degrees();
        count += 1;
    }
    if count == 0 {
        f64::NAN
    } else {
        sum / count as f64
    }
}

/// Intersection over union of two masks (1 when both are empty: they agree everywhere).
pub fn mask_iou(a: &[bool], b: &[bool]) -> f64 {
    assert_eq!(a.len(), b.len(), "mask_iou: masks of different lengths");
    let inter = a.iter().zip(b).filter(|(x, y)| **x && **y).count();
    let union = a.iter().zip(b).filter(|(x, y)| **x || **y).count();
    if union == 0 {
        1.0
    } else {
        inter as f64 / union as f64
    }
}

/// Composite linear colour over a white background and encode to sRGB:
/// srgb(clamp(rgb·α + (1 − α), 0, 1)). `alpha` is a 1-channel image or the last channel of a
/// 2/4-channel one. Returns a 3-channel image (grey input is replicated).
/// This is how NeRFactor compares relit images (then PSNR over alpha > 0.8).
pub fn over_white(rgb: &Image, alpha: &Image) -> Image {
    assert_eq!((rgb.width, rgb.height), (alpha.width, alpha.height), "over_white: size mismatch");
    let ac = match alpha.channels {
        1 => 0,
        2 | 4 => alpha.channels - 1,
        n => panic!("over_white: a {n}-channel image has no alpha channel"),
    };
    let mut out = Image::new(rgb.width, rgb.height, 3);
    for i in 0..rgb.pixel_count() {
        let a = alpha.data[i * alpha.channels + ac].clamp(0.0, 1.0);
        let lin = rgb.rgb(i) * a + glam::Vec3::splat(1.0 - a);
        out.set_rgb(i, lin.clamp(glam::Vec3::ZERO, glam::Vec3::ONE).to_array().map(linear_to_srgb).into());
    }
    out
}

/// PSNR of `render` against `target` over white in sRGB, on pixels where the target's alpha > 0.8.
pub fn protocol_psnr(render: &Image, target: &Image) -> f64 {
    let mask = mask_from_alpha(target, 0.8);
    psnr(&over_white(render, render), &over_white(target, target), Some(&mask))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn img(w: usize, h: usize, c: usize, data: &[f32]) -> Image {
        Image { width: w, height: h, channels: c, data: data.to_vec() }
    }

    #[test]
    fn mse_and_psnr_match_hand_computed_values() {
        let pred = img(2, 1, 3, &[0.1, 0.2, 0.3, 0.5, 0.5, 0.5]);
        let target = img(2, 1, 3, &[0.1, 0.2, 0.5, 0.5, 0.5, 0.9]);
        // squared errors 0.04 and 0.16 over 6 values.
        assert!((mse(&pred, &target, None) - 0.2 / 6.0).abs() < 1e-7);
        let only_first = [true, false];
        assert!((mse(&pred, &target, Some(&only_first)) - 0.04 / 3.0).abs() < 1e-7);
        // MSE 0.01 → 20 dB.
        let a = img(1, 1, 1, &[0.3]);
        let b = img(1, 1, 1, &[0.4]);
        assert!((psnr(&a, &b, None) - 20.0).abs() < 1e-5);
        assert!(mse(&a, &b, Some(&[false])).is_nan());
    }

    #[test]
    fn alpha_is_not_compared() {
        let a = img(1, 1, 4, &[0.2, 0.2, 0.2, 0.0]);
        let b = img(1, 1, 4, &[0.2, 0.2, 0.2, 1.0]);
        assert_eq!(mse(&a, &b, None), 0.0);
        assert_eq!(mask_from_alpha(&b, 0.9), vec![true]);
        assert_eq!(mask_from_alpha(&a, 0.0), vec![false]);
    }

    #[test]
    fn albedo_scale_is_the_least_squares_solution() {
        // R: pred (1, 2), target (1, 3) → (1 + 6) / (1 + 4) = 1.4.
        // G: target = 2·pred exactly → 2.  B: pred 0 → 1 (no signal).
        // The third pixel is masked out and would change every scale.
        let pred = img(3, 1, 4, &[1.0, 0.25, 0.0, 1.0, 2.0, 0.5, 0.0, 1.0, 9.0, 9.0, 9.0, 0.0]);
        let target = img(3, 1, 4, &[1.0, 0.5, 0.3, 1.0, 3.0, 1.0, 0.7, 1.0, 0.0, 0.0, 0.0, 0.0]);
        let mask = mask_from_alpha(&pred, 0.9);
        let s = albedo_scale(&pred, &target, Some(&mask));
        assert!((s[0] - 1.4).abs() < 1e-12 && (s[1] - 2.0).abs() < 1e-12 && s[2] == 1.0, "{s:?}");
        let scaled = scale_colour(&pred, s);
        assert!((scaled.data[1] - 0.5).abs() < 1e-7 && scaled.data[3] == 1.0);
        // Residual is orthogonal to pred: nudging the scale can only increase the error.
        let e0 = mse(&scale_colour(&pred, s), &target, Some(&mask));
        let e1 = mse(&scale_colour(&pred, [s[0] * 1.01, s[1], s[2]]), &target, Some(&mask));
        assert!(e1 > e0);
    }

    #[test]
    fn angular_error_in_degrees() {
        let s = std::f32::consts::FRAC_1_SQRT_2;
        // 45° and 90°; the third pixel is background (zero) and is skipped; inputs need not be unit.
        let a = img(3, 1, 3, &[0.0, 0.0, 2.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0]);
        let b = img(3, 1, 3, &[s, 0.0, s, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0]);
        assert!((mean_angular_error_deg(&a, &b, None) - 67.5).abs() < 1e-4);
        assert!((mean_angular_error_deg(&a, &b, Some(&[true, false, true])) - 45.0).abs() < 1e-4);
        assert!((mean_angular_error_deg(&a, &a, None)).abs() < 1e-6);
    }

    #[test]
    fn iou_of_known_masks() {
        // 2 pixels in both, 4 in either → 1/2; disjoint → 0; identical → 1; both empty → 1.
        let a = [true, true, true, false, false];
        let b = [false, true, true, true, false];
        assert_eq!(mask_iou(&a, &b), 0.5);
        assert_eq!(mask_iou(&[true, false], &[false, true]), 0.0);
        assert_eq!(mask_iou(&a, &a), 1.0);
        assert_eq!(mask_iou(&[false; 3], &[false; 3]), 1.0);
    }

    #[test]
    fn compositing_over_white_then_srgb() {
        let rgb = img(3, 1, 3, &[0.5, 0.5, 0.5, 0.0, 0.0, 0.0, 0.3, 2.0, 0.0]);
        let alpha = img(3, 1, 1, &[0.5, 0.0, 1.0]);
        let out = over_white(&rgb, &alpha);
        // 0.5·0.5 + 0.5 = 0.75 linear → 1.055·0.75^(1/2.4) − 0.055 = 0.880825.
        assert!((out.data[0] - 0.880_825).abs() < 2e-5, "{}", out.data[0]);
        // α = 0 is pure white; α = 1 keeps the colour (clamped to 1 above), 0.3 → 0.583831.
        assert!(out.data[3..6].iter().all(|v| (v - 1.0).abs() < 1e-6));
        assert!((out.data[6] - 0.583_831).abs() < 2e-5 && (out.data[7] - 1.0).abs() < 1e-6 && out.data[8] == 0.0);
    }
}

//! Accuracy of intrinsic labels against ground truth, as IDArb's paper reports it: scale-invariant
//! albedo PSNR, normal cosine similarity, roughness and metallic MSE — all over the mask.
//!
//! Scale-invariant albedo PSNR: both albedos are decoded from sRGB to linear, the prediction gets
//! the per-channel least-squares scale that best fits the truth (as the NeRFactor protocol), then
//! both are re-encoded and compared in sRGB.

use crate::color::{linear_to_srgb, srgb_to_linear};
use crate::image::Image;

fn masked<'a>(mask: &'a Image) -> impl Iterator<Item = usize> + 'a {
    (0..mask.pixel_count()).filter(|&i| mask.data[i * mask.channels] > 0.5)
}

/// PSNR (dB) of sRGB-encoded albedo `pred` against `truth` after a per-channel scale in linear space.
pub fn scale_invariant_albedo_psnr(pred: &Image, truth: &Image, mask: &Image) -> f64 {
    let lin = |img: &Image, i: usize, c: usize| srgb_to_linear(img.data[i * img.channels + c]) as f64;
    let mut scale = [1.0f64; 3];
    for (c, s) in scale.iter_mut().enumerate() {
        let (mut pt, mut pp) = (0.0, 0.0);
        for i in masked(mask) {
            pt += lin(pred, i, c) * lin(truth, i, c);
            pp += lin(pred, i, c) * lin(pred, i, c);
        }
        if pp > 0.0 {
            *s = pt / pp;
        }
    }
    let (mut sum, mut n) = (0.0f64, 0usize);
    for i in masked(mask) {
        for (c, s) in scale.iter().enumerate() {
            let p = linear_to_srgb((lin(pred, i, c) * s).clamp(0.0, 1.0) as f32) as f64;
            let d = p - truth.data[i * truth.channels + c] as f64;
            sum += d * d;
            n += 1;
        }
    }
    -10.0 * (sum / n.max(1) as f64).log10()
}

/// Mean cosine between normals encoded (n + 1)/2 (zero-length ones skipped).
pub fn normal_cosine_similarity(pred: &Image, truth: &Image, mask: &Image) -> f64 {
    let dec = |img: &Image, i: usize| glam::Vec3::from_slice(&img.data[i * img.channels..i * img.channels + 3]) * 2.0 - glam::Vec3::ONE;
    let (mut sum, mut n) = (0.0f64, 0usize);
    for i in masked(mask) {
        let (a, b) = (dec(pred, i), dec(truth, i));
        if a.length() > 1e-3 && b.length() > 1e-3 {
            sum += a.normalize().dot(b.normalize()) as f64;
            n += 1;
        }
    }
    sum / n.max(1) as f64
}

/// Mean squared error of the first channel over the mask.
pub fn masked_mse(pred: &Image, truth: &Image, mask: &Image) -> f64 {
    let (mut sum, mut n) = (0.0f64, 0usize);
    for i in masked(mask) {
        let d = pred.data[i * pred.channels] as f64 - truth.data[i * truth.channels] as f64;
        sum += d * d;
        n += 1;
    }
    sum / n.max(1) as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn metrics_match_hand_computed_values() {
        let mask = Image::filled(2, 1, &[1.0]);
        // A scaled albedo is perfect under the scale-invariant metric.
        let truth = Image::filled(2, 1, &[0.5, 0.4, 0.3]).srgb_to_linear();
        let truth_srgb = truth.linear_to_srgb();
        let half = Image { data: truth.data.iter().map(|v| v * 0.5).collect(), ..truth.clone() }.linear_to_srgb();
        assert!(scale_invariant_albedo_psnr(&half, &truth_srgb, &mask) > 60.0);
        // Normals 90° apart: cosine 0; equal: 1.
        let x = Image::filled(2, 1, &[1.0, 0.5, 0.5]);
        let y = Image::filled(2, 1, &[0.5, 1.0, 0.5]);
        assert!(normal_cosine_similarity(&x, &y, &mask).abs() < 1e-6);
        assert!((normal_cosine_similarity(&x, &x, &mask) - 1.0).abs() < 1e-6);
        // MSE over the mask only.
        let a = Image { width: 2, height: 1, channels: 1, data: vec![0.2, 0.9] };
        let b = Image { width: 2, height: 1, channels: 1, data: vec![0.5, 0.0] };
        let m = Image { width: 2, height: 1, channels: 1, data: vec![1.0, 0.0] };
        assert!((masked_mse(&a, &b, &m) - 0.09).abs() < 1e-6);
    }
}

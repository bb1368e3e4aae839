//! The labels of one view, the type every label source returns (the IDArb network, label files,
//! the oracle, simulated IDArb): the four material maps and the mask they cover. Here, beside the
//! `Prior` trait, so that the sources that never run the network do not depend on its code.

use crate::image::Image;

/// Labels of one view, at the view's original size; values in [0, 1].
#[derive(Debug, Clone)]
pub struct ViewLabels {
    /// Base colour, sRGB-encoded (as IDArb predicts it). 3 channels.
    pub albedo: Image,
    /// Camera-space normal encoded (n + 1)/2. 3 channels.
    pub normal: Image,
    /// Red channel of the third map. 1 channel.
    pub metallic: Image,
    /// Green channel of the third map. 1 channel.
    pub roughness: Image,
    /// Where the labels hold: for IDArb, the input mask (alpha > 0.5) the network saw, mapped
    /// back. 1 channel.
    pub mask: Image,
}

impl ViewLabels {
    /// The labels `factor`× smaller, for training at a reduced resolution: each map is averaged
    /// over its `factor`² block weighted by the mask (a pixel outside the labeller's mask says
    /// nothing, so it must not pull its block's value), and the mask is the block's mean. A block
    /// with no masked pixel keeps zeros. Normals are averaged encoded, which averages the vectors;
    /// their users renormalise.
    pub fn downsampled(&self, factor: usize) -> anyhow::Result<ViewLabels> {
        let (w, h) = (self.mask.width, self.mask.height);
        anyhow::ensure!(factor >= 1 && w % factor == 0 && h % factor == 0, "labels of {w}×{h} pixels do not divide by {factor}");
        if factor == 1 {
            return Ok(self.clone());
        }
        let reduce = |img: &Image| -> anyhow::Result<Image> {
            anyhow::ensure!(img.width == w && img.height == h, "a {}×{} label map beside a {w}×{h} mask", img.width, img.height);
            Ok(img.downsample_weighted(&self.mask, factor))
        };
        Ok(ViewLabels {
            albedo: reduce(&self.albedo)?,
            normal: reduce(&self.normal)?,
            metallic: reduce(&self.metallic)?,
            roughness: reduce(&self.roughness)?,
            mask: self.mask.downsample_box(factor),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn map(w: usize, h: usize, c: usize, f: impl Fn(usize, usize) -> f32) -> Image {
        let mut img = Image::new(w, h, c);
        for y in 0..h {
            for x in 0..w {
                img.data[(y * w + x) * c..(y * w + x + 1) * c].fill(f(x, y));
            }
        }
        img
    }

    #[test]
    fn downsampling_weighs_by_the_mask() {
        // Left column masked with value 0.8, right column unmasked with value 0.1 (ignored).
        let value = |x: usize, _| if x.is_multiple_of(2) { 0.8 } else { 0.1 };
        let mask = map(4, 2, 1, |x, _| if x.is_multiple_of(2) { 1.0 } else { 0.0 });
        let labels = ViewLabels { albedo: map(4, 2, 3, value), normal: map(4, 2, 3, value), metallic: map(4, 2, 1, value), roughness: map(4, 2, 1, value), mask };
        let small = labels.downsampled(2).expect("4×2 divides by 2");
        assert_eq!((small.mask.width, small.mask.height), (2, 1));
        assert_eq!(small.mask.data, vec![0.5, 0.5]);
        for img in [&small.albedo, &small.normal, &small.metallic, &small.roughness] {
            assert!(img.data.iter().all(|&v| (v - 0.8).abs() < 1e-6), "{:?}", img.data);
        }
        assert!(labels.downsampled(3).is_err());
        let empty = ViewLabels { mask: Image::new(4, 2, 1), ..labels };
        assert!(empty.downsampled(2).expect("divides").albedo.data.iter().all(|&v| v == 0.0));
    }
}

use glam::{Vec3, Vec4};

use crate::math::floor_f32;

/// An image of `channels` interleaved f32 values per pixel, row 0 at the top.
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    pub width: usize,
    pub height: usize,
    pub channels: usize,
    pub data: Vec<f32>,
}

impl Image {
    pub fn new(width: usize, height: usize, channels: usize) -> Self {
        Image { width, height, channels, data: vec![0.0; width * height * channels] }
    }

    pub fn filled(width: usize, height: usize, value: &[f32]) -> Self {
        let mut data = Vec::with_capacity(width * height * value.len());
        for _ in 0..width * height {
            data.extend_from_slice(value);
        }
        Image { width, height, channels: value.len(), data }
    }

    pub fn pixel_count(&self) -> usize {
        self.width * self.height
    }

    /// The first NaN or infinite value as (x, y, channel, value), row-major order; None when all are finite.
    pub fn first_non_finite(&self) -> Option<(usize, usize, usize, f32)> {
        let c = self.channels.max(1);
        let w = self.width.max(1);
        self.data.iter().position(|v| !v.is_finite()).map(|k| ((k / c) % w, k / c / w, k % c, self.data[k]))
    }

    /// Ok, or an error naming `what` (a file or view) and the first non-finite pixel.
    pub fn require_finite(&self, what: &str) -> anyhow::Result<()> {
        match self.first_non_finite() {
            None => Ok(()),
            Some((x, y, c, v)) => anyhow::bail!("{what}: pixel ({x}, {y}) channel {c} is {v} (values must be finite)"),
        }
    }

    pub fn pixel(&self, x: usize, y: usize) -> &[f32] {
        let i = (y * self.width + x) * self.channels;
        &self.data[i..i + self.channels]
    }

    pub fn pixel_mut(&mut self, x: usize, y: usize) -> &mut [f32] {
        let i = (y * self.width + x) * self.channels;
        &mut self.data[i..i + self.channels]
    }

    /// The first three channels of pixel `i` (row-major index).
    pub fn rgb(&self, i: usize) -> Vec3 {
        let p = &self.data[i * self.channels..];
        match self.channels {
            1 | 2 => Vec3::splat(p[0]),
            _ => Vec3::new(p[0], p[1], p[2]),
        }
    }

    /// RGBA of pixel `i`; alpha 1 when the image has none.
    pub fn rgba(&self, i: usize) -> Vec4 {
        let a = if self.channels == 4 || self.channels == 2 { self.data[i * self.channels + self.channels - 1] } else { 1.0 };
        self.rgb(i).extend(a)
    }

    pub fn set_rgb(&mut self, i: usize, v: Vec3) {
        let c = self.channels;
        let p = &mut self.data[i * c..];
        p[0] = v.x;
        if c >= 3 {
            p[1] = v.y;
            p[2] = v.z;
        }
    }

    /// One channel as its own single-channel image.
    pub fn channel(&self, c: usize) -> Image {
        let data = self.data.chunks_exact(self.channels).map(|p| p[c]).collect();
        Image { width: self.width, height: self.height, channels: 1, data }
    }

    /// Apply `f` to every value (e.g. a transfer curve) on the first `n` channels.
    pub fn map_channels(&self, n: usize, f: impl Fn(f32) -> f32) -> Image {
        let mut out = self.clone();
        for p in out.data.chunks_exact_mut(self.channels) {
            for v in p.iter_mut().take(n) {
                *v = f(*v);
            }
        }
        out
    }

    /// Number of colour channels: 1 for grey / grey+alpha, 3 for RGB / RGBA.
    pub fn colour_channels(&self) -> usize {
        match self.channels {
            1 | 2 => 1,
            c => c.min(3),
        }
    }

    /// sRGB-encoded colour to linear (exact curve); alpha is left as is.
    pub fn srgb_to_linear(&self) -> Image {
        self.map_channels(self.colour_channels(), crate::color::srgb_to_linear)
    }

    /// Linear colour to sRGB encoding (exact curve, not clipped above 1); alpha is left as is.
    pub fn linear_to_srgb(&self) -> Image {
        self.map_channels(self.colour_channels(), crate::color::linear_to_srgb)
    }

    /// Bilinear lookup at continuous pixel coordinates (pixel centres at +0.5), clamped to the edge.
    pub fn bilinear(&self, x: f32, y: f32, out: &mut [f32]) {
        let fx = (x - 0.5).clamp(0.0, (self.width - 1) as f32);
        let fy = (y - 0.5).clamp(0.0, (self.height - 1) as f32);
        let (x0, y0) = (floor_f32(fx) as usize, floor_f32(fy) as usize);
        let (x1, y1) = ((x0 + 1).min(self.width - 1), (y0 + 1).min(self.height - 1));
        let (tx, ty) = (fx - x0 as f32, fy - y0 as f32);
        for c in 0..self.channels.min(out.len()) {
            let a = self.pixel(x0, y0)[c] * (1.0 - tx) + self.pixel(x1, y0)[c] * tx;
            let b = self.pixel(x0, y1)[c] * (1.0 - tx) + self.pixel(x1, y1)[c] * tx;
            out[c] = a * (1.0 - ty) + b * ty;
        }
    }

    /// RGBA with colour divided by alpha where alpha > 0: premultiplied back to straight alpha,
    /// as the datasets store it.
    pub fn unpremultiplied(mut self) -> Image {
        debug_assert_eq!(self.channels, 4);
        for p in self.data.chunks_exact_mut(4) {
            let alpha = p[3];
            if alpha > 0.0 {
                for c in &mut p[..3] {
                    *c /= alpha;
                }
            }
        }
        self
    }

    /// `self` reduced `factor`× by a box filter weighted by `weight` (one channel, `self`'s size):
    /// each block's weighted mean, 0 where the block weighs nothing. What
    /// [`Image::downsample_straight_alpha`] does with the alpha in the image, for a weight held
    /// apart (a label map and its mask). `factor` must divide both sides.
    pub fn downsample_weighted(&self, weight: &Image, factor: usize) -> Image {
        assert!(weight.channels == 1 && weight.width == self.width && weight.height == self.height);
        let mut weighted = self.clone();
        for (px, w) in weighted.data.chunks_exact_mut(self.channels).zip(&weight.data) {
            px.iter_mut().for_each(|v| *v *= w);
        }
        let block_weight = weight.downsample_box(factor);
        let mut out = weighted.downsample_box(factor);
        for (px, &w) in out.data.chunks_exact_mut(self.channels).zip(&block_weight.data) {
            px.iter_mut().for_each(|v| *v = if w > 0.0 { *v / w } else { 0.0 });
        }
        out
    }

    /// Straight-alpha RGBA reduced `factor`× by the box filter done right for alpha: the
    /// premultiplied colour is averaged, then divided by the averaged alpha (averaging straight
    /// colour would let the background's arbitrary colour bleed into outline pixels).
    pub fn downsample_straight_alpha(&self, factor: usize) -> Image {
        self.premultiplied().downsample_box(factor).unpremultiplied()
    }

    /// Straight-alpha RGBA with its colour multiplied by alpha: the form that filters correctly.
    fn premultiplied(&self) -> Image {
        let mut pre = self.clone();
        for p in pre.data.chunks_exact_mut(4) {
            let a = p[3];
            p[..3].iter_mut().for_each(|c| *c *= a);
        }
        pre
    }

    /// Straight-alpha RGBA resampled to `width`×`height` with a filter as wide as the reduction
    /// (the `image` crate's triangle filter, whose support grows with the ratio, so every source
    /// pixel contributes), on premultiplied colour as in [`Image::downsample_straight_alpha`].
    /// For any ratio, where `downsample_straight_alpha` needs a whole factor.
    pub fn resized_straight_alpha(&self, width: usize, height: usize) -> anyhow::Result<Image> {
        anyhow::ensure!(self.channels == 4, "resampling with alpha: {} channels, RGBA expected", self.channels);
        let buffer = image::Rgba32FImage::from_raw(self.width as u32, self.height as u32, self.premultiplied().data)
            .ok_or_else(|| anyhow::anyhow!("resampling: {} values for a {}×{} RGBA image", self.data.len(), self.width, self.height))?;
        let out = image::imageops::resize(&buffer, width as u32, height as u32, image::imageops::FilterType::Triangle);
        Ok(Image { width, height, channels: 4, data: out.into_raw() }.unpremultiplied())
    }

    /// Average `factor`×`factor` blocks (box filter), e.g. to resolve a supersampled render.
    pub fn downsample_box(&self, factor: usize) -> Image {
        assert!(factor >= 1 && self.width.is_multiple_of(factor) && self.height.is_multiple_of(factor));
        let (w, h, c) = (self.width / factor, self.height / factor, self.channels);
        let mut out = Image::new(w, h, c);
        let norm = 1.0 / (factor * factor) as f32;
        for y in 0..h {
            for x in 0..w {
                let dst = (y * w + x) * c;
                for sy in 0..factor {
                    for sx in 0..factor {
                        let src = self.pixel(x * factor + sx, y * factor + sy);
                        for (o, s) in out.data[dst..dst + c].iter_mut().zip(src) {
                            *o += s * norm;
                        }
                    }
                }
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn resampling_with_alpha_keeps_the_colour_under_partial_coverage_and_the_covered_area() -> anyhow::Result<()> {
        // A disc of one colour on a background of another colour with zero alpha: straight colour
        // averaging would let the background bleed into the outline; premultiplied must not.
        let (w, h) = (64, 48);
        let mut img = Image::new(w, h, 4);
        for y in 0..h {
            for x in 0..w {
                let inside = ((x as f32 - 30.0).powi(2) + (y as f32 - 22.0).powi(2)).sqrt() < 15.0;
                img.pixel_mut(x, y).copy_from_slice(&if inside { [0.2, 0.5, 0.9, 1.0] } else { [5.0, 0.0, 3.0, 0.0] });
            }
        }
        let small = img.resized_straight_alpha(45, 34)?;
        assert_eq!((small.width, small.height, small.channels), (45, 34, 4));
        let mean_alpha = |i: &Image| i.data.chunks_exact(4).map(|p| p[3] as f64).sum::<f64>() / i.pixel_count() as f64;
        assert!((mean_alpha(&small) - mean_alpha(&img)).abs() < 0.01, "{} vs {}", mean_alpha(&small), mean_alpha(&img));
        let mut partial = 0;
        for p in small.data.chunks_exact(4).filter(|p| p[3] > 1e-3) {
            partial += (p[3] < 0.999) as usize;
            for (c, want) in p[..3].iter().zip([0.2, 0.5, 0.9]) {
                assert!((c - want).abs() < 1e-4, "{p:?}");
            }
        }
        assert!(partial > 10, "the outline should hold partly covered pixels");
        assert!(Image::new(4, 4, 3).resized_straight_alpha(2, 2).is_err());
        Ok(())
    }

    #[test]
    fn bilinear_hits_pixel_centres_and_midpoints() {
        let mut img = Image::new(2, 1, 1);
        img.data = vec![1.0, 3.0];
        let mut v = [0.0];
        img.bilinear(0.5, 0.5, &mut v);
        assert_eq!(v[0], 1.0);
        img.bilinear(1.0, 0.5, &mut v);
        assert_eq!(v[0], 2.0);
        img.bilinear(5.0, 0.5, &mut v);
        assert_eq!(v[0], 3.0);
    }

    #[test]
    fn box_downsample_averages_blocks() {
        let mut img = Image::new(2, 2, 1);
        img.data = vec![1.0, 2.0, 3.0, 6.0];
        assert_eq!(img.downsample_box(2).data, vec![3.0]);
    }
}

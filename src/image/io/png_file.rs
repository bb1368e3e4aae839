//! PNG: 8- and 16-bit, grey / grey-alpha / RGB / RGBA (palette images are expanded).

use std::path::Path;

use anyhow::{bail, Context, Result};
use image::{DynamicImage, ImageBuffer, ImageFormat};

use super::require_file;
use crate::image::safe_decode::decode_with_image_crate;
use crate::image::Image;

/// Read a PNG; values are the stored codes divided by 255 (or 65535), no transfer curve.
pub fn read_png(path: &Path) -> Result<Image> {
    require_file(path, "PNG image")?;
    let format = image::ImageReader::open(path)
        .with_context(|| format!("cannot open PNG image {}", path.display()))?
        .with_guessed_format()
        .with_context(|| format!("cannot read PNG image {}", path.display()))?
        .format();
    if format != Some(ImageFormat::Png) {
        bail!("{} is not a PNG file (its content is {:?})", path.display(), format);
    }
    let decoded = decode_with_image_crate(path, "PNG image")?;
    let (w, h) = (decoded.width() as usize, decoded.height() as usize);
    let (channels, data): (usize, Vec<f32>) = match decoded {
        DynamicImage::ImageLuma8(b) => (1, scale8(b.as_raw())),
        DynamicImage::ImageLumaA8(b) => (2, scale8(b.as_raw())),
        DynamicImage::ImageRgb8(b) => (3, scale8(b.as_raw())),
        DynamicImage::ImageRgba8(b) => (4, scale8(b.as_raw())),
        DynamicImage::ImageLuma16(b) => (1, scale16(b.as_raw())),
        DynamicImage::ImageLumaA16(b) => (2, scale16(b.as_raw())),
        DynamicImage::ImageRgb16(b) => (3, scale16(b.as_raw())),
        DynamicImage::ImageRgba16(b) => (4, scale16(b.as_raw())),
        other => bail!("unsupported PNG pixel layout {:?} in {}", other.color(), path.display()),
    };
    Ok(Image { width: w, height: h, channels, data })
}

fn scale8(v: &[u8]) -> Vec<f32> {
    v.iter().map(|&c| c as f32 / 255.0).collect()
}

fn scale16(v: &[u16]) -> Vec<f32> {
    v.iter().map(|&c| c as f32 / 65535.0).collect()
}

fn quantise(v: f32, max: f32) -> f32 {
    // NaN becomes 0 rather than poisoning the file.
    let v = if v.is_nan() { 0.0 } else { v.clamp(0.0, 1.0) };
    (v * max).round()
}

/// Write an 8-bit PNG: values clamped to [0, 1] and rounded (no transfer curve applied).
/// 1 = grey, 2 = grey + alpha, 3 = RGB, 4 = RGBA channels.
pub fn write_png(path: &Path, img: &Image) -> Result<()> {
    let (w, h) = (img.width as u32, img.height as u32);
    let raw: Vec<u8> = img.data.iter().map(|&v| quantise(v, 255.0) as u8).collect();
    let too_small = || format!("image data too small for {}x{}x{}", w, h, img.channels);
    let dynimg = match img.channels {
        1 => DynamicImage::ImageLuma8(ImageBuffer::from_raw(w, h, raw).with_context(too_small)?),
        2 => DynamicImage::ImageLumaA8(ImageBuffer::from_raw(w, h, raw).with_context(too_small)?),
        3 => DynamicImage::ImageRgb8(ImageBuffer::from_raw(w, h, raw).with_context(too_small)?),
        4 => DynamicImage::ImageRgba8(ImageBuffer::from_raw(w, h, raw).with_context(too_small)?),
        c => bail!("cannot write {} as PNG: {c} channels (expected 1, 2, 3 or 4)", path.display()),
    };
    save(path, &dynimg)
}

/// Write a 16-bit PNG (values clamped to [0, 1], rounded to 1/65535), e.g. to mimic
/// NeRFactor's original renders.
pub fn write_png16(path: &Path, img: &Image) -> Result<()> {
    let (w, h) = (img.width as u32, img.height as u32);
    let raw: Vec<u16> = img.data.iter().map(|&v| quantise(v, 65535.0) as u16).collect();
    let too_small = || format!("image data too small for {}x{}x{}", w, h, img.channels);
    let dynimg = match img.channels {
        1 => DynamicImage::ImageLuma16(ImageBuffer::from_raw(w, h, raw).with_context(too_small)?),
        2 => DynamicImage::ImageLumaA16(ImageBuffer::from_raw(w, h, raw).with_context(too_small)?),
        3 => DynamicImage::ImageRgb16(ImageBuffer::from_raw(w, h, raw).with_context(too_small)?),
        4 => DynamicImage::ImageRgba16(ImageBuffer::from_raw(w, h, raw).with_context(too_small)?),
        c => bail!("cannot write {} as PNG: {c} channels (expected 1, 2, 3 or 4)", path.display()),
    };
    save(path, &dynimg)
}

fn save(path: &Path, img: &DynamicImage) -> Result<()> {
    img.save_with_format(path, ImageFormat::Png)
        .with_context(|| format!("cannot write PNG image {}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn temp_path(name: &str) -> std::path::PathBuf {
        let dir = std::env::temp_dir().join(format!("reconstruct-png-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("test setup");
        dir.join(name)
    }

    #[test]
    fn every_8bit_code_survives_a_round_trip_for_each_channel_count() {
        for channels in 1..=4 {
            let mut img = Image::new(256, 1, channels);
            for (i, v) in img.data.iter_mut().enumerate() {
                *v = ((i * 7) % 256) as f32 / 255.0;
            }
            let p = temp_path(&format!("codes{channels}.png"));
            write_png(&p, &img).expect("test setup");
            let back = read_png(&p).expect("test setup");
            assert_eq!((back.width, back.height, back.channels), (256, 1, channels));
            assert_eq!(back.data, img.data);
        }
    }

    #[test]
    fn writing_clamps_and_rounds() {
        let mut img = Image::new(4, 1, 1);
        img.data = vec![-0.5, 1.7, 0.5 / 255.0 + 1e-4, 0.49 / 255.0];
        let p = temp_path("clamp.png");
        write_png(&p, &img).expect("test setup");
        let back = read_png(&p).expect("test setup");
        assert_eq!(back.data, vec![0.0, 1.0, 1.0 / 255.0, 0.0]);
    }

    #[test]
    fn sixteen_bit_keeps_its_precision() {
        let mut img = Image::new(3, 2, 4);
        for (i, v) in img.data.iter_mut().enumerate() {
            *v = (i as f32 * 1234.0 % 65536.0) / 65535.0;
        }
        let p = temp_path("deep.png");
        write_png16(&p, &img).expect("test setup");
        let back = read_png(&p).expect("test setup");
        for (a, b) in back.data.iter().zip(&img.data) {
            assert!((a - b).abs() < 0.6 / 65535.0, "{a} vs {b}");
        }
    }

    #[test]
    fn a_file_that_is_not_png_is_refused_naming_it() {
        let p = temp_path("fake.png");
        std::fs::write(&p, b"definitely not a picture").expect("test setup");
        let msg = format!("{:#}", read_png(&p).unwrap_err());
        assert!(msg.contains("fake.png"), "{msg}");
    }
}

//! Base-colour texture files for the mesh loaders: sRGB-encoded PNGs decoded to linear RGB.
//! (Read with the `image` crate directly so geometry IO does not depend on `image::io`.)

use std::path::Path;
use std::sync::Arc;

use anyhow::{Context, Result};

use crate::color::{linear_to_srgb, srgb_to_linear};
use crate::image::Image;

/// Read an sRGB-encoded colour texture (8- or 16-bit; alpha dropped) as a linear RGB image.
pub fn load_srgb_texture(path: &Path) -> Result<Arc<Image>> {
    let decoded = image::open(path).with_context(|| format!("reading texture {}", path.display()))?;
    let rgb = decoded.to_rgb32f();
    let (width, height) = (rgb.width() as usize, rgb.height() as usize);
    let data = rgb.into_raw().into_iter().map(srgb_to_linear).collect();
    Ok(Arc::new(Image { width, height, channels: 3, data }))
}

/// Linear RGB(A) image → 8-bit sRGB PNG (used for exports and round-trip tests).
pub fn save_srgb_texture(path: &Path, img: &Image) -> Result<()> {
    let mut bytes = Vec::with_capacity(img.pixel_count() * 3);
    for i in 0..img.pixel_count() {
        let c = img.rgb(i);
        for v in [c.x, c.y, c.z] {
            bytes.push((linear_to_srgb(v).clamp(0.0, 1.0) * 255.0).round() as u8);
        }
    }
    let buf = image::RgbImage::from_raw(img.width as u32, img.height as u32, bytes)
        .with_context(|| format!("texture {} has inconsistent size", path.display()))?;
    buf.save(path).with_context(|| format!("writing texture {}", path.display()))
}

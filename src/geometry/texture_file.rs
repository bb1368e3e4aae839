//! Material texture files for the mesh loaders: sRGB-encoded base-colour images decoded to linear
//! RGB, and linear single-value images (roughness, metallic) read as stored.
//! (Read with the `image` crate directly, through `image::safe_decode`'s size limit and panic guard,
//! so geometry IO does not depend on `image::io`.)

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{bail, Context, Result};

use crate::color::{linear_to_srgb, srgb_to_linear};
use crate::image::safe_decode::decode_with_image_crate;
use crate::image::Image;

/// Read an sRGB-encoded colour texture (8- or 16-bit; alpha dropped) as a linear RGB image.
pub fn load_srgb_texture(path: &Path) -> Result<Arc<Image>> {
    let decoded = decode_with_image_crate(path, "texture")?;
    let rgb = decoded.to_rgb32f();
    let (width, height) = (rgb.width() as usize, rgb.height() as usize);
    let data = rgb.into_raw().into_iter().map(srgb_to_linear).collect();
    Ok(Arc::new(Image { width, height, channels: 3, data }))
}

/// Read one channel (0 = red or grey, 1 = green, 2 = blue, 3 = alpha) of a texture whose values
/// are linear (roughness, metallic): 8/16-bit codes divided by their maximum, no transfer curve.
pub fn load_linear_texture(path: &Path, channel: usize) -> Result<Arc<Image>> {
    let decoded = decode_with_image_crate(path, "texture")?;
    // A grey image's value stands for every colour channel (to_rgba32f replicates it).
    if channel > 3 || (channel == 3 && !decoded.color().has_alpha()) {
        bail!("texture {} has no channel {channel} ({:?})", path.display(), decoded.color());
    }
    let rgba = decoded.to_rgba32f();
    let (width, height) = (rgba.width() as usize, rgba.height() as usize);
    let data = rgba.into_raw().chunks_exact(4).map(|p| p[channel]).collect();
    Ok(Arc::new(Image { width, height, channels: 1, data }))
}

/// Decoded texture files by (file, channel), so materials sharing a file decode it once.
#[derive(Default)]
pub struct TextureCache(HashMap<(PathBuf, Option<usize>), Arc<Image>>);

impl TextureCache {
    /// [`load_srgb_texture`], cached.
    pub fn srgb(&mut self, path: &Path) -> Result<Arc<Image>> {
        self.get(path, None)
    }

    /// [`load_linear_texture`], cached.
    pub fn linear(&mut self, path: &Path, channel: usize) -> Result<Arc<Image>> {
        self.get(path, Some(channel))
    }

    fn get(&mut self, path: &Path, channel: Option<usize>) -> Result<Arc<Image>> {
        let key = (path.to_path_buf(), channel);
        if let Some(t) = self.0.get(&key) {
            return Ok(t.clone());
        }
        let t = match channel {
            None => load_srgb_texture(path)?,
            Some(c) => load_linear_texture(path, c)?,
        };
        self.0.insert(key, t.clone());
        Ok(t)
    }
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

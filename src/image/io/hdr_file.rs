//! Radiance RGBE (.hdr), the format of NeRFactor's light probes.

use std::fs::File;
use std::io::BufReader;
use std::path::Path;

use anyhow::{bail, Context, Result};
use image::codecs::hdr::HdrDecoder;
use image::{DynamicImage, ImageDecoder};

use super::require_file;
use crate::image::safe_decode::{check_dimensions, guard};
use crate::image::Image;

/// Read a Radiance .hdr file as linear RGB (3 channels).
///
/// RGBE texels decode as m·2^(e−136) (no half-code offset), as OpenCV does (NeRFactor reads its
/// probes with OpenCV) and as the shared hotdog renders assume; Radiance's own and Blender's
/// readers add 0.5 to m, which differs by up to 0.5/m (e.g. 0.3 % at m = 182).
pub fn read_hdr(path: &Path) -> Result<Image> {
    require_file(path, "Radiance HDR image")?;
    let decoded = guard(path, "Radiance HDR image", || {
        let file = File::open(path).with_context(|| format!("cannot open HDR image {}", path.display()))?;
        let decoder = HdrDecoder::new(BufReader::new(file))
            .with_context(|| format!("cannot read {} as a Radiance .hdr file", path.display()))?;
        let (w, h) = decoder.dimensions();
        check_dimensions(path, w as u64, h as u64)?;
        DynamicImage::from_decoder(decoder).with_context(|| format!("cannot decode Radiance HDR image {}", path.display()))
    })?;
    let (width, height) = (decoded.width() as usize, decoded.height() as usize);
    let data = match decoded {
        DynamicImage::ImageRgb32F(b) => b.into_raw(),
        other => bail!("unexpected pixel layout {:?} in {}", other.color(), path.display()),
    };
    Ok(Image { width, height, channels: 3, data })
}

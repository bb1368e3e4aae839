//! Reading and writing pictures: PNG (8/16-bit), Radiance HDR, OpenEXR.
//!
//! Every reader returns values exactly as stored (PNG codes scaled to [0, 1], no transfer
//! curve); colour-space decisions belong to the caller (see `crate::color`). Every error
//! names the file and says what is wrong.

mod exr_file;
mod hdr_file;
mod png_file;

use std::path::Path;

use anyhow::{bail, Result};

use super::Image;

pub use exr_file::{read_exr, read_exr_channel, write_exr, write_exr_channels};
pub use hdr_file::read_hdr;
pub use png_file::{read_png, write_png, write_png16};

/// Fails with a clear message when `path` does not exist (before a decoder gives a vaguer one).
pub(crate) fn require_file(path: &Path, what: &str) -> Result<()> {
    if !path.exists() {
        bail!("{what} not found: {}", path.display());
    }
    if path.is_dir() {
        bail!("{what} {} is a folder, expected a file", path.display());
    }
    Ok(())
}

/// A light probe (lat-long environment map) as linear RGB, from a Radiance `.hdr` or an
/// OpenEXR `.exr` file (chosen by extension). Alpha, if any, is dropped.
pub fn read_probe(path: &Path) -> Result<Image> {
    let ext = path.extension().and_then(|e| e.to_str()).map(|e| e.to_ascii_lowercase());
    let img = match ext.as_deref() {
        Some("hdr") | Some("pic") => read_hdr(path)?,
        Some("exr") => read_exr(path)?,
        _ => bail!(
            "unsupported light probe format: {} (expected a Radiance .hdr or OpenEXR .exr file)",
            path.display()
        ),
    };
    Ok(to_rgb(&img))
}

/// The colour channels of an image as a 3-channel image (grey is replicated, alpha dropped).
pub fn to_rgb(img: &Image) -> Image {
    if img.channels == 3 {
        return img.clone();
    }
    let mut out = Image::new(img.width, img.height, 3);
    for i in 0..img.pixel_count() {
        out.set_rgb(i, img.rgb(i));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn probe_with_unknown_extension_is_refused_naming_the_file() {
        let err = read_probe(Path::new("/nowhere/light.png")).unwrap_err();
        let msg = format!("{err:#}");
        assert!(msg.contains("/nowhere/light.png") && msg.contains("unsupported"), "{msg}");
    }

    #[test]
    fn missing_probe_names_the_file() {
        let err = read_probe(Path::new("/nowhere/light.hdr")).unwrap_err();
        let msg = format!("{err:#}");
        assert!(msg.contains("/nowhere/light.hdr") && msg.contains("not found"), "{msg}");
    }
}

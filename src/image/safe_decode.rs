//! What every picture decode goes through: a size limit checked on the header before any pixel is
//! allocated, and a panic inside a third-party decoder turned into an error naming the file.
//!
//! Why both: a corrupt or hostile header can claim 2³¹ × 2³¹ pixels, which would be refused only when
//! the allocation fails (an abort, not an error) — so sizes are checked against [`MAX_IMAGE_SIDE`] and
//! [`MAX_IMAGE_PIXELS`] first. And the decoders (`image`, `exr`, `tobj`, `gltf`, `safetensors`) are
//! fuzzed by their authors but not guaranteed panic-free on every input; a panic there must not take
//! a run down without saying which file caused it.

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::Path;

use anyhow::{anyhow, bail, Result};

/// Largest width or height accepted: 2¹⁵ = 32768 holds the largest pictures the project reads,
/// 16k × 8k light probes (HDRI sites publish up to 16k wide) and 16k² textures, with a factor of two
/// to spare; views are at most a few thousand pixels on a side.
pub const MAX_IMAGE_SIDE: usize = 1 << 15;

/// Largest pixel count accepted: 2²⁸ (a 16k² texture). Decoded as 4 × f32 that is 4 GiB, the most
/// one picture may take on the 24 GiB machine this project is measured on while a run holds the
/// rest of its data; a file claiming more is refused before anything is allocated.
pub const MAX_IMAGE_PIXELS: usize = 1 << 28;

/// Refuses a header size outside the limits (or zero), naming the file.
pub fn check_dimensions(path: &Path, width: u64, height: u64) -> Result<()> {
    if width == 0 || height == 0 {
        bail!("{}: the header gives an empty image ({width}×{height})", path.display());
    }
    let side = MAX_IMAGE_SIDE as u64;
    if width > side || height > side || width.saturating_mul(height) > MAX_IMAGE_PIXELS as u64 {
        bail!(
            "{}: the header claims {width}×{height} pixels, more than this program reads ({MAX_IMAGE_SIDE} a side, {MAX_IMAGE_PIXELS} in all): corrupt or not meant for it",
            path.display()
        );
    }
    Ok(())
}

/// Runs `decode` (a third-party decoder reading `path`); a panic inside it becomes an error naming
/// the file and carrying the panic's message.
pub fn guard<T>(path: &Path, what: &str, decode: impl FnOnce() -> Result<T>) -> Result<T> {
    match catch_unwind(AssertUnwindSafe(decode)) {
        Ok(result) => result,
        Err(payload) => {
            let message = payload
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| payload.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "no message".into());
            Err(anyhow!("cannot read {what} {}: its decoder failed on it ({message}); the file is corrupt", path.display()))
        }
    }
}

/// Opens a picture with the `image` crate (format guessed from the content), checks the header's size
/// against the limits, then decodes, inside [`guard`]. `what` names the kind of file in errors.
pub fn decode_with_image_crate(path: &Path, what: &str) -> Result<image::DynamicImage> {
    use anyhow::Context;
    use image::ImageDecoder;
    guard(path, what, || {
        let mut reader = image::ImageReader::open(path)
            .with_context(|| format!("cannot open {what} {}", path.display()))?
            .with_guessed_format()
            .with_context(|| format!("cannot read {what} {}", path.display()))?;
        if reader.format().is_none() {
            bail!("{what} {} is in no picture format this program reads", path.display());
        }
        // Our limits first (their message says what the header claims), then the crate's for its buffers.
        reader.no_limits();
        let mut decoder = reader.into_decoder().with_context(|| format!("cannot read the header of {what} {}", path.display()))?;
        let (w, h) = decoder.dimensions();
        check_dimensions(path, w as u64, h as u64)?;
        decoder.set_limits(image_crate_limits()).with_context(|| format!("{what} {}: too large to decode", path.display()))?;
        image::DynamicImage::from_decoder(decoder)
            .with_context(|| format!("cannot decode {what} {} (corrupt or unsupported)", path.display()))
    })
}

/// The same limits for the `image` crate's own checks (it also bounds its intermediate buffers):
/// [`MAX_IMAGE_PIXELS`] at 16 bytes a pixel (four 32-bit channels, the widest layout it decodes to).
fn image_crate_limits() -> image::Limits {
    let mut limits = image::Limits::default();
    limits.max_image_width = Some(MAX_IMAGE_SIDE as u32);
    limits.max_image_height = Some(MAX_IMAGE_SIDE as u32);
    limits.max_alloc = Some(MAX_IMAGE_PIXELS as u64 * 16);
    limits
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sizes_beyond_the_limits_are_refused_naming_the_file() {
        let p = Path::new("/data/huge.png");
        assert!(check_dimensions(p, 800, 800).is_ok());
        assert!(check_dimensions(p, MAX_IMAGE_SIDE as u64, (MAX_IMAGE_PIXELS / MAX_IMAGE_SIDE) as u64).is_ok());
        for (w, h) in [(1u64 << 31, 1u64 << 31), (MAX_IMAGE_SIDE as u64 + 1, 1), (MAX_IMAGE_SIDE as u64, MAX_IMAGE_SIDE as u64), (0, 5)] {
            let msg = format!("{:#}", check_dimensions(p, w, h).unwrap_err());
            assert!(msg.contains("huge.png"), "{w}×{h}: {msg}");
        }
    }

    #[test]
    fn a_panicking_decoder_becomes_an_error_naming_the_file() {
        let r: Result<()> = guard(Path::new("/data/bad.exr"), "EXR image", || panic!("index out of bounds"));
        let msg = format!("{:#}", r.unwrap_err());
        assert!(msg.contains("bad.exr") && msg.contains("index out of bounds"), "{msg}");
    }
}

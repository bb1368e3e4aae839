//! Light probes: lat-long environment maps (Blender's equirect convention) with a strength.
//! The direction ↔ texel mapping lives in `crate::light::latlong`.

use std::path::Path;

use anyhow::{bail, Result};

use crate::image::io::read_probe;
use crate::image::Image;

#[derive(Clone, Debug)]
pub struct Probe {
    /// File stem, e.g. "2163" or "city".
    pub name: String,
    /// Linear RGB lat-long image as stored (strength not applied).
    pub image: Image,
    /// Radiance multiplier (NeRFactor: 3 for the training probe, 1 for the test probes).
    pub strength: f32,
}

impl Probe {
    /// Read a `.hdr` or `.exr` probe.
    pub fn load(path: &Path, strength: f32) -> Result<Probe> {
        if !strength.is_finite() || strength < 0.0 {
            bail!("light probe {}: strength must be finite and ≥ 0, got {strength}", path.display());
        }
        let image = read_probe(path)?;
        if image.width == 0 || image.height == 0 {
            bail!("light probe {} is empty", path.display());
        }
        image.require_finite(&format!("light probe {}", path.display()))?;
        if let Some(k) = image.data.iter().position(|v| *v < 0.0) {
            let (x, y) = ((k / 3) % image.width, k / 3 / image.width);
            bail!("light probe {} holds a negative value ({}) at pixel ({x}, {y})", path.display(), image.data[k]);
        }
        let name = path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
        Ok(Probe { name, image, strength })
    }

    /// The radiance the probe emits: image × strength.
    pub fn radiance_image(&self) -> Image {
        let mut out = self.image.clone();
        out.data.iter_mut().for_each(|v| *v *= self.strength);
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::image::io::write_exr;

    #[test]
    fn strength_scales_radiance_and_name_is_the_stem() {
        let dir = std::env::temp_dir().join(format!("reconstruct-probe-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("test setup");
        let mut img = Image::new(4, 2, 3);
        img.data.iter_mut().enumerate().for_each(|(i, v)| *v = i as f32 * 0.25);
        let path = dir.join("sky.exr");
        write_exr(&path, &img).expect("test setup");
        let probe = Probe::load(&path, 3.0).expect("test setup");
        assert_eq!(probe.name, "sky");
        assert_eq!(probe.image, img);
        let r = probe.radiance_image();
        assert_eq!(r.data[5], 5.0 * 0.25 * 3.0);
    }

    #[test]
    fn negative_radiance_is_refused_naming_the_file() {
        let dir = std::env::temp_dir().join(format!("reconstruct-probe-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("test setup");
        let path = dir.join("bad.exr");
        write_exr(&path, &Image::filled(2, 1, &[1.0, -1.0, 0.0])).expect("test setup");
        let msg = format!("{:#}", Probe::load(&path, 1.0).unwrap_err());
        assert!(msg.contains("bad.exr") && msg.contains("negative") && msg.contains("pixel (0, 0)"), "{msg}");
    }

    #[test]
    fn nan_or_inf_radiance_is_refused_naming_the_file_and_pixel() {
        let dir = std::env::temp_dir().join(format!("reconstruct-probe-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("test setup");
        for (name, bad) in [("nan.exr", f32::NAN), ("inf.exr", f32::INFINITY)] {
            let path = dir.join(name);
            let mut img = Image::filled(4, 2, &[1.0, 1.0, 1.0]);
            *img.pixel_mut(3, 1).get_mut(2).expect("3 channels") = bad;
            write_exr(&path, &img).expect("test setup");
            let msg = format!("{:#}", Probe::load(&path, 1.0).unwrap_err());
            assert!(msg.contains(name) && msg.contains("pixel (3, 1) channel 2"), "{msg}");
        }
    }
}

//! OpenEXR: RGB(A), luminance (Y) or any single channel (e.g. a depth map's "Z").

use std::path::Path;

use anyhow::{bail, Context, Result};
use exr::prelude as exrs;
use exr::prelude::{AnyChannel, AnyChannels, FlatSamples, ReadChannels, ReadLayers, WritableImage};

use super::require_file;
use crate::image::safe_decode::{check_dimensions, guard};
use crate::image::Image;

type FlatLayer = exrs::Layer<AnyChannels<FlatSamples>>;
/// The display window: position and size.
type Window = (exrs::Vec2<i32>, exrs::Vec2<usize>);

/// Read the first layer of an EXR file as f32.
///
/// Channels are chosen by name, ignoring any layer prefix ("ViewLayer.Combined.R" counts as "R"):
/// R, G, B (+ A) give a 3- or 4-channel image; otherwise Y (+ A) gives 1 or 2 channels;
/// otherwise a file with exactly one channel (such as depth's "Z") gives a 1-channel image.
/// Pixels outside the data window are 0.
pub fn read_exr(path: &Path) -> Result<Image> {
    let (layer, display) = read_first_layer(path)?;
    let names = ["R", "G", "B", "A"].map(|n| find_channel(&layer, n));
    let picked: Vec<usize> = match names {
        [Some(r), Some(g), Some(b), a] => [Some(r), Some(g), Some(b), a].into_iter().flatten().collect(),
        _ => match (find_channel(&layer, "Y"), names[3]) {
            (Some(y), a) => [Some(y), a].into_iter().flatten().collect(),
            _ if layer.channel_data.list.len() == 1 => vec![0],
            _ => bail!(
                "{}: no RGB or Y channels and more than one channel ({}); name the channel to read",
                path.display(),
                channel_names(&layer).join(", ")
            ),
        },
    };
    Ok(assemble(&layer, display, &picked))
}

/// Read one named channel (e.g. "Z") of an EXR file as a 1-channel image.
pub fn read_exr_channel(path: &Path, name: &str) -> Result<Image> {
    let (layer, display) = read_first_layer(path)?;
    match find_channel(&layer, name) {
        Some(i) => Ok(assemble(&layer, display, &[i])),
        None => bail!(
            "{}: no channel named {name:?} (it has {})",
            path.display(),
            channel_names(&layer).join(", ")
        ),
    }
}

/// Write an image as a 32-bit float EXR. Channel names: 1 → Y, 2 → Y A, 3 → R G B, 4 → R G B A.
pub fn write_exr(path: &Path, img: &Image) -> Result<()> {
    let names: &[&str] = match img.channels {
        1 => &["Y"],
        2 => &["Y", "A"],
        3 => &["R", "G", "B"],
        4 => &["R", "G", "B", "A"],
        c => bail!("cannot write {} as EXR without channel names: {c} channels", path.display()),
    };
    write_exr_channels(path, img, names)
}

/// Write an image as a 32-bit float EXR with the given channel names (one per channel).
pub fn write_exr_channels(path: &Path, img: &Image, names: &[&str]) -> Result<()> {
    if names.len() != img.channels {
        bail!("cannot write {}: {} channel names for {} channels", path.display(), names.len(), img.channels);
    }
    if img.data.len() != img.pixel_count() * img.channels {
        bail!("cannot write {}: image data does not match its size", path.display());
    }
    let channels: Vec<AnyChannel<FlatSamples>> = names
        .iter()
        .enumerate()
        .map(|(c, name)| {
            let samples = img.data.iter().skip(c).step_by(img.channels).copied().collect();
            AnyChannel::new(*name, FlatSamples::F32(samples))
        })
        .collect();
    let exr_image = exrs::Image::from_channels((img.width, img.height), AnyChannels::sort(channels.into()));
    exr_image
        .write()
        .to_file(path)
        .with_context(|| format!("cannot write EXR image {}", path.display()))
}

/// The first layer at full resolution, and the display window (position, size).
fn read_first_layer(path: &Path) -> Result<(FlatLayer, Window)> {
    require_file(path, "EXR image")?;
    guard(path, "EXR image", || {
        check_exr_header(path)?;
        let image = exrs::read()
            .no_deep_data()
            .largest_resolution_level()
            .all_channels()
            .first_valid_layer()
            .all_attributes()
            .from_file(path)
            .with_context(|| format!("cannot read {} as an OpenEXR file (corrupt or unsupported)", path.display()))?;
        let display = image.attributes.display_window;
        Ok((image.layer_data, (display.position, display.size)))
    })
}

/// The sizes every header of an EXR file claims (data and display windows), checked against the
/// limits before the pixels are read.
fn check_exr_header(path: &Path) -> Result<()> {
    let meta = exr::meta::MetaData::read_from_file(path, false)
        .with_context(|| format!("cannot read the header of {} as an OpenEXR file (corrupt or unsupported)", path.display()))?;
    for header in &meta.headers {
        for size in [header.layer_size, header.shared_attributes.display_window.size] {
            check_dimensions(path, size.width() as u64, size.height() as u64)?;
        }
    }
    Ok(())
}

fn channel_names(layer: &FlatLayer) -> Vec<String> {
    layer.channel_data.list.iter().map(|c| c.name.to_string()).collect()
}

/// Index of the channel called `name`, with or without a "layer." prefix.
fn find_channel(layer: &FlatLayer, name: &str) -> Option<usize> {
    layer.channel_data.list.iter().position(|c| {
        let full = c.name.to_string();
        full == name || full.rsplit('.').next() == Some(name)
    })
}

/// Place the picked channels of the data window into an image of the display window's size.
fn assemble(layer: &FlatLayer, (origin, size): Window, picked: &[usize]) -> Image {
    let (w, h) = (size.width(), size.height());
    let mut out = Image::new(w, h, picked.len());
    let (lw, lh) = (layer.size.width(), layer.size.height());
    let off_x = layer.attributes.layer_position.x() - origin.x();
    let off_y = layer.attributes.layer_position.y() - origin.y();
    for (k, &ci) in picked.iter().enumerate() {
        let values: Vec<f32> = layer.channel_data.list[ci].sample_data.values_as_f32().collect();
        for y in 0..lh {
            let ty = y as i32 + off_y;
            if ty < 0 || ty as usize >= h {
                continue;
            }
            for x in 0..lw {
                let tx = x as i32 + off_x;
                if tx < 0 || tx as usize >= w {
                    continue;
                }
                out.data[(ty as usize * w + tx as usize) * picked.len() + k] = values[y * lw + x];
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn temp_path(name: &str) -> std::path::PathBuf {
        let dir = std::env::temp_dir().join(format!("reconstruct-exr-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("test setup");
        dir.join(name)
    }

    fn ramp(w: usize, h: usize, c: usize) -> Image {
        let mut img = Image::new(w, h, c);
        for (i, v) in img.data.iter_mut().enumerate() {
            *v = (i as f32 * 0.37).sin() * 10.0 + 1e-3 * i as f32;
        }
        img
    }

    #[test]
    fn float_values_survive_exactly_for_each_channel_count() {
        for c in 1..=4 {
            let img = ramp(7, 5, c);
            let p = temp_path(&format!("ramp{c}.exr"));
            write_exr(&p, &img).expect("test setup");
            assert_eq!(read_exr(&p).expect("test setup"), img, "{c} channels");
        }
    }

    #[test]
    fn a_named_single_channel_reads_back_by_name_and_by_default() {
        let img = ramp(6, 4, 1);
        let p = temp_path("depth.exr");
        write_exr_channels(&p, &img, &["Z"]).expect("test setup");
        assert_eq!(read_exr_channel(&p, "Z").expect("test setup"), img);
        assert_eq!(read_exr(&p).expect("test setup"), img);
        let msg = format!("{:#}", read_exr_channel(&p, "Q").unwrap_err());
        assert!(msg.contains("depth.exr") && msg.contains("\"Q\""), "{msg}");
    }

    #[test]
    fn ambiguous_channels_are_an_error_naming_them() {
        let img = ramp(3, 3, 2);
        let p = temp_path("uv.exr");
        write_exr_channels(&p, &img, &["U", "V"]).expect("test setup");
        let msg = format!("{:#}", read_exr(&p).unwrap_err());
        assert!(msg.contains("uv.exr") && msg.contains("U, V"), "{msg}");
    }
}

//! `--prior labels:DIR`: labels made elsewhere (e.g. by the official IDArb code) read from a
//! folder and matched to training views by name. Accepted layouts (docs/prior_labels.md):
//! 1. one strip per view, `<view>.png`: four tiles side by side, [albedo | normal | metallic |
//!    roughness], each W wide (metallic and roughness read from their first channel);
//! 2. one file per map: `<view>_albedo.png`, `<view>_normal.png`, `<view>_metallic.png`,
//!    `<view>_roughness.png`;
//! 3. a folder per view: `<view>/albedo.png`, `<view>/normal.png`, `<view>/metallic.png`,
//!    `<view>/roughness.png`.
//!
//! `<view>` is the view's name (`train_000`) or its image stem (`r_0`). Labels made at another
//! resolution with the view's aspect ratio are resized (bilinear); any other size is an error that
//! names the file. The mask is the view's alpha > 0.5. Views without files get no label.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};

use crate::image::io::read_png;
use crate::image::Image;
use crate::scene::dataset::{Dataset, View};

use super::view_labels::ViewLabels;
use super::source::Prior;

pub struct LabelsDir {
    pub dir: PathBuf,
}

const MAPS: [&str; 4] = ["albedo", "normal", "metallic", "roughness"];

impl LabelsDir {
    pub fn open(dir: &Path) -> Result<LabelsDir> {
        if !dir.is_dir() {
            bail!("--prior labels:{}: no such folder", dir.display());
        }
        Ok(LabelsDir { dir: dir.to_path_buf() })
    }

    fn names(view: &View) -> Vec<String> {
        let mut names = vec![view.name.clone()];
        if let Some(stem) = view.image_path.file_stem().map(|s| s.to_string_lossy().into_owned()) {
            if !names.contains(&stem) {
                names.push(stem);
            }
        }
        names
    }

    /// The four map files of `view` (per-map layouts), or its strip, or nothing.
    fn locate(&self, view: &View) -> Option<Result<[Image; 4]>> {
        for name in Self::names(view) {
            let per_map: Vec<PathBuf> = MAPS.iter().map(|m| self.dir.join(format!("{name}_{m}.png"))).collect();
            let sub: Vec<PathBuf> = MAPS.iter().map(|m| self.dir.join(&name).join(format!("{m}.png"))).collect();
            for files in [per_map, sub] {
                let present = files.iter().filter(|p| p.is_file()).count();
                if present == 4 {
                    return Some(read_maps(&files, view));
                }
                if present > 0 {
                    let missing = files.iter().find(|p| !p.is_file()).map(|p| p.display().to_string()).unwrap_or_default();
                    return Some(Err(anyhow::anyhow!("labels of view {}: {missing} is missing (the other maps are there)", view.name)));
                }
            }
            let strip = self.dir.join(format!("{name}.png"));
            if strip.is_file() {
                return Some(read_strip(&strip, view));
            }
        }
        None
    }
}

/// Resize to the view's size when the aspect ratio matches; otherwise an error naming `path`.
fn fit_to_view(img: Image, path: &Path, view: &View) -> Result<Image> {
    let (w, h) = (view.camera.width, view.camera.height);
    if (img.width, img.height) == (w, h) {
        return Ok(img);
    }
    if img.width * h != img.height * w {
        bail!("label file {} is {}×{}, but view {} is {w}×{h} (a different aspect ratio)", path.display(), img.width, img.height, view.name);
    }
    let mut out = Image::new(w, h, img.channels);
    let (sx, sy) = (img.width as f32 / w as f32, img.height as f32 / h as f32);
    let mut px = vec![0.0; img.channels];
    for y in 0..h {
        for x in 0..w {
            img.bilinear((x as f32 + 0.5) * sx, (y as f32 + 0.5) * sy, &mut px);
            out.pixel_mut(x, y).copy_from_slice(&px);
        }
    }
    Ok(out)
}

fn rgb(img: &Image) -> Image {
    if img.channels == 1 {
        let mut out = Image::new(img.width, img.height, 3);
        for (o, v) in out.data.chunks_exact_mut(3).zip(&img.data) {
            o.fill(*v);
        }
        out
    } else {
        crate::image::io::to_rgb(img)
    }
}

fn read_maps(files: &[PathBuf], view: &View) -> Result<[Image; 4]> {
    let mut maps = Vec::new();
    for (k, f) in files.iter().enumerate() {
        let img = fit_to_view(read_png(f)?, f, view)?;
        maps.push(if k < 2 { rgb(&img) } else { img.channel(0) });
    }
    maps.try_into().map_err(|_| anyhow::anyhow!("four maps expected"))
}

fn read_strip(path: &Path, view: &View) -> Result<[Image; 4]> {
    let img = read_png(path)?;
    if img.width % 4 != 0 {
        bail!("label strip {} is {} pixels wide: expected four tiles [albedo | normal | metallic | roughness] of equal width", path.display(), img.width);
    }
    let tw = img.width / 4;
    let tile = |k: usize| -> Image {
        let mut t = Image::new(tw, img.height, img.channels);
        for y in 0..img.height {
            for x in 0..tw {
                t.pixel_mut(x, y).copy_from_slice(img.pixel(k * tw + x, y));
            }
        }
        t
    };
    let mut maps = Vec::new();
    for (k, map) in MAPS.iter().enumerate() {
        let t = fit_to_view(tile(k), path, view).with_context(|| format!("tile {} ({map}) of the strip", k + 1))?;
        maps.push(if k < 2 { rgb(&t) } else { t.channel(0) });
    }
    maps.try_into().map_err(|_| anyhow::anyhow!("four maps expected"))
}

impl Prior for LabelsDir {
    fn describe(&self) -> String {
        format!("labels:{} (label files read from a folder)", self.dir.display())
    }
    fn labels(&self, dataset: &Dataset, views: &[usize]) -> Result<Vec<Option<ViewLabels>>> {
        if views.is_empty() {
            return Ok(Vec::new());
        }
        let mut out = Vec::new();
        let mut found = 0;
        for &i in views {
            let view = &dataset.train[i];
            match self.locate(view) {
                None => out.push(None),
                Some(maps) => {
                    let [albedo, normal, metallic, roughness] = maps?;
                    let mask = view.load_alpha()?.map_channels(1, |a| if a > 0.5 { 1.0 } else { 0.0 });
                    out.push(Some(ViewLabels { albedo, normal, metallic, roughness, mask }));
                    found += 1;
                }
            }
        }
        if found == 0 {
            bail!("--prior labels:{}: no label file matches any training view (looked for e.g. {}.png, {}_albedo.png, {}/albedo.png)", self.dir.display(), dataset.train[views[0]].name, dataset.train[views[0]].name, dataset.train[views[0]].name);
        }
        Ok(out)
    }
}

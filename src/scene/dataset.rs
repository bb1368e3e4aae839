//! Multi-view datasets in the NeRFactor or NeRF-synthetic layout.
//!
//! Both layouts have `transforms_{train,val,test}.json` (NeRF's Blender format: `camera_angle_x`
//! and per-frame `file_path` + camera-to-world `transform_matrix`). They differ in what
//! `file_path` points to:
//! - **NeRFactor**: `./train_000/rgba` → a folder per view holding `rgba.png` (sRGB, straight
//!   alpha), `albedo.png` (LINEAR), `normal.png` (world normal, (n+1)/2), `metadata.json`,
//!   test views' `rgba_<probe>.png`, and optionally `roughness.png`, `metallic.png`, `depth.exr`.
//! - **NeRF-synthetic**: `./train/r_0` → the image `train/r_0.png`; no other per-view files.
//!
//! The layout is detected per frame (the image's name is `rgba.png`, or `file_path` is a
//! folder). Loading reads only JSON files and image headers (sizes are checked); pixels are
//! read lazily by the `View::load_*` methods.

use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context, Result};
use glam::{Mat4, Vec3};
use rayon::prelude::*;
use serde::Deserialize;

use super::camera::rigid_problem;
use super::Camera;
use crate::image::io::{read_exr, read_exr_channel, read_png};
use crate::image::safe_decode::{check_dimensions, guard};
use crate::image::Image;

/// A pixel belongs to the object's mask when its alpha is at least this: half coverage, where the
/// outline of an anti-aliased mask passes. The visual hull, the geometry pass and the view
/// screening all cut the masks here.
pub const MASK_THRESHOLD: f32 = 0.5;

/// How many of the coverage values `alpha` lie inside the mask, i.e. are at least `threshold`
/// ([`MASK_THRESHOLD`] but where a caller's options say otherwise). None means the view's mask is
/// empty: the view does not show the object, and the visual hull, the geometry pass and the view
/// screening all leave it out (each with its own warning).
pub fn mask_pixels(alpha: impl IntoIterator<Item = f32>, threshold: f32) -> usize {
    alpha.into_iter().filter(|&a| a >= threshold).count()
}

/// Which of the three lists of views.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Split {
    Train,
    Val,
    Test,
}

impl Split {
    pub const ALL: [Split; 3] = [Split::Train, Split::Val, Split::Test];

    pub fn name(self) -> &'static str {
        match self {
            Split::Train => "train",
            Split::Val => "val",
            Split::Test => "test",
        }
    }
}

/// How a view's files are arranged on disk.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Layout {
    /// A folder per view with `rgba.png` and ground-truth maps.
    NeRFactor,
    /// One image per view (`train/r_0.png`), nothing else.
    NerfSynthetic,
}

/// NeRFactor's per-view `metadata.json` (every key optional).
#[derive(Clone, Debug, Default)]
pub struct ViewMetadata {
    pub scene: Option<String>,
    /// `cam_transform_mat`: the camera-to-world matrix (stored row-major as 16 comma-separated floats).
    pub cam_transform_mat: Option<Mat4>,
    pub cam_angle_x: Option<f32>,
    /// The light probe the view was rendered under, and its strength.
    pub envmap: Option<String>,
    pub envmap_inten: Option<f32>,
    pub imw: Option<usize>,
    pub imh: Option<usize>,
    pub spp: Option<u32>,
}

/// One camera view of the dataset, with lazy access to its pictures.
#[derive(Clone, Debug)]
pub struct View {
    /// `train_000` (NeRFactor) or `train_r_0` (NeRF-synthetic: split folder + image stem).
    pub name: String,
    /// The view's folder (NeRFactor) or the folder holding its image (NeRF-synthetic).
    pub dir: PathBuf,
    /// The colour image: `rgba.png` or `r_0.png`.
    pub image_path: PathBuf,
    pub layout: Layout,
    pub camera: Camera,
    /// NeRF's per-frame `rotation` field (unused by the renderers, kept for completeness).
    pub rotation: Option<f32>,
    pub metadata: Option<ViewMetadata>,
}

/// A whole dataset: cameras and image locations of the train, val and test views.
#[derive(Clone, Debug)]
pub struct Dataset {
    pub root: PathBuf,
    pub layout: Layout,
    pub train: Vec<View>,
    pub val: Vec<View>,
    pub test: Vec<View>,
}

#[derive(Deserialize)]
struct TransformsFile {
    camera_angle_x: f32,
    frames: Vec<FrameEntry>,
}

#[derive(Deserialize)]
struct FrameEntry {
    file_path: String,
    #[serde(default)]
    rotation: Option<f32>,
    transform_matrix: [[f32; 4]; 4],
}

/// A split of up to this many views is listed by name in an error: NeRFactor's test and val splits
/// (8 views each) in full, a train split of 100 by its first and last view.
const LISTED_VIEWS: usize = 8;

impl Dataset {
    /// Load `dir/transforms_{train,val,test}.json` and check every view's files.
    /// `transforms_train.json` is required; a missing val or test file gives an empty list.
    pub fn load(dir: &Path) -> Result<Dataset> {
        if !dir.is_dir() {
            bail!("dataset folder not found: {}", dir.display());
        }
        let mut splits = Vec::new();
        for split in Split::ALL {
            let file = dir.join(format!("transforms_{}.json", split.name()));
            if !file.exists() {
                if split == Split::Train {
                    bail!("{} is not a NeRF/NeRFactor dataset: {} not found", dir.display(), file.display());
                }
                splits.push(Vec::new());
                continue;
            }
            splits.push(load_split(dir, &file)?);
        }
        let test = splits.pop().unwrap_or_default();
        let val = splits.pop().unwrap_or_default();
        let train = splits.pop().unwrap_or_default();
        let layout = train
            .first()
            .map(|v| v.layout)
            .ok_or_else(|| anyhow!("{}: transforms_train.json lists no frames", dir.display()))?;
        Ok(Dataset { root: dir.to_path_buf(), layout, train, val, test })
    }

    pub fn views(&self, split: Split) -> &[View] {
        match split {
            Split::Train => &self.train,
            Split::Val => &self.val,
            Split::Test => &self.test,
        }
    }

    /// Train, val and test views in that order.
    pub fn all_views(&self) -> impl Iterator<Item = &View> {
        self.train.iter().chain(&self.val).chain(&self.test)
    }

    /// The view called `name` in any split; the error lists the views there are (a split of up to
    /// `LISTED_VIEWS` by name, a longer one by its first and last).
    pub fn view(&self, name: &str) -> Result<&View> {
        self.all_views().find(|v| v.name == name).ok_or_else(|| {
            let split = |label: &str, views: &[View]| match views {
                [] => format!("no {label} views"),
                [only] => format!("1 {label} view ({})", only.name),
                [first, .., last] if views.len() > LISTED_VIEWS => format!("{} {label} views ({} … {})", views.len(), first.name, last.name),
                _ => format!("{} {label} views ({})", views.len(), views.iter().map(|v| v.name.as_str()).collect::<Vec<_>>().join(", ")),
            };
            anyhow!(
                "no view named {name:?} in dataset {}: it has {}, {} and {}",
                self.root.display(),
                split("test", &self.test),
                split("train", &self.train),
                split("val", &self.val)
            )
        })
    }
}

fn load_split(root: &Path, file: &Path) -> Result<Vec<View>> {
    let text = std::fs::read_to_string(file).with_context(|| format!("cannot read {}", file.display()))?;
    let parsed: TransformsFile = serde_json::from_str(&text)
        .with_context(|| format!("cannot parse {} as NeRF transforms JSON", file.display()))?;
    let fov = parsed.camera_angle_x;
    if !(fov.is_finite() && fov > 0.0 && fov < std::f32::consts::PI) {
        bail!("{}: camera_angle_x {fov} is not a field of view in (0, π) radians", file.display());
    }
    parsed
        .frames
        .par_iter()
        .enumerate()
        .map(|(i, frame)| {
            View::from_frame(root, frame, parsed.camera_angle_x)
                .with_context(|| format!("frame {i} ({:?}) of {}", frame.file_path, file.display()))
        })
        .collect()
}

/// Read a PNG's size from its header only.
fn png_size(path: &Path) -> Result<(usize, usize)> {
    let (w, h) = guard(path, "PNG image", || {
        image::image_dimensions(path).with_context(|| format!("cannot read the size of image {}", path.display()))
    })?;
    check_dimensions(path, w as u64, h as u64)?;
    Ok((w as usize, h as usize))
}

fn exr_size(path: &Path) -> Result<(usize, usize)> {
    let meta = guard(path, "EXR image", || {
        exr::meta::MetaData::read_from_file(path, false).with_context(|| format!("cannot read the header of EXR image {}", path.display()))
    })?;
    let header = meta.headers.first().ok_or_else(|| anyhow!("{} has no image layer", path.display()))?;
    let size = header.shared_attributes.display_window.size;
    check_dimensions(path, size.width() as u64, size.height() as u64)?;
    Ok((size.width(), size.height()))
}

fn parse_metadata(path: &Path) -> Result<ViewMetadata> {
    let text = std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
    let v: serde_json::Value =
        serde_json::from_str(&text).with_context(|| format!("cannot parse {} as JSON", path.display()))?;
    let num = |k: &str| v.get(k).and_then(|x| x.as_f64().or_else(|| x.as_str().and_then(|s| s.trim().parse().ok())));
    let string = |k: &str| v.get(k).and_then(|x| x.as_str()).map(str::to_owned);
    let cam_transform_mat = match v.get("cam_transform_mat") {
        None => None,
        Some(m) => Some(parse_matrix(m).with_context(|| format!("{}: bad cam_transform_mat", path.display()))?),
    };
    Ok(ViewMetadata {
        scene: string("scene"),
        cam_transform_mat,
        cam_angle_x: num("cam_angle_x").map(|x| x as f32),
        envmap: string("envmap"),
        envmap_inten: num("envmap_inten").map(|x| x as f32),
        imw: num("imw").map(|x| x as usize),
        imh: num("imh").map(|x| x as usize),
        spp: num("spp").map(|x| x as u32),
    })
}

/// A 4×4 matrix given row-major, either as "a,b,c,…" (NeRFactor's `listify_matrix`) or as JSON numbers.
fn parse_matrix(m: &serde_json::Value) -> Result<Mat4> {
    let values: Vec<f32> = match m {
        serde_json::Value::String(s) => s
            .split(',')
            .map(|t| t.trim().parse::<f32>().map_err(|e| anyhow!("{t:?}: {e}")))
            .collect::<Result<_>>()?,
        serde_json::Value::Array(rows) => rows
            .iter()
            .flat_map(|r| r.as_array().cloned().unwrap_or_else(|| vec![r.clone()]))
            .map(|x| x.as_f64().map(|f| f as f32).ok_or_else(|| anyhow!("not a number: {x}")))
            .collect::<Result<_>>()?,
        other => bail!("expected a string or array, found {other}"),
    };
    if values.len() != 16 {
        bail!("expected 16 values, found {}", values.len());
    }
    Ok(matrix_from_rows(std::array::from_fn(|r| std::array::from_fn(|c| values[4 * r + c]))))
}

/// JSON matrices are row-major; glam is column-major.
fn matrix_from_rows(rows: [[f32; 4]; 4]) -> Mat4 {
    Mat4::from_cols_array_2d(&rows).transpose()
}

impl View {
    fn from_frame(root: &Path, frame: &FrameEntry, fov_x: f32) -> Result<View> {
        let rel = frame.file_path.trim_start_matches("./");
        let target = root.join(rel);
        let with_png = root.join(format!("{rel}.png"));
        let image_path = if target.is_dir() {
            target.join("rgba.png")
        } else if target.is_file() {
            target.clone()
        } else if with_png.is_file() {
            with_png
        } else if target.file_name().is_some_and(|n| n == "rgba") {
            let folder = target.parent().unwrap_or(root);
            if folder.is_dir() {
                bail!("image not found: {}", folder.join("rgba.png").display());
            }
            bail!("view folder not found: {}", folder.display());
        } else {
            bail!("image not found: {} (nor {})", with_png.display(), target.display());
        };
        if !image_path.is_file() {
            bail!("image not found: {}", image_path.display());
        }
        let is_nerfactor = image_path.file_name().is_some_and(|n| n == "rgba.png");
        let layout = if is_nerfactor { Layout::NeRFactor } else { Layout::NerfSynthetic };
        let dir = image_path.parent().unwrap_or(root).to_path_buf();
        let name = match layout {
            Layout::NeRFactor => dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default(),
            Layout::NerfSynthetic => rel.trim_end_matches(".png").replace('/', "_"),
        };
        let (width, height) = png_size(&image_path)?;
        let c2w = matrix_from_rows(frame.transform_matrix);
        if let Some(problem) = rigid_problem(&c2w) {
            bail!("transform_matrix is not a rigid camera pose: {problem}");
        }
        let camera = Camera { c2w, fov_x, width, height };
        let metadata_path = dir.join("metadata.json");
        let metadata = if layout == Layout::NeRFactor && metadata_path.is_file() {
            Some(parse_metadata(&metadata_path)?)
        } else {
            None
        };
        let view = View { name, dir, image_path, layout, camera, rotation: frame.rotation, metadata };
        view.validate()?;
        Ok(view)
    }

    /// Check that the metadata's image size and every picture present match the view's size.
    pub fn validate(&self) -> Result<()> {
        let (w, h) = (self.camera.width, self.camera.height);
        if let Some(m) = &self.metadata {
            if let (Some(mw), Some(mh)) = (m.imw, m.imh) {
                if (mw, mh) != (w, h) {
                    bail!(
                        "{}: imw×imh = {mw}×{mh} but {} is {w}×{h}",
                        self.dir.join("metadata.json").display(),
                        self.image_path.display()
                    );
                }
            }
        }
        if self.layout == Layout::NerfSynthetic {
            return Ok(());
        }
        let mut pictures: Vec<PathBuf> = ["albedo.png", "normal.png", "roughness.png", "metallic.png"]
            .iter()
            .map(|f| self.dir.join(f))
            .filter(|p| p.is_file())
            .collect();
        pictures.extend(self.relit_probes()?.iter().map(|p| self.relit_path(p)));
        for p in pictures {
            self.check_size(&p, png_size(&p)?)?;
        }
        let depth = self.dir.join("depth.exr");
        if depth.is_file() {
            self.check_size(&depth, exr_size(&depth)?)?;
        }
        Ok(())
    }

    fn check_size(&self, path: &Path, (w, h): (usize, usize)) -> Result<()> {
        if (w, h) != (self.camera.width, self.camera.height) {
            bail!(
                "wrong image size: {} is {w}×{h}, but the view's image {} is {}×{}",
                path.display(),
                self.image_path.display(),
                self.camera.width,
                self.camera.height
            );
        }
        Ok(())
    }

    /// The path of a per-view ground-truth file, if this layout has such files.
    fn extra_path(&self, file: &str) -> Option<PathBuf> {
        (self.layout == Layout::NeRFactor).then(|| self.dir.join(file))
    }

    fn has(&self, file: &str) -> bool {
        self.extra_path(file).is_some_and(|p| p.is_file())
    }

    fn require(&self, file: &str, what: &str) -> Result<PathBuf> {
        match self.extra_path(file) {
            None => bail!("view {} ({}) has no {what}: the NeRF-synthetic layout carries none", self.name, self.image_path.display()),
            Some(p) if !p.is_file() => bail!("{what} not found: {}", p.display()),
            Some(p) => Ok(p),
        }
    }

    fn read_png_checked(&self, path: &Path) -> Result<Image> {
        let img = read_png(path)?;
        self.check_size(path, (img.width, img.height))?;
        Ok(img)
    }

    pub fn has_albedo(&self) -> bool {
        self.has("albedo.png")
    }
    pub fn has_normal(&self) -> bool {
        self.has("normal.png")
    }
    pub fn has_roughness(&self) -> bool {
        self.has("roughness.png")
    }
    pub fn has_metallic(&self) -> bool {
        self.has("metallic.png")
    }
    pub fn has_depth(&self) -> bool {
        self.has("depth.exr")
    }
    pub fn has_relit(&self, probe: &str) -> bool {
        self.layout == Layout::NeRFactor && self.relit_path(probe).is_file()
    }

    /// Path of the view rendered under another probe: `rgba_<probe>.png`.
    pub fn relit_path(&self, probe: &str) -> PathBuf {
        self.dir.join(format!("rgba_{probe}.png"))
    }

    /// Names of the probes this view has relit images for (from `rgba_<probe>.png`), sorted.
    /// NeRFactor's one-light-at-a-time renders (`rgba_olat-*.png`, hundreds per view) are not listed
    /// (nor size-checked at load); `load_relit("olat-…")` still reads them.
    pub fn relit_probes(&self) -> Result<Vec<String>> {
        if self.layout != Layout::NeRFactor {
            return Ok(Vec::new());
        }
        let entries = std::fs::read_dir(&self.dir).with_context(|| format!("cannot list view folder {}", self.dir.display()))?;
        let mut names: Vec<String> = entries
            .filter_map(|e| e.ok())
            .filter_map(|e| {
                let n = e.file_name().to_string_lossy().into_owned();
                n.strip_prefix("rgba_").and_then(|s| s.strip_suffix(".png")).map(str::to_owned)
            })
            .filter(|n| !n.starts_with("olat"))
            .collect();
        names.sort();
        Ok(names)
    }

    /// The colour image as 4 channels: linear RGB (sRGB decoded) and straight alpha
    /// (1 when the file has none).
    pub fn load_rgba(&self) -> Result<Image> {
        Ok(to_rgba(&self.read_png_checked(&self.image_path)?).srgb_to_linear())
    }

    /// The view under test probe `probe` (`rgba_<probe>.png`), decoded like [`View::load_rgba`].
    pub fn load_relit(&self, probe: &str) -> Result<Image> {
        let path = self.require(&format!("rgba_{probe}.png"), &format!("relit image for probe {probe:?}"))?;
        Ok(to_rgba(&self.read_png_checked(&path)?).srgb_to_linear())
    }

    /// The view's coverage (alpha of the colour image) as a 1-channel image.
    pub fn load_alpha(&self) -> Result<Image> {
        Ok(alpha_of(&self.read_png_checked(&self.image_path)?))
    }

    /// Ground-truth base colour as 4 channels: LINEAR RGB as stored (no curve) and alpha
    /// (the file's, or the colour image's if the file has none).
    pub fn load_albedo(&self) -> Result<Image> {
        let path = self.require("albedo.png", "albedo map")?;
        let img = self.read_png_checked(&path)?;
        let mut out = to_rgba(&img);
        if !has_alpha(&img) {
            self.copy_alpha_into(&mut out)?;
        }
        Ok(out)
    }

    /// Ground-truth world-space normals as 4 channels: unit xyz (decoded from (n+1)/2 and
    /// renormalised) and alpha. Background pixels (alpha 0, or an encoded zero vector) are all 0.
    /// Alpha is the file's, or the colour image's if the file has none.
    pub fn load_normal(&self) -> Result<Image> {
        let path = self.require("normal.png", "normal map")?;
        let img = self.read_png_checked(&path)?;
        if img.channels < 3 {
            bail!("normal map {} has {} channel(s), expected RGB or RGBA", path.display(), img.channels);
        }
        let mut out = to_rgba(&img);
        if !has_alpha(&img) {
            self.copy_alpha_into(&mut out)?;
        }
        for p in out.data.chunks_exact_mut(4) {
            let n = Vec3::new(p[0], p[1], p[2]) * 2.0 - Vec3::ONE;
            let len = n.length();
            let n = if p[3] > 0.0 && len > 1e-3 { n / len } else { Vec3::ZERO };
            let alpha = if n == Vec3::ZERO { 0.0 } else { p[3] };
            p.copy_from_slice(&n.extend(alpha).to_array());
        }
        Ok(out)
    }

    /// Ground-truth roughness (1 channel, linear as stored).
    pub fn load_roughness(&self) -> Result<Image> {
        let path = self.require("roughness.png", "roughness map")?;
        Ok(self.read_png_checked(&path)?.channel(0))
    }

    /// Ground-truth metallic (1 channel, linear as stored).
    pub fn load_metallic(&self) -> Result<Image> {
        let path = self.require("metallic.png", "metallic map")?;
        Ok(self.read_png_checked(&path)?.channel(0))
    }

    /// Planar depth along the camera's viewing axis (1 channel, world units, 0 on the background),
    /// from `depth.exr`'s "Z" channel (or its only channel).
    pub fn load_depth(&self) -> Result<Image> {
        let path = self.require("depth.exr", "depth map")?;
        let img = read_exr_channel(&path, "Z").or_else(|_| read_exr(&path))?;
        if img.channels != 1 {
            bail!("depth map {} has {} channels and none named Z", path.display(), img.channels);
        }
        self.check_size(&path, (img.width, img.height))?;
        Ok(img)
    }

    /// `Some(map)` when the optional map is present, `None` when the dataset lacks it.
    pub fn load_roughness_if_present(&self) -> Result<Option<Image>> {
        self.has_roughness().then(|| self.load_roughness()).transpose()
    }
    pub fn load_metallic_if_present(&self) -> Result<Option<Image>> {
        self.has_metallic().then(|| self.load_metallic()).transpose()
    }
    pub fn load_depth_if_present(&self) -> Result<Option<Image>> {
        self.has_depth().then(|| self.load_depth()).transpose()
    }

    fn copy_alpha_into(&self, out: &mut Image) -> Result<()> {
        let alpha = self.load_alpha()?;
        for (p, a) in out.data.chunks_exact_mut(4).zip(&alpha.data) {
            p[3] = *a;
        }
        Ok(())
    }
}

fn has_alpha(img: &Image) -> bool {
    img.channels == 2 || img.channels == 4
}

/// Any PNG layout to 4 channels: grey is replicated, missing alpha is 1.
fn to_rgba(img: &Image) -> Image {
    if img.channels == 4 {
        return img.clone();
    }
    let mut out = Image::new(img.width, img.height, 4);
    for i in 0..img.pixel_count() {
        out.data[4 * i..4 * i + 4].copy_from_slice(&img.rgba(i).to_array());
    }
    out
}

/// The alpha channel, or all ones when there is none.
fn alpha_of(img: &Image) -> Image {
    if has_alpha(img) {
        img.channel(img.channels - 1)
    } else {
        Image::filled(img.width, img.height, &[1.0])
    }
}

//! One training view prepared once (geometry is fixed): the G-buffer's covered pixels with their
//! surface points and atlas UVs, and the target colour and alpha at those pixels. Everything the
//! loop renders and compares is a list of covered pixels, not a full image: pixels the primary ray
//! misses are left out of the loss (with fixed geometry their term would be a constant) and cost
//! nothing.

use std::sync::Arc;

use anyhow::{Context, Result};
use candle_core::{Device, Tensor};
use glam::Vec3;

use crate::geometry::bvh::Bvh;
use crate::geometry::Mesh;
use crate::image::Image;
use crate::optim::loss::LossTarget;
use crate::render::denoise::DenoiseGuides;
use crate::render::gbuffer::{GBuffer, Surfel};
use crate::scene::dataset::{self, View};
use crate::scene::Camera;

use super::labels::PixelLabels;
use super::view_screening::{silhouette_disagreement, MASK_THRESHOLD};

#[derive(Clone)]
pub struct TrainingView {
    pub name: String,
    pub camera: Camera,
    /// Index of the view in the dataset's training list (also separates random streams).
    pub index: usize,
    /// Image index (y·W + x) of each covered pixel.
    pub pixels: Vec<u32>,
    pub surfels: Vec<Surfel>,
    /// Atlas UV of each covered pixel.
    pub uv: Arc<[[f32; 2]]>,
    /// Camera position (outgoing directions).
    pub origin: Vec3,
    /// Target linear RGB and alpha at the covered pixels, [n, 1, 4] (a column "image" so the
    /// image loss applies unchanged), with the loss's constants of it computed once.
    pub target: LossTarget,
    /// Prior labels at the covered pixels, when this view has them.
    pub labels: Option<PixelLabels>,
    /// Pixels of the target whose alpha is at least `view_screening::MASK_THRESHOLD` (0: the object is
    /// not in the view).
    pub mask_pixels: usize,
    /// Share of silhouette pixels on which the mesh and the mask disagree
    /// (`view_screening::silhouette_disagreement`).
    pub silhouette_disagreement: f32,
}

impl TrainingView {
    /// Trace `view`'s camera against the atlas mesh and gather its target at the covered pixels;
    /// `downscale` > 1 uses a camera that many times smaller and a box-filtered target.
    pub fn new(view: &View, index: usize, mesh: &Mesh, bvh: &Bvh, downscale: usize) -> Result<TrainingView> {
        let rgba = view.load_rgba().with_context(|| format!("training view {}", view.name))?;
        rgba.require_finite(&format!("training view {} ({})", view.name, view.image_path.display()))?;
        anyhow::ensure!(downscale >= 1, "training view {}: the training downscale must be 1 or more", view.name);
        let s = downscale;
        let (w, h) = (view.camera.width, view.camera.height);
        anyhow::ensure!(w % s == 0 && h % s == 0, "training view {}: its {w}×{h} pixels do not divide by the training downscale {s}", view.name);
        if s == 1 {
            return Self::from_image(&view.name, &view.camera, index, &rgba, mesh, bvh);
        }
        let small = rgba.downsample_straight_alpha(s);
        let camera = view.camera.resized(view.camera.width / s, view.camera.height / s);
        Self::from_image(&view.name, &camera, index, &small, mesh, bvh)
    }

    /// As [`TrainingView::new`] with the target given (linear RGBA at the camera's size).
    pub fn from_image(name: &str, camera: &Camera, index: usize, rgba: &Image, mesh: &Mesh, bvh: &Bvh) -> Result<TrainingView> {
        anyhow::ensure!(
            rgba.width == camera.width && rgba.height == camera.height && rgba.channels == 4,
            "training view {name}: image is {}×{}×{}, the camera expects {}×{}×4",
            rgba.width,
            rgba.height,
            rgba.channels,
            camera.width,
            camera.height
        );
        rgba.require_finite(&format!("training view {name}: target image"))?;
        let gbuf = GBuffer::trace(mesh, bvh, camera);
        let (mut pixels, mut surfels, mut uv, mut target) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        for (i, s) in gbuf.surfels.iter().enumerate() {
            if let Some(s) = s {
                pixels.push(i as u32);
                surfels.push(*s);
                uv.push([s.uv.x, s.uv.y]);
                target.extend_from_slice(&rgba.data[4 * i..4 * i + 4]);
            }
        }
        let n = pixels.len();
        let alpha: Vec<f32> = rgba.data.chunks_exact(4).map(|p| p[3]).collect();
        let mesh_covered: Vec<bool> = gbuf.surfels.iter().map(Option::is_some).collect();
        let mask_pixels = dataset::mask_pixels(alpha.iter().copied(), MASK_THRESHOLD);
        let silhouette_disagreement = silhouette_disagreement(&mesh_covered, &alpha, camera.width, camera.height);
        Ok(TrainingView {
            name: name.to_string(),
            camera: camera.clone(),
            index,
            pixels,
            surfels,
            uv: uv.into(),
            origin: gbuf.origin,
            target: LossTarget::new(&Tensor::from_vec(target, (n, 1, 4), &Device::Cpu)?)?,
            labels: None,
            mask_pixels,
            silhouette_disagreement,
        })
    }

    pub fn len(&self) -> usize {
        self.pixels.len()
    }

    /// This view on a moved mesh (same triangles, e.g. `fit::vertex_refinement`'s): each covered
    /// pixel's surfel and UV retraced; the pixel list, targets and labels are kept, and a pixel
    /// whose ray now misses keeps its surfel.
    pub fn retraced(&self, mesh: &Mesh, bvh: &Bvh) -> TrainingView {
        let gbuf = GBuffer::trace(mesh, bvh, &self.camera);
        let surfels: Vec<Surfel> = self.surfels.iter().zip(&self.pixels).map(|(old, &p)| gbuf.surfels[p as usize].unwrap_or(*old)).collect();
        let uv = surfels.iter().map(|s| [s.uv.x, s.uv.y]).collect();
        TrainingView { surfels, uv, ..self.clone() }
    }

    pub fn is_empty(&self) -> bool {
        self.pixels.is_empty()
    }

    /// (normal, direction to the camera) per covered pixel, as split-sum shading wants it.
    pub fn normal_and_view(&self) -> Vec<Option<(Vec3, Vec3)>> {
        self.surfels.iter().map(|s| Some((s.normal, (self.origin - s.position).normalize()))).collect()
    }

    /// Normals, depths and coverage of the full view, for the cross-bilateral denoiser.
    pub fn denoise_guides(&self) -> Result<DenoiseGuides> {
        let n = self.camera.width * self.camera.height;
        let (mut normal, mut depth, mut covered) = (vec![Vec3::ZERO; n], vec![0.0f32; n], vec![false; n]);
        for (s, &p) in self.surfels.iter().zip(&self.pixels) {
            normal[p as usize] = s.normal;
            depth[p as usize] = s.depth;
            covered[p as usize] = true;
        }
        DenoiseGuides::new(self.camera.width, self.camera.height, normal, depth, covered)
    }

    /// Scatter per-covered-pixel values (n × c) into a full image (zero elsewhere).
    pub fn to_image(&self, values: &[f32], channels: usize) -> Image {
        let mut img = Image::new(self.camera.width, self.camera.height, channels);
        for (k, &p) in self.pixels.iter().enumerate() {
            let p = p as usize;
            img.data[channels * p..channels * (p + 1)].copy_from_slice(&values[channels * k..channels * (k + 1)]);
        }
        img
    }
}

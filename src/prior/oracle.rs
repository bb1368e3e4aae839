//! The oracle prior: a synthetic dataset's ground-truth maps as labels, in IDArb's label spaces
//! (the upper bound of what any labeller could give):
//! - albedo: the dataset stores linear base colour, IDArb predicts sRGB-encoded → encoded here;
//! - normal: the dataset stores world-space normals, IDArb predicts camera-space ones → rotated
//!   into the camera frame with the axes of docs/model.md, *Frames and cameras* (+x image-left, +y
//!   up, +z toward the camera: the OpenGL camera frame with x mirrored), encoded (n + 1)/2. Not yet
//!   verified on real IDArb output; only the x sign could change;
//! - roughness, metallic: as stored (a dataset without them gets 0.5 / 0, with the mask kept);
//! - mask: alpha > 0.5 (what IDArb's preprocessing uses).

use anyhow::{Context, Result};
use glam::Vec3;

use crate::image::Image;
use crate::scene::dataset::{Dataset, View};

use super::view_labels::ViewLabels;
use super::source::Prior;

pub struct Oracle;

/// World-space unit normals (RGBA, zero where invalid) → camera-space encoded labels, for the
/// camera `c2w` (`fit::labels::world_normal` is the inverse).
pub fn camera_normals(normals: &Image, c2w: glam::Mat4) -> Image {
    let w2c = c2w.inverse();
    let mut out = Image::new(normals.width, normals.height, 3);
    for i in 0..normals.pixel_count() {
        let n = normals.rgb(i);
        if n != Vec3::ZERO {
            let c = w2c.transform_vector3(n).normalize_or_zero() * Vec3::new(-1.0, 1.0, 1.0);
            out.set_rgb(i, (c + Vec3::ONE) * 0.5);
        }
    }
    out
}

/// The ground-truth labels of one view.
pub fn view_labels(view: &View) -> Result<ViewLabels> {
    let ctx = || format!("ground-truth labels of view {}", view.name);
    let albedo = view.load_albedo().with_context(ctx)?;
    let alpha = view.load_alpha().with_context(ctx)?;
    let mask = alpha.map_channels(1, |a| if a > 0.5 { 1.0 } else { 0.0 });
    let normal = if view.has_normal() { camera_normals(&view.load_normal().with_context(ctx)?, view.camera.c2w) } else { Image::new(albedo.width, albedo.height, 3) };
    let roughness = view.load_roughness_if_present().with_context(ctx)?.unwrap_or_else(|| Image::filled(albedo.width, albedo.height, &[0.5]));
    let metallic = view.load_metallic_if_present().with_context(ctx)?.unwrap_or_else(|| Image::filled(albedo.width, albedo.height, &[0.0]));
    let albedo = crate::image::io::to_rgb(&albedo).linear_to_srgb();
    Ok(ViewLabels { albedo, normal, metallic, roughness, mask })
}

impl Prior for Oracle {
    fn describe(&self) -> String {
        "oracle (the dataset's ground-truth maps: an upper bound, not a labeller)".into()
    }
    fn labels(&self, dataset: &Dataset, views: &[usize]) -> Result<Vec<Option<ViewLabels>>> {
        views.iter().map(|&i| view_labels(&dataset.train[i]).map(Some)).collect()
    }
}

//! Prior labels gathered at a training view's covered pixels, as constant tensors for the prior
//! term (docs/model.md, *Loss*).

use anyhow::{ensure, Result};
use candle_core::{Device, Tensor};
use glam::{Mat4, Vec3};

use crate::image::Image;
use crate::prior::view_labels::ViewLabels;

/// Labels at the covered pixels of one view: [n, 1, C] columns (see `TrainingView::target`).
#[derive(Clone)]
pub struct PixelLabels {
    /// Base colour, sRGB-encoded as IDArb predicts it.
    pub albedo_srgb: Tensor,
    pub roughness: Tensor,
    pub metallic: Tensor,
    /// 1 where the label is valid (the labeller's mask), else 0.
    pub mask: Tensor,
    /// The normal label turned to world space (unit vectors; zero where there is none), and its
    /// mask: the labeller's, times 0 where the normal label is empty.
    pub normal_world: Tensor,
    pub normal_mask: Tensor,
}

fn gather(img: &Image, pixels: &[u32], channels: usize, what: &str, view: &str) -> Result<Tensor> {
    ensure!(img.channels >= channels, "labels of view {view}: {what} has {} channels, need {channels}", img.channels);
    let mut out = Vec::with_capacity(pixels.len() * channels);
    for &p in pixels {
        let p = p as usize;
        out.extend_from_slice(&img.data[img.channels * p..img.channels * p + channels]);
    }
    Ok(Tensor::from_vec(out, (pixels.len(), 1, channels), &Device::Cpu)?)
}

/// A camera-space normal label, encoded (n + 1)/2 with x mirrored (IDArb's convention,
/// `prior::oracle::camera_normals`), as a world-space unit vector; zero for an empty label
/// (encoded zeros, what the labellers write where they have no normal).
pub fn world_normal(encoded: Vec3, c2w: Mat4) -> Vec3 {
    if encoded == Vec3::ZERO {
        return Vec3::ZERO;
    }
    let camera = (encoded * 2.0 - Vec3::ONE) * Vec3::new(-1.0, 1.0, 1.0);
    c2w.transform_vector3(camera).normalize_or_zero()
}

impl PixelLabels {
    /// `labels` must have the view's size (`width`×`height`); `c2w` is the view's camera-to-world
    /// matrix, which turns the camera-space normal labels to world space.
    pub fn gather(labels: &ViewLabels, pixels: &[u32], width: usize, height: usize, c2w: Mat4, view: &str) -> Result<PixelLabels> {
        for (what, img) in [("albedo", &labels.albedo), ("normal", &labels.normal), ("roughness", &labels.roughness), ("metallic", &labels.metallic), ("mask", &labels.mask)] {
            ensure!(
                img.width == width && img.height == height,
                "labels of view {view}: {what} is {}×{}, the view is {width}×{height}",
                img.width,
                img.height
            );
            img.require_finite(&format!("labels of view {view}: {what} map"))?;
        }
        ensure!(labels.normal.channels >= 3, "labels of view {view}: normal has {} channels, need 3", labels.normal.channels);
        let (mut normal, mut normal_mask) = (Vec::with_capacity(3 * pixels.len()), Vec::with_capacity(pixels.len()));
        for &p in pixels {
            let (p, c) = (p as usize, labels.normal.channels);
            let encoded = Vec3::from_slice(&labels.normal.data[c * p..c * p + 3]);
            let n = world_normal(encoded, c2w);
            normal.extend_from_slice(&n.to_array());
            normal_mask.push(if n == Vec3::ZERO { 0.0 } else { labels.mask.data[p] });
        }
        Ok(PixelLabels {
            normal_world: Tensor::from_vec(normal, (pixels.len(), 1, 3), &Device::Cpu)?,
            normal_mask: Tensor::from_vec(normal_mask, (pixels.len(), 1, 1), &Device::Cpu)?,
            albedo_srgb: gather(&labels.albedo, pixels, 3, "albedo", view)?,
            roughness: gather(&labels.roughness, pixels, 1, "roughness", view)?,
            metallic: gather(&labels.metallic, pixels, 1, "metallic", view)?,
            mask: gather(&labels.mask, pixels, 1, "mask", view)?,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::prior::oracle::camera_normals;
    use crate::scene::camera::Camera;

    #[test]
    fn world_normals_undo_the_camera_space_labels() {
        // A camera looking at the origin from an oblique direction, and normals all round.
        let camera = Camera::look_at(Vec3::new(2.0, -3.0, 1.5), Vec3::ZERO, Vec3::Z, 0.7, 4, 4);
        let normals: Vec<Vec3> = (0..16).map(|i| Vec3::new((i as f32 * 1.3).sin(), (i as f32 * 0.7).cos(), 0.4 * i as f32 - 3.0).normalize()).collect();
        let mut world = Image::new(4, 4, 4);
        for (i, n) in normals.iter().enumerate() {
            world.data[4 * i..4 * i + 4].copy_from_slice(&[n.x, n.y, n.z, 1.0]);
        }
        let labels = camera_normals(&world, camera.c2w);
        for (i, n) in normals.iter().enumerate() {
            let back = world_normal(Vec3::from_slice(&labels.data[3 * i..3 * i + 3]), camera.c2w);
            assert!(back.distance(*n) < 1e-5, "pixel {i}: {n} → {back}");
        }
        assert_eq!(world_normal(Vec3::ZERO, camera.c2w), Vec3::ZERO);
    }
}

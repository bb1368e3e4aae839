//! Prior labels gathered at a training view's covered pixels, as constant tensors for the prior
//! term (docs/model.md, *Loss*).

use anyhow::{ensure, Result};
use candle_core::{Device, Tensor};

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

impl PixelLabels {
    /// `labels` must have the view's size (`width`×`height`).
    pub fn gather(labels: &ViewLabels, pixels: &[u32], width: usize, height: usize, view: &str) -> Result<PixelLabels> {
        for (what, img) in [("albedo", &labels.albedo), ("roughness", &labels.roughness), ("metallic", &labels.metallic), ("mask", &labels.mask)] {
            ensure!(
                img.width == width && img.height == height,
                "labels of view {view}: {what} is {}×{}, the view is {width}×{height}",
                img.width,
                img.height
            );
            img.require_finite(&format!("labels of view {view}: {what} map"))?;
        }
        labels.normal.require_finite(&format!("labels of view {view}: normal map"))?;
        Ok(PixelLabels {
            albedo_srgb: gather(&labels.albedo, pixels, 3, "albedo", view)?,
            roughness: gather(&labels.roughness, pixels, 1, "roughness", view)?,
            metallic: gather(&labels.metallic, pixels, 1, "metallic", view)?,
            mask: gather(&labels.mask, pixels, 1, "mask", view)?,
        })
    }
}

//! A mesh part's material as a scene file describes it (e.g. the hotdog's `materials.json`).

use std::sync::Arc;

use glam::{Vec2, Vec3};

use crate::image::Image;

/// Base colour: a constant or a texture (linear RGB in memory, looked up bilinearly, wrapping).
#[derive(Clone, Debug)]
pub enum BaseColor {
    Constant(Vec3),
    /// Linear RGB texture; OBJ convention: v = 0 is the bottom row.
    Texture(Arc<Image>),
}

#[derive(Clone, Debug)]
pub struct PartMaterial {
    pub name: String,
    pub base_color: BaseColor,
    pub roughness: f32,
    pub metallic: f32,
}

/// The BRDF inputs at one surface point (NVDiffRecMC's kd and ks = (0, roughness, metallic)).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfaceParams {
    pub kd: Vec3,
    pub roughness: f32,
    pub metallic: f32,
}

impl PartMaterial {
    pub fn eval(&self, uv: Vec2) -> SurfaceParams {
        let kd = match &self.base_color {
            BaseColor::Constant(c) => *c,
            BaseColor::Texture(img) => {
                // Wrap like a repeating texture; flip v because row 0 is the top of the image.
                let u = uv.x - uv.x.floor();
                let v = 1.0 - (uv.y - uv.y.floor());
                let mut c = [0.0f32; 3];
                img.bilinear(u * img.width as f32, v * img.height as f32, &mut c);
                Vec3::from_array(c)
            }
        };
        SurfaceParams { kd, roughness: self.roughness, metallic: self.metallic }
    }

    pub fn is_glossy(&self) -> bool {
        self.roughness < 0.5 || self.metallic > 0.0
    }
}

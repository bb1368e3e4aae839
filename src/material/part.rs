//! A mesh part's material as a scene file describes it (a ground-truth `materials.json`, an MTL or
//! glTF file): base colour, roughness and metallic, each a constant or a texture over the part's UVs.

use std::sync::Arc;

use glam::{Vec2, Vec3};

use crate::image::Image;
use crate::math::floor_f32;

/// Base colour: a constant or a texture (linear RGB in memory, looked up bilinearly, wrapping).
#[derive(Clone, Debug)]
pub enum BaseColor {
    Constant(Vec3),
    /// Linear RGB texture; OBJ convention: v = 0 is the bottom row.
    Texture(Arc<Image>),
}

/// Roughness or metallic: a constant or a texture (linear values, channel 0 is read; looked up
/// bilinearly, wrapping, v = 0 at the bottom row like the base colour).
#[derive(Clone, Debug)]
pub enum Scalar {
    Constant(f32),
    Texture(Arc<Image>),
}

impl Scalar {
    /// The smallest and largest value the material can take (over every texel of a texture).
    pub fn range(&self) -> (f32, f32) {
        match self {
            Scalar::Constant(v) => (*v, *v),
            Scalar::Texture(img) => img
                .data
                .iter()
                .step_by(img.channels.max(1))
                .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), &v| (lo.min(v), hi.max(v))),
        }
    }

    /// The constant, or a texture's mean texel (what a file format without textures can store).
    pub fn mean(&self) -> f32 {
        match self {
            Scalar::Constant(v) => *v,
            Scalar::Texture(img) => {
                let n = img.pixel_count().max(1);
                (img.data.iter().step_by(img.channels.max(1)).map(|&v| v as f64).sum::<f64>() / n as f64) as f32
            }
        }
    }

    /// The constant, or `None` for a texture.
    pub fn constant(&self) -> Option<f32> {
        match self {
            Scalar::Constant(v) => Some(*v),
            Scalar::Texture(_) => None,
        }
    }
}

impl std::fmt::Display for Scalar {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Scalar::Constant(v) => write!(f, "{v:.2}"),
            Scalar::Texture(_) => {
                let (lo, hi) = self.range();
                write!(f, "{lo:.2}–{hi:.2} (texture)")
            }
        }
    }
}

#[derive(Clone, Debug)]
pub struct PartMaterial {
    pub name: String,
    pub base_color: BaseColor,
    pub roughness: Scalar,
    pub metallic: Scalar,
}

/// The BRDF inputs at one surface point (NVDiffRecMC's kd and ks = (0, roughness, metallic)).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfaceParams {
    pub kd: Vec3,
    pub roughness: f32,
    pub metallic: f32,
}

/// Bilinear lookup of a part texture at `uv`: wraps like a repeating texture and flips v (row 0
/// is the top of the image, v = 0 the bottom).
fn lookup(img: &Image, uv: Vec2, out: &mut [f32]) {
    let u = uv.x - floor_f32(uv.x);
    let v = 1.0 - (uv.y - floor_f32(uv.y));
    img.bilinear(u * img.width as f32, v * img.height as f32, out);
}

impl PartMaterial {
    /// A material of constants.
    pub fn constant(name: &str, base_color: Vec3, roughness: f32, metallic: f32) -> PartMaterial {
        let (base_color, roughness, metallic) = (BaseColor::Constant(base_color), Scalar::Constant(roughness), Scalar::Constant(metallic));
        PartMaterial { name: name.into(), base_color, roughness, metallic }
    }

    /// The BRDF inputs at surface UV `uv` (the one place part materials are evaluated).
    pub fn eval(&self, uv: Vec2) -> SurfaceParams {
        let kd = match &self.base_color {
            BaseColor::Constant(c) => *c,
            BaseColor::Texture(img) => {
                let mut c = [0.0f32; 3];
                lookup(img, uv, &mut c);
                Vec3::from_array(c)
            }
        };
        let scalar = |s: &Scalar| match s {
            Scalar::Constant(v) => *v,
            Scalar::Texture(img) => {
                let mut c = [0.0f32; 1];
                lookup(img, uv, &mut c);
                c[0]
            }
        };
        SurfaceParams { kd, roughness: scalar(&self.roughness), metallic: scalar(&self.metallic) }
    }

    /// Whether any point of the part can be glossy (roughness below 0.5 or some metal).
    pub fn is_glossy(&self) -> bool {
        self.roughness.range().0 < 0.5 || self.metallic.range().1 > 0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn textured_roughness_and_metallic_are_looked_up_like_the_base_colour() {
        // 2×1 textures: left texel 0.2, right 0.8 (roughness); metallic 1 then 0.
        let rough = Image { width: 2, height: 1, channels: 1, data: vec![0.2, 0.8] };
        let metal = Image { width: 2, height: 1, channels: 1, data: vec![1.0, 0.0] };
        let m = PartMaterial {
            name: "m".into(),
            base_color: BaseColor::Constant(Vec3::new(0.1, 0.2, 0.3)),
            roughness: Scalar::Texture(Arc::new(rough)),
            metallic: Scalar::Texture(Arc::new(metal)),
        };
        // Texel centres at u = 0.25 and 0.75; halfway between them the lookup is the mean.
        let p = m.eval(Vec2::new(0.25, 0.5));
        assert_eq!((p.kd, p.roughness, p.metallic), (Vec3::new(0.1, 0.2, 0.3), 0.2, 1.0));
        let p = m.eval(Vec2::new(1.75, 0.5)); // wraps to u = 0.75
        assert!((p.roughness - 0.8).abs() < 1e-6 && p.metallic.abs() < 1e-6, "{p:?}");
        let p = m.eval(Vec2::new(0.5, 0.5));
        assert!((p.roughness - 0.5).abs() < 1e-6 && (p.metallic - 0.5).abs() < 1e-6, "{p:?}");
        assert_eq!(m.roughness.range(), (0.2, 0.8));
        assert!(m.is_glossy());
        assert!(!PartMaterial::constant("c", Vec3::ONE, 0.9, 0.0).is_glossy());
    }
}

//! Surface materials: the GGX/Lambert BRDF of docs/model.md (*BRDF*) and per-part material descriptions.

pub mod brdf;
pub mod brdf_grad;
pub mod field;
pub mod normal_map;
mod part;
pub mod texture_maps;

pub use field::MaterialField;
pub use part::{BaseColor, PartMaterial, Scalar, SurfaceParams};

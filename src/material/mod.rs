//! Surface materials: the GGX/Lambert BRDF of DESIGN.md §3 and per-part material descriptions.

pub mod brdf;
pub mod brdf_grad;
mod part;
pub mod texture_maps;

pub use part::{BaseColor, PartMaterial, SurfaceParams};

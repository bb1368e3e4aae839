//! Environment light: cube map, lat-long conversion, mip chain, split-sum prefiltering,
//! the BRDF lookup table, and importance sampling by texel.

pub mod brdf_lut;
pub mod cubemap;
pub mod latlong;
pub mod prefilter;
pub mod sampler;

pub use cubemap::CubeMap;

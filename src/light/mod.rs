//! Environment light: cube map, lat-long conversion, mip chain, split-sum prefiltering,
//! the BRDF lookup table, and importance sampling by texel.

pub mod brdf_lut;
pub mod cubemap;
pub mod latlong;
pub mod prefilter;
pub mod sampler;

pub use brdf_lut::BrdfLut;
pub use cubemap::CubeMap;
pub use prefilter::SplitSumLight;
pub use sampler::{LightSample, LightSampler};

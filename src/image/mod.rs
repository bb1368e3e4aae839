//! Pictures in memory (linear f32, interleaved channels) and their files (PNG, EXR, HDR).

mod buffer;
pub mod io;
pub mod safe_decode;

pub use buffer::Image;

//! Plumbing shared by the UNet's CPU kernels (candle custom ops, inference only).
use candle_core::backend::BackendStorage;
use candle_core::{bail, CpuStorage, Layout, Result};

/// The f32 elements of a contiguous tensor, in order.
pub fn contiguous_f32<'a>(s: &'a CpuStorage, l: &Layout, op: &str) -> Result<&'a [f32]> {
    match (s, l.contiguous_offsets()) {
        (CpuStorage::F32(v), Some((start, end))) => Ok(&v[start..end]),
        (CpuStorage::F32(_), None) => bail!("{op}: expects a contiguous input"),
        _ => bail!("{op}: expects f32, got {:?}", s.dtype()),
    }
}

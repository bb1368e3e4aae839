//! The CPU kernels under the port: candle custom ops (inference only) that fuse what the official
//! modules do in several PyTorch calls (`conv`, `linear`, `group_norm`, GEGLU's gating in `geglu`),
//! and their building blocks (`matmul` on strided views through the gemm crate, the online
//! `softmax`, branch-free `vector_math`, per-thread `scratch` buffers). Kept apart from the files
//! beside them, which mirror the official IDArb / diffusers / transformers modules one to one, so
//! a reader can hold the port beside the reference. docs/scale.md lists which need a GPU path.

pub mod conv;
pub mod geglu;
pub mod group_norm;
pub mod linear;
pub mod matmul;
pub mod scratch;
pub mod softmax;
pub mod vector_math;

//! The IDArb network (ICLR 2025) ported to candle: per-view albedo, normal, metallic and roughness
//! from N RGBA views. Module names mirror the official modules and weight keys.
//!
//! Entry point: [`labels_for_views`]. The parts: [`unet_dr2d_condition`] (UNet-DR2D) built from
//! [`unet_dr2d_blocks`], [`transformer_dr2d`] (cross-domain / cross-view attention with [`cape`]),
//! [`resnet`], [`attention`]; [`autoencoder_kl`] (VAE); [`scheduling_ddim`]; [`preprocess`];
//! [`pipeline_idarbdiffusion`] (sampling loop); the prompt embeddings from the folder's own
//! [`tokenization_clip`] and [`modeling_clip`] text tower ([`text_embeddings`]); [`weights`];
//! [`labels`] and [`labels_cache`]. The CPU kernels these run on (fused convolution, linear,
//! group norm, GEGLU, matrix products, softmax) are in [`kernels`], apart from the mirrored modules.

pub mod attention;
pub mod autoencoder_kl;
pub mod cape;
pub mod feed_forward;
pub mod kernels;
pub mod labels;
pub mod labels_cache;
pub mod modeling_clip;
pub mod pipeline_idarbdiffusion;
pub mod preprocess;
pub mod resnet;
pub mod scheduling_ddim;
pub mod text_embeddings;
pub mod tokenization_clip;
pub mod transformer_dr2d;
pub mod unet_dr2d_blocks;
pub mod unet_dr2d_condition;
pub mod weights;

pub use labels::{labels_for_views, run_network, IdarbOptions, InputEncoding};
pub use pipeline_idarbdiffusion::IdarbPipeline;
pub use preprocess::{default_pose, pose_from_camera_origin};
pub use weights::{resolve_weights_dir, WeightFiles, NO_WEIGHTS_MESSAGE, WEIGHTS_ENV};

//! Optimisation: the tape pattern for differentiable kernels, the gradient checker, the
//! differentiable operators that do not depend on the renderer (texture lookups, sRGB, image loss,
//! prior loss, regularisers) and Adam with its schedule. The cross-bilateral denoiser, which uses
//! the same tape, lives in `render::denoise`.

pub mod adam;
pub mod gradcheck;
pub mod guarded_step;
pub mod large_steps;
pub mod laplacian;
pub mod light_balance;
pub mod loss;
pub mod mip;
pub mod prior_loss;
pub mod shading;
pub mod smoothness;
pub mod srgb;
pub mod tape;
pub mod texture;
pub mod vertex_smoothness;
pub mod weights;

pub use adam::{Adam, GroupConfig, LrSchedule};
pub use gradcheck::{check_gradient, check_gradient_with, GradCheckOptions, GradReport};
pub use laplacian::UniformLaplacian;
pub use loss::{image_loss, log_srgb, LossTarget};
pub use mip::{build_pyramid, sample_trilinear, MipLevels};
pub use prior_loss::prior_loss;
pub use shading::shading_regularizer;
pub use smoothness::{smoothness_regularizer, JitteredLookups, JitteredUv};
pub use srgb::srgb_encode;
pub use tape::{apply, scatter_add_banded, Kernel, Real};
pub use texture::{jitter_uv, sample_bilinear, BilinearWrap};
pub use weights::RegularizerWeights;

//! Default weights of the regularisers of the material and light fit, as NVDiffRecMC sets them
//! (train.py flags) or, for the light, NVDiffRec's training loop, so a run can cite where each
//! number comes from. Every weight here is applied by `fit::objective` (docs/model.md, *Loss*).

/// λ of each regulariser; the image loss has weight 1.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RegularizerWeights {
    /// kd smoothness (`lambda_kd`).
    pub kd_smoothness: f64,
    /// ks smoothness (`lambda_ks`).
    pub ks_smoothness: f64,
    /// Monochrome shading: diffuse part (`lambda_diffuse`). Monte Carlo mode only: split-sum
    /// shading has no separate diffuse and specular light buffers.
    pub shading_diffuse: f64,
    /// Monochrome shading: specular/diffuse ratio (`lambda_specular`). Monte Carlo mode only.
    pub shading_specular: f64,
    /// Light white balance (NVDiffRec's `lgt.regularizer() * 0.005`).
    pub light_white_balance: f64,
}

impl Default for RegularizerWeights {
    fn default() -> Self {
        RegularizerWeights { kd_smoothness: 0.1, ks_smoothness: 0.05, shading_diffuse: 0.15, shading_specular: 0.0025, light_white_balance: 0.005 }
    }
}

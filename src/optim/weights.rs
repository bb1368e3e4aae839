//! Default weights of the loss terms, as NVDiffRecMC sets them (train.py flags and
//! geometry/dlmesh.py), so a run can cite where each number comes from.

/// λ of each regulariser; the image loss has weight 1.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RegularizerWeights {
    /// kd smoothness (`lambda_kd`).
    pub kd_smoothness: f64,
    /// ks smoothness (`lambda_ks`).
    pub ks_smoothness: f64,
    /// Monochrome shading: diffuse part (`lambda_diffuse`).
    pub shading_diffuse: f64,
    /// Monochrome shading: specular/diffuse ratio (`lambda_specular`).
    pub shading_specular: f64,
    /// Laplacian on vertex offsets (`laplace_scale`, "relative" mode), ramped down linearly to 0
    /// over the run.
    pub laplacian: f64,
    /// Light white balance (NVDiffRec's `lgt.regularizer() * 0.005`).
    pub light_white_balance: f64,
}

impl Default for RegularizerWeights {
    fn default() -> Self {
        RegularizerWeights {
            kd_smoothness: 0.1,
            ks_smoothness: 0.05,
            shading_diffuse: 0.15,
            shading_specular: 0.0025,
            laplacian: 3000.0,
            light_white_balance: 0.005,
        }
    }
}

impl RegularizerWeights {
    /// The Laplacian weight at `step` of `total` steps: λ·(1 − step/total).
    pub fn laplacian_at(&self, step: usize, total: usize) -> f64 {
        if total == 0 {
            return self.laplacian;
        }
        self.laplacian * (1.0 - (step as f64 / total as f64).min(1.0))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn laplacian_weight_ramps_from_full_to_zero() {
        let w = RegularizerWeights::default();
        assert_eq!(w.laplacian_at(0, 100), 3000.0);
        assert_eq!(w.laplacian_at(50, 100), 1500.0);
        assert_eq!(w.laplacian_at(100, 100), 0.0);
        assert_eq!(w.laplacian_at(200, 100), 0.0);
    }
}

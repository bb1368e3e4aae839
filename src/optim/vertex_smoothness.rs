//! Smoothness of a per-vertex attribute (the geometry pass's base colour): the mean over the
//! mesh's edges of mean_c |f_a − f_b|, the L1 difference across each edge. It is NVDiffRecMC's kd
//! smoothness term (|kd(x) − kd(x + jitter)|, `optim::smoothness` for textures) with the neighbour
//! one edge away instead of at a jittered point.
//!
//! Why the geometry pass needs it: with a free colour per vertex, Lambertian shading kd·E(n) can
//! match any pixel's brightness with any normal, since kd absorbs the shading; the images then
//! pin the surface only through multi-view consistency, and a concavity the visual hull bridged
//! stays bridged. Colour that must vary smoothly leaves the shading to the normals.
//!
//! Built from candle ops (gather, difference, |·|, mean), so candle's autodiff is its backward;
//! the finite-difference test below checks it like the hand-written kernels.

use candle_core::{Device, Result, Tensor};

use super::laplacian::UniformLaplacian;

/// The mesh's edges as two index tensors, built once per connectivity.
pub struct VertexSmoothness {
    from: Tensor,
    to: Tensor,
}

impl VertexSmoothness {
    pub fn new(laplacian: &UniformLaplacian) -> Result<Self> {
        let edges = laplacian.edges();
        let dev = &Device::Cpu;
        let from = Tensor::from_vec(edges.iter().map(|e| e[0]).collect::<Vec<_>>(), edges.len(), dev)?;
        let to = Tensor::from_vec(edges.iter().map(|e| e[1]).collect::<Vec<_>>(), edges.len(), dev)?;
        Ok(VertexSmoothness { from, to })
    }

    /// mean over edges and channels of |f_a − f_b| for `values` [V, C] (0 for a mesh without edges).
    pub fn apply(&self, values: &Tensor) -> Result<Tensor> {
        if self.from.dims1()? == 0 {
            return values.zeros_like()?.sum_all();
        }
        (values.index_select(&self.from, 0)? - values.index_select(&self.to, 0)?)?.abs()?.mean_all()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optim::gradcheck::check_gradient;

    fn square() -> (UniformLaplacian, Vec<f64>) {
        // Two triangles over four vertices: five edges.
        let l = UniformLaplacian::new(4, &[[0, 1, 2], [0, 2, 3]]).expect("valid triangles");
        (l, vec![0.1, 0.5, 0.9, 0.4, 0.2, 0.3, 0.8, 0.7, 0.05, 0.6, 0.45, 0.35])
    }

    #[test]
    fn value_is_the_mean_edge_difference() -> anyhow::Result<()> {
        let (l, v) = square();
        assert_eq!(l.edges(), vec![[0, 1], [0, 2], [0, 3], [1, 2], [2, 3]]);
        let s = VertexSmoothness::new(&l)?;
        let got = s.apply(&Tensor::from_vec(v.clone(), (4, 3), &Device::Cpu)?)?.to_scalar::<f64>()?;
        let px = |i: usize| &v[3 * i..3 * i + 3];
        let want: f64 = l.edges().iter().map(|e| (0..3).map(|c| (px(e[0] as usize)[c] - px(e[1] as usize)[c]).abs()).sum::<f64>()).sum::<f64>() / 15.0;
        assert!((got - want).abs() < 1e-12, "{got} vs {want}");
        Ok(())
    }

    #[test]
    fn gradients_match_finite_differences() -> anyhow::Result<()> {
        // No two neighbours share a channel value, so |·| is differentiable at this point.
        let (l, v) = square();
        let s = VertexSmoothness::new(&l)?;
        let report = check_gradient(|x| s.apply(&x[0]), &[Tensor::from_vec(v, (4, 3), &Device::Cpu)?], 1e-7, 1e-6)?;
        println!("{report}");
        Ok(())
    }
}

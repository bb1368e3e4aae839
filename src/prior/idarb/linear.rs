//! torch's `Linear` for inference, y = x Wᵀ + b, as one product accumulating onto rows that start
//! as the bias: candle-nn's Linear multiplies, then adds the bias in a second pass into a second
//! fresh tensor.
use super::cpu_kernel::contiguous_f32;
use super::matmul::{gemm, MatMut, MatRef};
use candle_core::{bail, CpuStorage, CustomOp2, CustomOp3, Layout, Module, Result, Shape, Tensor};
use candle_nn::VarBuilder;
use rayon::prelude::*;

#[derive(Debug, Clone)]
pub struct Linear {
    /// [out, in], contiguous.
    weight: Tensor,
    /// [out].
    bias: Option<Tensor>,
}

/// `weight` and `bias` under `vb`, initialised as candle-nn's when created (random weights).
pub fn linear(in_dim: usize, out_dim: usize, vb: VarBuilder) -> Result<Linear> {
    let l = candle_nn::linear(in_dim, out_dim, vb)?;
    Ok(Linear { weight: l.weight().contiguous()?, bias: l.bias().cloned() })
}

/// [`linear`] without a bias.
pub fn linear_no_bias(in_dim: usize, out_dim: usize, vb: VarBuilder) -> Result<Linear> {
    let l = candle_nn::linear_no_bias(in_dim, out_dim, vb)?;
    Ok(Linear { weight: l.weight().contiguous()?, bias: None })
}

impl Module for Linear {
    /// `x`: [..., in] f32 → [..., out].
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let x = x.contiguous()?;
        match &self.bias {
            Some(b) => x.apply_op3_no_bwd(&self.weight, b, &LinearKernel),
            None => x.apply_op2_no_bwd(&self.weight, &LinearKernel),
        }
    }
}

struct LinearKernel;

impl LinearKernel {
    fn run(&self, x: &[f32], xl: &Layout, w: &[f32], wl: &Layout, bias: Option<&[f32]>) -> Result<(CpuStorage, Shape)> {
        let (out_dim, in_dim) = wl.shape().dims2()?;
        let dims = xl.dims();
        if dims.last() != Some(&in_dim) || bias.is_some_and(|b| b.len() != out_dim) {
            bail!("linear: input {:?}, weight {:?}", xl.shape(), wl.shape());
        }
        let m = x.len() / in_dim.max(1);
        let mut y = vec![0f32; m * out_dim];
        if let Some(b) = bias {
            y.par_chunks_mut(out_dim.max(1)).for_each(|row| row.copy_from_slice(b));
        }
        gemm(MatMut::new(&mut y, m, out_dim, out_dim, 1), MatRef::new(x, m, in_dim, in_dim, 1), MatRef::new(w, out_dim, in_dim, in_dim, 1).t(), 1.0, bias.is_some(), true);
        let mut shape = dims.to_vec();
        *shape.last_mut().expect("checked above") = out_dim;
        Ok((CpuStorage::F32(y), Shape::from_dims(&shape)))
    }
}

impl CustomOp2 for LinearKernel {
    fn name(&self) -> &'static str {
        "idarb-linear"
    }

    fn cpu_fwd(&self, xs: &CpuStorage, xl: &Layout, ws: &CpuStorage, wl: &Layout) -> Result<(CpuStorage, Shape)> {
        self.run(contiguous_f32(xs, xl, "linear")?, xl, contiguous_f32(ws, wl, "linear")?, wl, None)
    }
}

impl CustomOp3 for LinearKernel {
    fn name(&self) -> &'static str {
        "idarb-linear"
    }

    fn cpu_fwd(&self, xs: &CpuStorage, xl: &Layout, ws: &CpuStorage, wl: &Layout, bs: &CpuStorage, bl: &Layout) -> Result<(CpuStorage, Shape)> {
        self.run(contiguous_f32(xs, xl, "linear")?, xl, contiguous_f32(ws, wl, "linear")?, wl, Some(contiguous_f32(bs, bl, "linear")?))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Device};
    use std::collections::HashMap;

    /// Against candle-nn's Linear on a 3-D input, with and without a bias.
    #[test]
    fn matches_candle_nn_linear() -> Result<()> {
        let dev = Device::Cpu;
        let w = Tensor::randn(0f32, 1.0, (6, 5), &dev)?;
        let b = Tensor::randn(0f32, 1.0, 6, &dev)?;
        let x = Tensor::randn(0f32, 1.0, (2, 3, 5), &dev)?;
        let vb = VarBuilder::from_tensors(HashMap::from([("weight".to_string(), w.clone()), ("bias".to_string(), b.clone())]), DType::F32, &dev);
        for (ours, theirs) in [
            (linear(5, 6, vb.clone())?, candle_nn::Linear::new(w.clone(), Some(b.clone()))),
            (linear_no_bias(5, 6, vb)?, candle_nn::Linear::new(w.clone(), None)),
        ] {
            let d = (ours.forward(&x)? - theirs.forward(&x)?)?.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?;
            assert!(d < 1e-5, "linear differs by {d}");
        }
        Ok(())
    }
}

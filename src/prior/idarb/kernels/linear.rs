//! torch's `Linear` for inference, y = x Wᵀ + b (+ a residual), as one product accumulating onto
//! rows that start as the bias (and residual): candle-nn's Linear multiplies, then adds the bias
//! in a second pass into a second fresh tensor, and a residual add would be a third.
use crate::optim::tape::contiguous_slice;
use super::matmul::{gemm, MatMut, MatRef};
use candle_core::{bail, CpuStorage, CustomOp2, CustomOp3, Layout, Module, Result, Shape, Storage, Tensor};
use candle_nn::VarBuilder;
use rayon::prelude::*;

#[derive(Debug, Clone)]
pub struct Linear {
    /// [out, in], contiguous.
    weight: Tensor,
    bias: Option<Vec<f32>>,
}

/// `weight` and `bias` under `vb`, initialised as candle-nn's when created (random weights).
pub fn linear(in_dim: usize, out_dim: usize, vb: VarBuilder) -> Result<Linear> {
    let l = candle_nn::linear(in_dim, out_dim, vb)?;
    Ok(Linear { weight: l.weight().contiguous()?, bias: l.bias().map(Tensor::to_vec1::<f32>).transpose()? })
}

/// [`linear`] without a bias.
pub fn linear_no_bias(in_dim: usize, out_dim: usize, vb: VarBuilder) -> Result<Linear> {
    let l = candle_nn::linear_no_bias(in_dim, out_dim, vb)?;
    Ok(Linear { weight: l.weight().contiguous()?, bias: None })
}

impl Linear {
    /// `residual` + x Wᵀ + b, `residual` shaped as the output.
    pub fn forward_plus(&self, x: &Tensor, residual: &Tensor) -> Result<Tensor> {
        x.contiguous()?.apply_op3_no_bwd(&self.weight, &residual.contiguous()?, &LinearKernel { bias: self.bias.as_deref() })
    }

    /// dst ← x Wᵀ + b, or dst ← dst + x Wᵀ + b when `accumulate`, for rows of `x` (row-major,
    /// `in` wide) and of `dst` (`out` wide): the slice-level product fused kernels build on.
    pub fn product_into(&self, x: &[f32], dst: &mut [f32], accumulate: bool) -> Result<()> {
        let (storage, layout) = self.weight.storage_and_layout();
        let w = match &*storage {
            Storage::Cpu(s) => contiguous_slice::<f32>("linear", s, layout)?,
            _ => bail!("linear: CPU tensors only"),
        };
        product_into(x, w, layout, self.bias.as_deref(), dst, accumulate)
    }
}

/// dst (+)= x Wᵀ + b for a weight `w` [out, in] (layout `wl`): the bias goes in first and the
/// product accumulates onto it.
fn product_into(x: &[f32], w: &[f32], wl: &Layout, bias: Option<&[f32]>, dst: &mut [f32], accumulate: bool) -> Result<()> {
    let (out_dim, in_dim) = wl.shape().dims2()?;
    let m = x.len() / in_dim.max(1);
    if x.len() != m * in_dim || dst.len() != m * out_dim || bias.is_some_and(|b| b.len() != out_dim) {
        bail!("linear: {} inputs and {} outputs for a weight {:?}", x.len(), dst.len(), wl.shape());
    }
    if let Some(b) = bias {
        dst.par_chunks_mut(out_dim.max(1)).for_each(|row| match accumulate {
            true => row.iter_mut().zip(b).for_each(|(y, b)| *y += b),
            false => row.copy_from_slice(b),
        });
    }
    let onto = accumulate || bias.is_some();
    gemm(MatMut::new(dst, m, out_dim, out_dim, 1), MatRef::new(x, m, in_dim, in_dim, 1), MatRef::new(w, out_dim, in_dim, in_dim, 1).t(), 1.0, onto, true);
    Ok(())
}

impl Module for Linear {
    /// `x`: [..., in] f32 → [..., out].
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        x.contiguous()?.apply_op2_no_bwd(&self.weight, &LinearKernel { bias: self.bias.as_deref() })
    }
}

struct LinearKernel<'a> {
    bias: Option<&'a [f32]>,
}

impl LinearKernel<'_> {
    fn run(&self, x: &[f32], xl: &Layout, w: &[f32], wl: &Layout, residual: Option<(&[f32], &Layout)>) -> Result<(CpuStorage, Shape)> {
        let (out_dim, in_dim) = wl.shape().dims2()?;
        let mut shape = xl.dims().to_vec();
        if shape.last() != Some(&in_dim) {
            bail!("linear: input {:?}, weight {:?}", xl.shape(), wl.shape());
        }
        *shape.last_mut().expect("checked above") = out_dim;
        let y = match residual {
            Some((r, rl)) if rl.dims() == shape.as_slice() => {
                // residual + bias in one pass, then the product onto it
                let mut y = vec![0f32; r.len()];
                y.par_chunks_mut(out_dim.max(1)).zip(r.par_chunks(out_dim.max(1))).for_each(|(y, r)| match self.bias {
                    Some(b) => y.iter_mut().zip(r).zip(b).for_each(|((y, r), b)| *y = r + b),
                    None => y.copy_from_slice(r),
                });
                product_into(x, w, wl, None, &mut y, true)?;
                y
            }
            Some((_, rl)) => bail!("linear: residual {:?} for an output {shape:?}", rl.shape()),
            None => {
                let mut y = vec![0f32; x.len() / in_dim.max(1) * out_dim];
                product_into(x, w, wl, self.bias, &mut y, false)?;
                y
            }
        };
        Ok((CpuStorage::F32(y), Shape::from_dims(&shape)))
    }
}

impl CustomOp2 for LinearKernel<'_> {
    fn name(&self) -> &'static str {
        "idarb-linear"
    }

    fn cpu_fwd(&self, xs: &CpuStorage, xl: &Layout, ws: &CpuStorage, wl: &Layout) -> Result<(CpuStorage, Shape)> {
        self.run(contiguous_slice::<f32>("linear", xs, xl)?, xl, contiguous_slice::<f32>("linear", ws, wl)?, wl, None)
    }
}

impl CustomOp3 for LinearKernel<'_> {
    fn name(&self) -> &'static str {
        "idarb-linear"
    }

    fn cpu_fwd(&self, xs: &CpuStorage, xl: &Layout, ws: &CpuStorage, wl: &Layout, rs: &CpuStorage, rl: &Layout) -> Result<(CpuStorage, Shape)> {
        self.run(contiguous_slice::<f32>("linear", xs, xl)?, xl, contiguous_slice::<f32>("linear", ws, wl)?, wl, Some((contiguous_slice::<f32>("linear", rs, rl)?, rl)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Device};
    use std::collections::HashMap;

    /// Against candle-nn's Linear on a 3-D input, with and without a bias and a residual.
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
            let want = theirs.forward(&x)?;
            let d = (ours.forward(&x)? - &want)?.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?;
            assert!(d < 1e-5, "linear differs by {d}");
            let r = Tensor::randn(0f32, 1.0, want.dims(), &dev)?;
            let d = (ours.forward_plus(&x, &r)? - (want + &r)?)?.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?;
            assert!(d < 1e-5, "linear with residual differs by {d}");
        }
        Ok(())
    }
}

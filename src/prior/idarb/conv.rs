//! 2-D convolution through candle, with a workaround for a candle-core 0.9 CPU bug: its tiled
//! im2col kernel mistakes a contiguous NCHW input for channels-last when C = H = W (e.g. 16
//! channels at 16×16) and returns wrong values. Such inputs are handed over as a channels-last
//! view, which takes the kernel's (correct) copying path. candle-core 0.11 no longer has the bug.
use candle_core::{Module, Result, Tensor};
use candle_nn::{Conv2dConfig, VarBuilder};

#[derive(Debug, Clone)]
pub struct Conv2d {
    inner: candle_nn::Conv2d,
    kernel: usize,
}

pub fn conv2d(in_channels: usize, out_channels: usize, kernel: usize, cfg: Conv2dConfig, vb: VarBuilder) -> Result<Conv2d> {
    Ok(Conv2d { inner: candle_nn::conv2d(in_channels, out_channels, kernel, cfg, vb)?, kernel })
}

impl Module for Conv2d {
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let (_, c, h, w) = x.dims4()?;
        if self.kernel > 1 && c == h && c == w {
            let channels_last = x.permute((0, 2, 3, 1))?.contiguous()?.permute((0, 3, 1, 2))?;
            return self.inner.forward(&channels_last);
        }
        self.inner.forward(x)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Device};
    use std::collections::HashMap;

    /// 3×3 convolution (padding 1) against a direct loop, including the C = H = W case.
    #[test]
    fn matches_direct_convolution() -> Result<()> {
        let dev = Device::Cpu;
        for (ci, co, hw) in [(16usize, 24usize, 16usize), (8, 8, 8), (5, 3, 7)] {
            let x = Tensor::randn(0f32, 1.0, (1, ci, hw, hw), &dev)?;
            let wt = Tensor::randn(0f32, 1.0, (co, ci, 3, 3), &dev)?;
            let b = Tensor::zeros(co, DType::F32, &dev)?;
            let vb = VarBuilder::from_tensors(HashMap::from([("weight".to_string(), wt.clone()), ("bias".to_string(), b)]), DType::F32, &dev);
            let got = conv2d(ci, co, 3, Conv2dConfig { padding: 1, ..Default::default() }, vb)?.forward(&x)?.flatten_all()?.to_vec1::<f32>()?;
            let (xv, wv) = (x.flatten_all()?.to_vec1::<f32>()?, wt.flatten_all()?.to_vec1::<f32>()?);
            for o in 0..co {
                for y in 0..hw {
                    for xx in 0..hw {
                        let mut s = 0f32;
                        for i in 0..ci {
                            for ky in 0..3 {
                                for kx in 0..3 {
                                    let (sy, sx) = (y as i64 + ky as i64 - 1, xx as i64 + kx as i64 - 1);
                                    if sy >= 0 && sx >= 0 && sy < hw as i64 && sx < hw as i64 {
                                        s += wv[((o * ci + i) * 3 + ky) * 3 + kx] * xv[(i * hw + sy as usize) * hw + sx as usize];
                                    }
                                }
                            }
                        }
                        let g = got[(o * hw + y) * hw + xx];
                        assert!((g - s).abs() < 1e-3, "{ci}->{co}@{hw} ({o},{y},{xx}): {g} vs {s}");
                    }
                }
            }
        }
        Ok(())
    }
}

//! diffusers `ResnetBlock2D`, `Downsample2D` and `Upsample2D` (shared by the UNet and the VAE).
use candle_core::{Module, Result, Tensor};
use super::kernels::conv::{conv2d, Conv2d};
use super::kernels::group_norm::{group_norm, GroupNorm};
use super::kernels::linear::{linear, Linear};
use candle_nn::{Conv2dConfig, VarBuilder};

fn conv3x3(vb: VarBuilder, i: usize, o: usize, stride: usize, padding: usize) -> Result<Conv2d> {
    conv2d(i, o, 3, Conv2dConfig { padding, stride, ..Default::default() }, vb)
}

/// norm1 → SiLU → conv1 (+ time projection) → norm2 → SiLU → conv2, plus a 1×1 shortcut when the
/// channel count changes. Output scale factor 1 (SD).
#[derive(Debug, Clone)]
pub struct ResnetBlock2D {
    norm1: GroupNorm,
    conv1: Conv2d,
    time_emb_proj: Option<Linear>,
    norm2: GroupNorm,
    conv2: Conv2d,
    conv_shortcut: Option<Conv2d>,
}

impl ResnetBlock2D {
    /// `temb_channels` is None in the VAE (no time conditioning).
    pub fn new(vb: VarBuilder, i: usize, o: usize, temb_channels: Option<usize>, groups: usize, eps: f64) -> Result<Self> {
        Ok(Self {
            norm1: group_norm(groups, i, eps, vb.pp("norm1"))?,
            conv1: conv3x3(vb.pp("conv1"), i, o, 1, 1)?,
            time_emb_proj: temb_channels.map(|t| linear(t, o, vb.pp("time_emb_proj"))).transpose()?,
            norm2: group_norm(groups, o, eps, vb.pp("norm2"))?,
            conv2: conv3x3(vb.pp("conv2"), o, o, 1, 1)?,
            conv_shortcut: if i != o { Some(conv2d(i, o, 1, Default::default(), vb.pp("conv_shortcut"))?) } else { None },
        })
    }

    /// `temb` is the already SiLU-free time embedding [B, T]; the block applies SiLU itself.
    /// The time projection enters conv1 as a per-image bias, the skip enters conv2 as a residual.
    pub fn forward(&self, x: &Tensor, temb: Option<&Tensor>) -> Result<Tensor> {
        let a = self.norm1.forward_silu(x)?;
        let h = match (&self.time_emb_proj, temb) {
            (Some(proj), Some(t)) => self.conv1.forward_plus(&a, &proj.forward(&t.silu()?)?)?,
            _ => self.conv1.forward(&a)?,
        };
        let a = self.norm2.forward_silu(&h)?;
        match &self.conv_shortcut {
            Some(c) => self.conv2.forward_plus(&a, &c.forward(x)?),
            None => self.conv2.forward_plus(&a, x),
        }
    }
}

/// Stride-2 3×3 convolution (`downsamplers.0.conv`).
#[derive(Debug, Clone)]
pub struct Downsample2D {
    conv: Conv2d,
    /// The VAE pads only right and bottom by one (padding 0 + asymmetric pad); the UNet pads 1.
    asymmetric_pad: bool,
}

impl Downsample2D {
    pub fn new(vb: VarBuilder, channels: usize, asymmetric_pad: bool) -> Result<Self> {
        let padding = if asymmetric_pad { 0 } else { 1 };
        Ok(Self { conv: conv3x3(vb.pp("conv"), channels, channels, 2, padding)?, asymmetric_pad })
    }

    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        if self.asymmetric_pad {
            let x = x.pad_with_zeros(3, 0, 1)?.pad_with_zeros(2, 0, 1)?;
            self.conv.forward(&x)
        } else {
            self.conv.forward(x)
        }
    }
}

/// Nearest ×2 upsampling then a 3×3 convolution (`upsamplers.0.conv`).
#[derive(Debug, Clone)]
pub struct Upsample2D {
    conv: Conv2d,
}

impl Upsample2D {
    pub fn new(vb: VarBuilder, channels: usize) -> Result<Self> {
        Ok(Self { conv: conv3x3(vb.pp("conv"), channels, channels, 1, 1)? })
    }

    /// `size` is the skip connection's spatial size (differs from 2× when a side was odd).
    pub fn forward(&self, x: &Tensor, size: Option<(usize, usize)>) -> Result<Tensor> {
        let (_, _, h, w) = x.dims4()?;
        let (th, tw) = size.unwrap_or((2 * h, 2 * w));
        self.conv.forward(&x.upsample_nearest2d(th, tw)?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Device};
    use std::collections::HashMap;

    /// The VAE's downsampler against a direct loop: zero pad right/bottom by one, 3×3 stride 2.
    #[test]
    fn asymmetric_downsample_matches_direct_convolution() -> Result<()> {
        let dev = Device::Cpu;
        let (c, h, w) = (3usize, 6usize, 5usize);
        let x = Tensor::randn(0f32, 1.0, (1, c, h, w), &dev)?;
        let wt = Tensor::randn(0f32, 1.0, (c, c, 3, 3), &dev)?;
        let b = Tensor::randn(0f32, 1.0, c, &dev)?;
        let vb = VarBuilder::from_tensors(HashMap::from([("conv.weight".to_string(), wt.clone()), ("conv.bias".to_string(), b.clone())]), DType::F32, &dev);
        let got = Downsample2D::new(vb, c, true)?.forward(&x)?;
        let (oh, ow) = ((h + 1 - 3) / 2 + 1, (w + 1 - 3) / 2 + 1);
        assert_eq!(got.dims(), &[1, c, oh, ow]);
        let xv = x.flatten_all()?.to_vec1::<f32>()?;
        let wv = wt.flatten_all()?.to_vec1::<f32>()?;
        let bv = b.to_vec1::<f32>()?;
        let gv = got.flatten_all()?.to_vec1::<f32>()?;
        for o in 0..c {
            for y in 0..oh {
                for xx in 0..ow {
                    let mut s = bv[o];
                    for i in 0..c {
                        for ky in 0..3 {
                            for kx in 0..3 {
                                let (sy, sx) = (2 * y + ky, 2 * xx + kx);
                                if sy < h && sx < w {
                                    s += wv[((o * c + i) * 3 + ky) * 3 + kx] * xv[(i * h + sy) * w + sx];
                                }
                            }
                        }
                    }
                    let g = gv[(o * oh + y) * ow + xx];
                    assert!((g - s).abs() < 1e-4, "({o},{y},{xx}): {g} vs {s}");
                }
            }
        }
        Ok(())
    }
}

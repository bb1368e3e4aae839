//! 2-D convolution (inference only) as matrix products: out[Co, pixels] = W[Co, Ci·k·k] ·
//! col[Ci·k·k, pixels], the im2col matrix built in a reused per-thread buffer of bounded size
//! (several small images per product, or one large image in bands of output rows); a 1×1
//! convolution multiplies the input itself. The products accumulate onto the bias, plus a
//! per-image bias (time embedding) or a residual when given, so those cost no pass of their own.
//! candle-core 0.9's conv2d spent as long in its im2col as in the product, faulted in a fresh
//! buffer each call, and got C = H = W inputs wrong.
use crate::optim::tape::contiguous_slice;
use super::matmul::{gemm, MatMut, MatRef};
use super::scratch::Scratch;
use candle_core::{bail, CpuStorage, CustomOp2, CustomOp3, Layout, Module, Result, Shape, Tensor};
use candle_nn::{Conv2dConfig, VarBuilder};
use rayon::prelude::*;

/// Largest im2col buffer, in bytes.
const COL_BUDGET_BYTES: usize = 64 << 20;

#[derive(Debug, Clone)]
pub struct Conv2d {
    /// [Co, Ci, k, k], contiguous.
    weight: Tensor,
    bias: Vec<f32>,
    shape: ConvShape,
}

/// Weights `weight` [Co, Ci, k, k] and `bias` [Co] under `vb`, initialised as candle-nn's conv2d
/// when they are created (random-weight benchmarks).
pub fn conv2d(in_channels: usize, out_channels: usize, kernel: usize, cfg: Conv2dConfig, vb: VarBuilder) -> Result<Conv2d> {
    if cfg.groups != 1 || cfg.dilation != 1 {
        bail!("conv2d: only groups = 1 and dilation = 1 are supported");
    }
    let conv = candle_nn::conv2d(in_channels, out_channels, kernel, cfg, vb)?;
    let bias = conv.bias().ok_or_else(|| candle_core::Error::Msg("conv2d: no bias".into()))?.to_vec1::<f32>()?;
    let shape = ConvShape { kernel, stride: cfg.stride, padding: cfg.padding, col_budget: COL_BUDGET_BYTES / 4 };
    Ok(Conv2d { weight: conv.weight().contiguous()?, bias, shape })
}

impl Conv2d {
    /// conv(x) + `extra`, where `extra` is a per-image bias [N, Co] or a residual [N, Co, H', W'].
    pub fn forward_plus(&self, x: &Tensor, extra: &Tensor) -> Result<Tensor> {
        let kernel = ConvKernel { shape: self.shape, bias: &self.bias };
        x.contiguous()?.apply_op3_no_bwd(&self.weight, &extra.contiguous()?, &kernel)
    }
}

impl Module for Conv2d {
    /// `x`: [N, Ci, H, W] f32 → [N, Co, H', W'].
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        x.contiguous()?.apply_op2_no_bwd(&self.weight, &ConvKernel { shape: self.shape, bias: &self.bias })
    }
}

#[derive(Debug, Clone, Copy)]
struct ConvShape {
    kernel: usize,
    stride: usize,
    padding: usize,
    /// Largest im2col buffer, in elements.
    col_budget: usize,
}

struct ConvKernel<'a> {
    shape: ConvShape,
    bias: &'a [f32],
}

/// Sizes of one convolution.
#[derive(Debug, Clone, Copy)]
struct Geometry {
    ci: usize,
    h: usize,
    w: usize,
    k: usize,
    stride: usize,
    pad: usize,
    wo: usize,
}

/// im2col for images `i0..i0 + images` and output rows `r0..r0 + rows`: row (c, ky, kx) of `col`
/// holds, image after image, the input value under tap (ky, kx) of channel c for every output pixel.
fn im2col(x: &[f32], g: Geometry, i0: usize, images: usize, r0: usize, rows: usize, col: &mut [f32]) {
    let (k, s, p, wo) = (g.k, g.stride, g.pad, g.wo);
    col.par_chunks_mut(images * rows * wo).enumerate().for_each(|(r, col_row)| {
        let (c, ky, kx) = (r / (k * k), (r / k) % k, r % k);
        // output columns whose tap lands inside the image (stride 1: one contiguous span)
        let lo = p.saturating_sub(kx).min(wo);
        let hi = (g.w + p).saturating_sub(kx).min(wo).max(lo);
        for (j, col_img) in col_row.chunks_mut(rows * wo).enumerate() {
            let plane = &x[((i0 + j) * g.ci + c) * g.h * g.w..][..g.h * g.w];
            for (oy, out) in col_img.chunks_mut(wo).enumerate() {
                let iy = (r0 + oy) * s + ky;
                if iy < p || iy - p >= g.h {
                    out.fill(0.0);
                    continue;
                }
                let src = &plane[(iy - p) * g.w..][..g.w];
                if s == 1 {
                    out[..lo].fill(0.0);
                    out[lo..hi].copy_from_slice(&src[lo + kx - p..hi + kx - p]);
                    out[hi..].fill(0.0);
                } else {
                    for (ox, o) in out.iter_mut().enumerate() {
                        let ix = ox * s + kx;
                        *o = if ix >= p && ix - p < g.w { src[ix - p] } else { 0.0 };
                    }
                }
            }
        }
    });
}

impl ConvKernel<'_> {
    fn run(&self, x: &[f32], xl: &Layout, wt: &[f32], wl: &Layout, extra: Option<(&[f32], &Layout)>) -> Result<(CpuStorage, Shape)> {
        let (n, ci, h, w) = xl.shape().dims4()?;
        let (co, wci, kh, kw) = wl.shape().dims4()?;
        let ConvShape { kernel: k, stride: s, padding: p, col_budget } = self.shape;
        if wci != ci || kh != k || kw != k || self.bias.len() != co || s == 0 || h + 2 * p < k || w + 2 * p < k {
            bail!("conv2d: input {:?}, weight {:?}, {} biases, stride {s}, padding {p}", xl.shape(), wl.shape(), self.bias.len());
        }
        let (ho, wo) = ((h + 2 * p - k) / s + 1, (w + 2 * p - k) / s + 1);
        let (hwo, kk) = (ho * wo, ci * k * k);
        if let Some((_, el)) = extra {
            if el.dims() != [n, co] && el.dims() != [n, co, ho, wo] {
                bail!("conv2d: the added term {:?} is neither [{n}, {co}] nor [{n}, {co}, {ho}, {wo}]", el.shape());
            }
        }
        let mut out = vec![0f32; n * co * hwo];
        // bias (+ extra) first: every product below accumulates onto it
        out.par_chunks_mut(hwo.max(1)).enumerate().for_each(|(i, plane)| {
            let b = self.bias[i % co];
            match extra {
                None => plane.fill(b),
                Some((e, _)) if e.len() == n * co => plane.fill(b + e[i]),
                Some((e, _)) => plane.iter_mut().zip(&e[i * hwo..][..hwo]).for_each(|(o, r)| *o = b + r),
            }
        });
        let wm = MatRef::new(wt, co, kk, kk, 1);
        if k == 1 && s == 1 && p == 0 {
            for (i, out_i) in out.chunks_mut(co * hwo).enumerate() {
                gemm(MatMut::new(out_i, co, hwo, hwo, 1), wm, MatRef::new(&x[i * ci * hwo..], ci, hwo, hwo, 1), 1.0, true, true);
            }
            return Ok((CpuStorage::F32(out), Shape::from_dims(&[n, co, ho, wo])));
        }
        let g = Geometry { ci, h, w, k, stride: s, pad: p, wo };
        let band = (col_budget / (kk * wo)).clamp(1, ho);
        let group = if band == ho { (col_budget / (kk * hwo)).clamp(1, n) } else { 1 };
        if group > 1 {
            // several whole images side by side in one product, then moved into NCHW
            for i0 in (0..n).step_by(group) {
                let images = group.min(n - i0);
                let cols = images * hwo;
                let mut col = Scratch::take(kk * cols);
                im2col(x, g, i0, images, 0, ho, col.as_mut_slice());
                let mut prod = Scratch::take(co * cols);
                gemm(MatMut::new(prod.as_mut_slice(), co, cols, cols, 1), wm, MatRef::new(col.as_mut_slice(), kk, cols, cols, 1), 1.0, false, true);
                let prod = &*prod.as_mut_slice();
                out[i0 * co * hwo..(i0 + images) * co * hwo].par_chunks_mut(hwo).enumerate().for_each(|(jo, plane)| {
                    let (j, o) = (jo / co, jo % co);
                    plane.iter_mut().zip(&prod[o * cols + j * hwo..][..hwo]).for_each(|(d, v)| *d += v);
                });
            }
        } else {
            // one image at a time, in bands of output rows, straight into the output
            for i in 0..n {
                for r0 in (0..ho).step_by(band) {
                    let rows = band.min(ho - r0);
                    let mut col = Scratch::take(kk * rows * wo);
                    im2col(x, g, i, 1, r0, rows, col.as_mut_slice());
                    let dst = MatMut::new(&mut out[i * co * hwo + r0 * wo..], co, rows * wo, hwo, 1);
                    gemm(dst, wm, MatRef::new(col.as_mut_slice(), kk, rows * wo, rows * wo, 1), 1.0, true, true);
                }
            }
        }
        Ok((CpuStorage::F32(out), Shape::from_dims(&[n, co, ho, wo])))
    }
}

impl CustomOp2 for ConvKernel<'_> {
    fn name(&self) -> &'static str {
        "idarb-conv2d"
    }

    fn cpu_fwd(&self, xs: &CpuStorage, xl: &Layout, ws: &CpuStorage, wl: &Layout) -> Result<(CpuStorage, Shape)> {
        self.run(contiguous_slice::<f32>("conv2d", xs, xl)?, xl, contiguous_slice::<f32>("conv2d", ws, wl)?, wl, None)
    }
}

impl CustomOp3 for ConvKernel<'_> {
    fn name(&self) -> &'static str {
        "idarb-conv2d"
    }

    fn cpu_fwd(&self, xs: &CpuStorage, xl: &Layout, ws: &CpuStorage, wl: &Layout, es: &CpuStorage, el: &Layout) -> Result<(CpuStorage, Shape)> {
        self.run(contiguous_slice::<f32>("conv2d", xs, xl)?, xl, contiguous_slice::<f32>("conv2d", ws, wl)?, wl, Some((contiguous_slice::<f32>("conv2d", es, el)?, el)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    /// Direct loop: zero padding `p`, stride `s`, square kernel.
    fn direct(x: &[f32], wt: &[f32], b: &[f32], (n, ci, h, w): (usize, usize, usize, usize), co: usize, (k, s, p): (usize, usize, usize)) -> Vec<f32> {
        let (ho, wo) = ((h + 2 * p - k) / s + 1, (w + 2 * p - k) / s + 1);
        let mut out = vec![0f32; n * co * ho * wo];
        for i in 0..n {
            for o in 0..co {
                for y in 0..ho {
                    for xx in 0..wo {
                        let mut acc = b[o];
                        for c in 0..ci {
                            for ky in 0..k {
                                for kx in 0..k {
                                    let (sy, sx) = ((y * s + ky) as i64 - p as i64, (xx * s + kx) as i64 - p as i64);
                                    if sy >= 0 && sx >= 0 && (sy as usize) < h && (sx as usize) < w {
                                        acc += wt[((o * ci + c) * k + ky) * k + kx] * x[((i * ci + c) * h + sy as usize) * w + sx as usize];
                                    }
                                }
                            }
                        }
                        out[((i * co + o) * ho + y) * wo + xx] = acc;
                    }
                }
            }
        }
        out
    }

    /// Every path (1×1, grouped images, whole images, bands of rows; stride 1 and 2; C = H = W,
    /// which candle 0.9 got wrong) against the direct loop.
    #[test]
    fn matches_direct_convolution() -> Result<()> {
        let dev = Device::Cpu;
        let cases = [
            // (n, ci, co, h, w, k, s, p)
            (2usize, 16usize, 24usize, 16usize, 16usize, 3usize, 1usize, 1usize),
            (3, 8, 8, 8, 8, 3, 1, 1),
            (2, 5, 3, 7, 6, 3, 2, 1),
            (1, 3, 4, 6, 5, 3, 2, 0),
            (3, 6, 5, 5, 7, 1, 1, 0),
        ];
        for (n, ci, co, h, w, k, s, p) in cases {
            let x = Tensor::randn(0f32, 1.0, (n, ci, h, w), &dev)?;
            let wt = Tensor::randn(0f32, 1.0, (co, ci, k, k), &dev)?;
            let b = Tensor::randn(0f32, 1.0, co, &dev)?;
            let want = direct(&x.flatten_all()?.to_vec1()?, &wt.flatten_all()?.to_vec1()?, &b.to_vec1()?, (n, ci, h, w), co, (k, s, p));
            // budgets: one tap row, one image, all images
            let wo = (w + 2 * p - k) / s + 1;
            let ho = (h + 2 * p - k) / s + 1;
            let bias = b.to_vec1::<f32>()?;
            for col_budget in [1, ci * k * k * wo * ho, usize::MAX / 8] {
                let op = ConvKernel { shape: ConvShape { kernel: k, stride: s, padding: p, col_budget }, bias: &bias };
                let got = x.apply_op2_no_bwd(&wt, &op)?.flatten_all()?.to_vec1::<f32>()?;
                for (idx, (g, e)) in got.iter().zip(&want).enumerate() {
                    assert!((g - e).abs() < 1e-4, "case {:?} budget {col_budget} at {idx}: {g} vs {e}", (n, ci, co, h, w, k, s, p));
                }
            }
        }
        Ok(())
    }

    /// The added term: a per-image bias broadcasts over pixels, a residual adds elementwise.
    #[test]
    fn adds_per_image_bias_or_residual() -> Result<()> {
        let dev = Device::Cpu;
        let (n, ci, co, hw) = (2usize, 3usize, 4usize, 5usize);
        let x = Tensor::randn(0f32, 1.0, (n, ci, hw, hw), &dev)?;
        let wt = Tensor::randn(0f32, 1.0, (co, ci, 3, 3), &dev)?;
        let bias = vec![0.5f32, -1.0, 2.0, 0.0];
        let conv = Conv2d { weight: wt, bias, shape: ConvShape { kernel: 3, stride: 1, padding: 1, col_budget: COL_BUDGET_BYTES / 4 } };
        let plain = conv.forward(&x)?;
        let per_image = Tensor::randn(0f32, 1.0, (n, co), &dev)?;
        let residual = Tensor::randn(0f32, 1.0, (n, co, hw, hw), &dev)?;
        for (extra, want) in [(&per_image, plain.broadcast_add(&per_image.reshape((n, co, 1, 1))?)?), (&residual, (&plain + &residual)?)] {
            let d = (conv.forward_plus(&x, extra)? - want)?.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?;
            assert!(d < 1e-5, "added term off by {d}");
        }
        Ok(())
    }
}

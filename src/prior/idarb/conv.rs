//! 2-D convolution (inference only) as matrix products: out[Co, pixels] = W[Co, Ci·k·k] ·
//! col[Ci·k·k, pixels], the im2col matrix built in a reused per-thread buffer of bounded size
//! (several small images per product, or one large image in bands of output rows); a 1×1
//! convolution multiplies the input itself. candle-core 0.9's conv2d spent as long in its im2col
//! as in the product, faulted in a fresh buffer each call, and got C = H = W inputs wrong.
use super::cpu_kernel::contiguous_f32;
use super::matmul::{gemm, MatMut, MatRef};
use super::scratch::Scratch;
use candle_core::{bail, CpuStorage, CustomOp3, Layout, Module, Result, Shape, Tensor};
use candle_nn::{Conv2dConfig, VarBuilder};
use rayon::prelude::*;

/// Largest im2col buffer, in bytes.
const COL_BUDGET_BYTES: usize = 64 << 20;

#[derive(Debug, Clone)]
pub struct Conv2d {
    /// [Co, Ci, k, k], contiguous.
    weight: Tensor,
    /// [Co].
    bias: Tensor,
    kernel: ConvKernel,
}

/// Weights `weight` [Co, Ci, k, k] and `bias` [Co] under `vb`, initialised as candle-nn's conv2d
/// when they are created (random-weight benchmarks).
pub fn conv2d(in_channels: usize, out_channels: usize, kernel: usize, cfg: Conv2dConfig, vb: VarBuilder) -> Result<Conv2d> {
    if cfg.groups != 1 || cfg.dilation != 1 {
        bail!("conv2d: only groups = 1 and dilation = 1 are supported");
    }
    let conv = candle_nn::conv2d(in_channels, out_channels, kernel, cfg, vb)?;
    let bias = conv.bias().cloned().ok_or_else(|| candle_core::Error::Msg("conv2d: no bias".into()))?;
    Ok(Conv2d {
        weight: conv.weight().contiguous()?,
        bias,
        kernel: ConvKernel { kernel, stride: cfg.stride, padding: cfg.padding, col_budget: COL_BUDGET_BYTES / 4 },
    })
}

impl Module for Conv2d {
    /// `x`: [N, Ci, H, W] f32 → [N, Co, H', W'].
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        x.contiguous()?.apply_op3_no_bwd(&self.weight, &self.bias, &self.kernel)
    }
}

#[derive(Debug, Clone, Copy)]
struct ConvKernel {
    kernel: usize,
    stride: usize,
    padding: usize,
    /// Largest im2col buffer, in elements.
    col_budget: usize,
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

impl CustomOp3 for ConvKernel {
    fn name(&self) -> &'static str {
        "idarb-conv2d"
    }

    fn cpu_fwd(&self, xs: &CpuStorage, xl: &Layout, ws: &CpuStorage, wl: &Layout, bs: &CpuStorage, bl: &Layout) -> Result<(CpuStorage, Shape)> {
        let (x, wt, bias) = (contiguous_f32(xs, xl, self.name())?, contiguous_f32(ws, wl, self.name())?, contiguous_f32(bs, bl, self.name())?);
        let (n, ci, h, w) = xl.shape().dims4()?;
        let (co, wci, kh, kw) = wl.shape().dims4()?;
        let (k, s, p) = (self.kernel, self.stride, self.padding);
        if wci != ci || kh != k || kw != k || bias.len() != co || s == 0 || h + 2 * p < k || w + 2 * p < k {
            bail!("conv2d: input {:?}, weight {:?}, bias {:?}, stride {s}, padding {p}", xl.shape(), wl.shape(), bl.shape());
        }
        let (ho, wo) = ((h + 2 * p - k) / s + 1, (w + 2 * p - k) / s + 1);
        let (hwo, kk) = (ho * wo, ci * k * k);
        let mut out = vec![0f32; n * co * hwo];
        // the bias first: every product below accumulates onto it
        out.par_chunks_mut(hwo.max(1)).enumerate().for_each(|(i, plane)| plane.fill(bias[i % co]));
        let wm = MatRef::new(wt, co, kk, kk, 1);
        if k == 1 && s == 1 && p == 0 {
            for (i, out_i) in out.chunks_mut(co * hwo).enumerate() {
                gemm(MatMut::new(out_i, co, hwo, hwo, 1), wm, MatRef::new(&x[i * ci * hwo..], ci, hwo, hwo, 1), 1.0, true, true);
            }
            return Ok((CpuStorage::F32(out), Shape::from_dims(&[n, co, ho, wo])));
        }
        let g = Geometry { ci, h, w, k, stride: s, pad: p, wo };
        let band = (self.col_budget / (kk * wo)).clamp(1, ho);
        let group = if band == ho { (self.col_budget / (kk * hwo)).clamp(1, n) } else { 1 };
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

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    /// Direct loop: zero padding `p`, stride `s`, square kernel.
    fn direct(x: &[f32], wt: &[f32], b: &[f32], (n, ci, h, w): (usize, usize, usize, usize), co: usize, k: usize, s: usize, p: usize) -> Vec<f32> {
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
            let want = direct(&x.flatten_all()?.to_vec1()?, &wt.flatten_all()?.to_vec1()?, &b.to_vec1()?, (n, ci, h, w), co, k, s, p);
            // budgets: one tap row, one image, all images
            let wo = (w + 2 * p - k) / s + 1;
            let ho = (h + 2 * p - k) / s + 1;
            for col_budget in [1, ci * k * k * wo * ho, usize::MAX / 8] {
                let op = ConvKernel { kernel: k, stride: s, padding: p, col_budget };
                let got = x.apply_op3_no_bwd(&wt, &b, &op)?.flatten_all()?.to_vec1::<f32>()?;
                for (idx, (g, e)) in got.iter().zip(&want).enumerate() {
                    assert!((g - e).abs() < 1e-4, "case {:?} budget {col_budget} at {idx}: {g} vs {e}", (n, ci, co, h, w, k, s, p));
                }
            }
        }
        Ok(())
    }
}

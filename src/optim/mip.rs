//! Mip-mapped (trilinear) texture lookups, differentiable w.r.t. the base texture.
//!
//! Plain bilinear lookups of a texture finer than the screen alias, and their gradients land on a
//! few texels only. As in NVDiffRec (nvdiffrast's 'linear-mipmap-linear'), a lookup blends two
//! levels of a box-filtered pyramid, chosen by its level of detail (log2 of the pixel footprint in
//! texels). Two operators:
//! - [`build_pyramid`]: [H, W, C] → [Σ texels of all levels, C], level 0 first, each next level the
//!   2×2 average of the previous while both sides are even. Adjoint: from the coarsest level down,
//!   acc_k = g_k + ¼·upsample(acc_{k+1}) (a gather, race-free).
//! - [`sample_trilinear`]: pyramid → [N, C] at (uv, lod), each level looked up like
//!   `texture::bilinear_taps` (wrap addressing, OBJ v convention); adjoint: banded scatter with the
//!   same taps and level weights.

use std::sync::Arc;

use candle_core::{Result, Tensor};
use rayon::prelude::*;

use super::tape::{apply, scatter_add_banded, Kernel, Real};
use super::texture::bilinear_taps;

/// Sizes and offsets (in texels) of the levels of a pyramid over an h×w base.
#[derive(Clone, Debug, PartialEq)]
pub struct MipLevels {
    /// (height, width, texel offset) per level, level 0 = the base.
    pub levels: Vec<(usize, usize, usize)>,
    pub total_texels: usize,
}

impl MipLevels {
    pub fn new(h: usize, w: usize) -> Self {
        let mut levels = vec![(h, w, 0)];
        let mut total = h * w;
        let (mut h, mut w) = (h, w);
        while h % 2 == 0 && w % 2 == 0 && h >= 2 && w >= 2 {
            h /= 2;
            w /= 2;
            levels.push((h, w, total));
            total += h * w;
        }
        MipLevels { levels, total_texels: total }
    }
}

struct BuildPyramid {
    levels: MipLevels,
}

impl Kernel for BuildPyramid {
    fn name(&self) -> &'static str {
        "mip_pyramid"
    }

    fn output_shape(&self, shapes: &[&[usize]]) -> Result<Vec<usize>> {
        match shapes {
            [[h, w, c]] if (*h, *w) == (self.levels.levels[0].0, self.levels.levels[0].1) => {
                Ok(vec![self.levels.total_texels, *c])
            }
            _ => Err(candle_core::Error::Msg(format!("mip pyramid: expected a texture [H, W, C], got {shapes:?}"))),
        }
    }

    fn forward<T: Real>(&self, x: &[&[T]], shapes: &[&[usize]], out: &mut [T]) -> Result<()> {
        let c = shapes[0][2];
        out[..x[0].len()].copy_from_slice(x[0]);
        let quarter = T::from_f64(0.25);
        for k in 1..self.levels.levels.len() {
            let (h, w, off) = self.levels.levels[k];
            let (_, pw, poff) = self.levels.levels[k - 1];
            let (prev, cur) = out.split_at_mut(off * c);
            let prev = &prev[poff * c..];
            cur[..h * w * c].par_chunks_mut(w * c).enumerate().for_each(|(y, row)| {
                for x in 0..w {
                    for ch in 0..c {
                        let at = |yy: usize, xx: usize| prev[((2 * y + yy) * pw + 2 * x + xx) * c + ch];
                        row[x * c + ch] = quarter * (at(0, 0) + at(0, 1) + at(1, 0) + at(1, 1));
                    }
                }
            });
        }
        Ok(())
    }

    fn backward<T: Real>(&self, _x: &[&[T]], shapes: &[&[usize]], g: &[T], grads: &mut [Option<&mut [T]>]) -> Result<()> {
        let Some(gx) = grads[0].as_deref_mut() else { return Ok(()) };
        let c = shapes[0][2];
        let quarter = T::from_f64(0.25);
        // acc holds the accumulated adjoint of the level below the one being filled.
        let levels = &self.levels.levels;
        let (lh, lw, loff) = levels[levels.len() - 1];
        let mut acc: Vec<T> = g[loff * c..(loff + lh * lw) * c].to_vec();
        for k in (0..levels.len() - 1).rev() {
            let (h, w, off) = levels[k];
            let cw = levels[k + 1].1;
            let mut next = g[off * c..(off + h * w) * c].to_vec();
            next.par_chunks_mut(w * c).enumerate().for_each(|(y, row)| {
                for x in 0..w {
                    for ch in 0..c {
                        row[x * c + ch] += quarter * acc[((y / 2) * cw + x / 2) * c + ch];
                    }
                }
            });
            acc = next;
        }
        gx.iter_mut().zip(acc).for_each(|(o, a)| *o += a);
        Ok(())
    }
}

/// The pyramid of `texture` [H, W, C] as one tensor [Σ texels, C] (levels as in [`MipLevels`]).
pub fn build_pyramid(texture: &Tensor) -> Result<(Tensor, MipLevels)> {
    let (h, w, _) = texture.dims3()?;
    let levels = MipLevels::new(h, w);
    let p = apply(BuildPyramid { levels: levels.clone() }, &[texture])?;
    Ok((p, levels))
}

/// Trilinear lookups at fixed (uv, lod).
#[derive(Clone)]
pub struct Trilinear {
    pub levels: MipLevels,
    pub uv: Arc<[[f32; 2]]>,
    pub lod: Arc<[f32]>,
}

impl Trilinear {
    /// The (level, weight) pair(s) of a lookup: lod clamped to [0, last level].
    #[inline]
    fn level_weights(&self, lod: f32) -> [(usize, f64); 2] {
        let last = (self.levels.levels.len() - 1) as f64;
        let l = (lod as f64).clamp(0.0, last);
        let l0 = l.floor();
        let t = l - l0;
        let l0 = l0 as usize;
        [(l0, 1.0 - t), ((l0 + 1).min(last as usize), t)]
    }

    /// Calls `f(texel index in the pyramid, weight)` for the 8 taps of lookup `n`.
    #[inline]
    fn for_each_tap(&self, n: usize, mut f: impl FnMut(usize, f64)) {
        for (level, lw) in self.level_weights(self.lod[n]) {
            if lw == 0.0 {
                continue;
            }
            let (h, w, off) = self.levels.levels[level];
            for (texel, bw) in bilinear_taps(self.uv[n], w, h) {
                f(off + texel, lw * bw);
            }
        }
    }
}

impl Kernel for Trilinear {
    fn name(&self) -> &'static str {
        "trilinear_wrap"
    }

    fn output_shape(&self, shapes: &[&[usize]]) -> Result<Vec<usize>> {
        match shapes {
            [[t, c]] if *t == self.levels.total_texels && self.uv.len() == self.lod.len() => Ok(vec![self.uv.len(), *c]),
            _ => Err(candle_core::Error::Msg(format!(
                "trilinear lookup: expected a pyramid [{}, C] and as many lods as uvs ({} vs {}), got {shapes:?}",
                self.levels.total_texels,
                self.lod.len(),
                self.uv.len()
            ))),
        }
    }

    fn forward<T: Real>(&self, x: &[&[T]], shapes: &[&[usize]], out: &mut [T]) -> Result<()> {
        let (p, c) = (x[0], shapes[0][1]);
        out.par_chunks_mut(c).enumerate().for_each(|(n, o)| {
            self.for_each_tap(n, |texel, wt| {
                let wt = T::from_f64(wt);
                for k in 0..c {
                    o[k] += wt * p[texel * c + k];
                }
            });
        });
        Ok(())
    }

    fn backward<T: Real>(&self, _x: &[&[T]], shapes: &[&[usize]], g: &[T], grads: &mut [Option<&mut [T]>]) -> Result<()> {
        let Some(gp) = grads[0].as_deref_mut() else { return Ok(()) };
        let c = shapes[0][1];
        scatter_add_banded(gp, self.uv.len(), |n, sink| {
            self.for_each_tap(n, |texel, wt| {
                let wt = T::from_f64(wt);
                for k in 0..c {
                    sink.add(texel * c + k, wt * g[n * c + k]);
                }
            });
        });
        Ok(())
    }
}

/// Looks the pyramid up at `uv` with level of detail `lod` (0 = base; fractional blends two levels).
pub fn sample_trilinear(pyramid: &Tensor, levels: &MipLevels, uv: &Arc<[[f32; 2]]>, lod: &Arc<[f32]>) -> Result<Tensor> {
    if let Some(i) = uv.iter().position(|p| !(p[0].is_finite() && p[1].is_finite())) {
        return Err(candle_core::Error::Msg(format!("trilinear lookup: uv #{i} is not finite ({:?})", uv[i])));
    }
    if let Some(i) = lod.iter().position(|l| l.is_nan()) {
        return Err(candle_core::Error::Msg(format!("trilinear lookup: lod #{i} is NaN")));
    }
    apply(Trilinear { levels: levels.clone(), uv: uv.clone(), lod: lod.clone() }, &[pyramid])
}

/// Level of detail for a pixel whose footprint spans `texels_per_pixel` texels of the base level.
pub fn lod_from_footprint(texels_per_pixel: f32) -> f32 {
    texels_per_pixel.max(1.0).log2()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optim::gradcheck::check_gradient;
    use crate::optim::texture::sample_bilinear;
    use crate::rng::Sampler;
    use candle_core::Device;

    #[test]
    fn level_sizes_stop_at_odd_sides() {
        let m = MipLevels::new(8, 12);
        assert_eq!(m.levels, vec![(8, 12, 0), (4, 6, 96), (2, 3, 120)]);
        assert_eq!(m.total_texels, 126);
        assert_eq!(MipLevels::new(1, 1).levels.len(), 1);
    }

    #[test]
    fn pyramid_averages_and_lod_zero_is_bilinear() -> anyhow::Result<()> {
        let dev = Device::Cpu;
        let tex = Tensor::rand(0f32, 1.0, (8, 8, 3), &dev)?;
        let (p, levels) = build_pyramid(&tex)?;
        assert_eq!(levels.levels.len(), 4);
        // The 1×1 top level is the mean of the texture.
        let top = p.narrow(0, levels.levels[3].2, 1)?.flatten_all()?.to_vec1::<f32>()?;
        let mean = tex.mean_keepdim(0)?.mean_keepdim(1)?.flatten_all()?.to_vec1::<f32>()?;
        for k in 0..3 {
            assert!((top[k] - mean[k]).abs() < 1e-5);
        }
        let mut s = Sampler::from_seed(2);
        let uv: Arc<[[f32; 2]]> = (0..50).map(|_| [s.next_f32() * 3.0 - 1.0, s.next_f32()]).collect::<Vec<_>>().into();
        let zero: Arc<[f32]> = vec![0.0f32; 50].into();
        let a = sample_trilinear(&p, &levels, &uv, &zero)?;
        let b = sample_bilinear(&tex, &uv)?;
        assert!((a - b)?.abs()?.max_all()?.to_scalar::<f32>()? < 1e-5);
        // Past the last level, lookups return the mean.
        let far: Arc<[f32]> = vec![40.0f32; 50].into();
        let c = sample_trilinear(&p, &levels, &uv, &far)?.to_vec2::<f32>()?;
        assert!(c.iter().all(|r| (0..3).all(|k| (r[k] - mean[k]).abs() < 1e-5)));
        Ok(())
    }

    #[test]
    fn pyramid_gradient_matches_finite_differences() -> anyhow::Result<()> {
        let tex = Tensor::rand(0f64, 1.0, (8, 4, 2), &Device::Cpu)?;
        check_gradient(|x| Ok(build_pyramid(&x[0])?.0), &[tex], 1e-6, 1e-2)?;
        Ok(())
    }

    #[test]
    fn trilinear_gradient_matches_finite_differences_at_integer_and_fractional_lods() -> anyhow::Result<()> {
        let tex = Tensor::rand(0f64, 1.0, (8, 8, 3), &Device::Cpu)?;
        let mut s = Sampler::from_seed(4);
        let uv: Arc<[[f32; 2]]> = (0..80).map(|_| [s.next_f32() * 2.0, s.next_f32()]).collect::<Vec<_>>().into();
        // Exact levels, fractions, below 0 and beyond the top.
        let lod: Arc<[f32]> = (0..80).map(|i| [0.0, 1.0, 2.0, 3.0, 0.3, 1.7, -2.0, 9.0][i % 8]).collect::<Vec<_>>().into();
        let levels = MipLevels::new(8, 8);
        check_gradient(|x| sample_trilinear(&build_pyramid(&x[0])?.0, &levels, &uv, &lod), &[tex], 1e-6, 1e-2)?;
        Ok(())
    }

    #[test]
    fn footprint_to_lod() {
        assert_eq!(lod_from_footprint(0.3), 0.0);
        assert_eq!(lod_from_footprint(4.0), 2.0);
    }
}

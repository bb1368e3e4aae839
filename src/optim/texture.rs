//! Differentiable bilinear texture lookup with wrap addressing, and its adjoint.
//!
//! Texture: a tensor [H, W, C], row 0 at the top (like `Image`). UV: OBJ convention, v = 0 is the
//! bottom row; texel centres sit at ((i + ½)/W, 1 − (j + ½)/H); both axes repeat (wrap), so the
//! four taps of a lookup near an edge come from the opposite edge too. UVs are fixed data (from the
//! G-buffer) and get no gradient. The forward gathers the four taps of [`bilinear_taps`]; the
//! adjoint scatters with the very same taps and weights (race-free, see `scatter_add_banded`).

use std::sync::Arc;

use candle_core::{Result, Tensor};
use rayon::prelude::*;

use super::tape::{apply, scatter_add_banded, Kernel, Real};
use crate::math::floor_f64;
use crate::rng::Sampler;

/// The four (flat texel index, weight) taps of a wrapped bilinear lookup at `uv` in a w×h texture.
#[inline]
pub fn bilinear_taps(uv: [f32; 2], w: usize, h: usize) -> [(usize, f64); 4] {
    let x = uv[0] as f64 * w as f64 - 0.5;
    let y = (1.0 - uv[1] as f64) * h as f64 - 0.5;
    let (x0, tx) = wrapped_floor(x, w);
    let (y0, ty) = wrapped_floor(y, h);
    let x1 = if x0 + 1 == w { 0 } else { x0 + 1 };
    let y1 = if y0 + 1 == h { 0 } else { y0 + 1 };
    [
        (y0 * w + x0, (1.0 - tx) * (1.0 - ty)),
        (y0 * w + x1, tx * (1.0 - ty)),
        (y1 * w + x0, (1.0 - tx) * ty),
        (y1 * w + x1, tx * ty),
    ]
}

/// ⌊x⌋ wrapped into 0..n, and x − ⌊x⌋: the texel left of (or below) a texture coordinate and the
/// weight of the next one. `floor` then `rem_euclid`, with the floor that needs no libm call
/// ([`floor_f64`]) and no integer division for coordinates within one wrap of the texture, which is
/// where lookups land. libm's `floor` alone took 1.55 % of the 4-spp step's samples beside the taps'
/// own 3.89 % (`perf` of `bench_step`, 2026-12-08).
#[inline]
fn wrapped_floor(x: f64, n: usize) -> (usize, f64) {
    let f = floor_f64(x);
    let (i, n) = (f as i64, n as i64);
    let wrapped = if (0..n).contains(&i) {
        i
    } else if (-n..0).contains(&i) {
        i + n
    } else {
        i.rem_euclid(n)
    };
    (wrapped as usize, x - f)
}

/// The lookup operator for one fixed set of UVs.
#[derive(Clone)]
pub struct BilinearWrap {
    pub uv: Arc<[[f32; 2]]>,
}

impl BilinearWrap {
    /// Fails (naming the first bad entry) when a UV is NaN or infinite.
    pub fn new(uv: Arc<[[f32; 2]]>) -> Result<Self> {
        if let Some(i) = uv.iter().position(|p| !(p[0].is_finite() && p[1].is_finite())) {
            return Err(candle_core::Error::Msg(format!(
                "texture lookup: uv #{i} is not finite ({:?})",
                uv[i]
            )));
        }
        Ok(BilinearWrap { uv })
    }
}

impl Kernel for BilinearWrap {
    fn name(&self) -> &'static str {
        "bilinear_wrap"
    }

    fn output_shape(&self, shapes: &[&[usize]]) -> Result<Vec<usize>> {
        match shapes {
            [[h, w, c]] if *h > 0 && *w > 0 && *c > 0 => Ok(vec![self.uv.len(), *c]),
            _ => Err(candle_core::Error::Msg(format!(
                "texture lookup: expected one non-empty texture [H, W, C], got shapes {shapes:?}"
            ))),
        }
    }

    fn forward<T: Real>(&self, x: &[&[T]], shapes: &[&[usize]], out: &mut [T]) -> Result<()> {
        let (tex, (w, h, c)) = (x[0], (shapes[0][1], shapes[0][0], shapes[0][2]));
        out.par_chunks_mut(c).zip(self.uv.par_iter()).for_each(|(o, &uv)| {
            for (texel, wt) in bilinear_taps(uv, w, h) {
                let wt = T::from_f64(wt);
                for k in 0..c {
                    o[k] += wt * tex[texel * c + k];
                }
            }
        });
        Ok(())
    }

    fn backward<T: Real>(&self, _x: &[&[T]], shapes: &[&[usize]], g: &[T], grads: &mut [Option<&mut [T]>]) -> Result<()> {
        let Some(gt) = grads[0].as_deref_mut() else { return Ok(()) };
        let (w, h, c) = (shapes[0][1], shapes[0][0], shapes[0][2]);
        scatter_add_banded(gt, self.uv.len(), |n, sink| {
            for (texel, wt) in bilinear_taps(self.uv[n], w, h) {
                let wt = T::from_f64(wt);
                for k in 0..c {
                    sink.add(texel * c + k, wt * g[n * c + k]);
                }
            }
        });
        Ok(())
    }
}

/// Looks `texture` [H, W, C] up at `uv` → [N, C], on the tape (gradient flows to the texture).
pub fn sample_bilinear(texture: &Tensor, uv: &Arc<[[f32; 2]]>) -> Result<Tensor> {
    apply(BilinearWrap::new(uv.clone())?, &[texture])
}

/// `uv` displaced by independent Gaussian offsets of standard deviation `sigma` (UV units), from a
/// seeded stream: the jittered lookups of the material smoothness regulariser (NVDiffRecMC uses
/// σ = 0.005).
pub fn jitter_uv(uv: &[[f32; 2]], sigma: f32, seed: u64) -> Arc<[[f32; 2]]> {
    uv.par_iter()
        .enumerate()
        .map(|(i, p)| {
            let mut s = Sampler::new(seed, i as u64);
            let (u1, u2) = s.next_2d();
            // Box–Muller; 1 − u1 ∈ (0, 1] keeps the log finite.
            let r = (-2.0 * (1.0 - u1).ln()).sqrt() * sigma;
            let a = std::f32::consts::TAU * u2;
            [p[0] + r * a.cos(), p[1] + r * a.sin()]
        })
        .collect::<Vec<_>>()
        .into()
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{DType, Device};

    fn texture(h: usize, w: usize, c: usize) -> Result<Tensor> {
        let data: Vec<f32> = (0..h * w * c).map(|i| ((i * 37) % 11) as f32 * 0.1).collect();
        Tensor::from_vec(data, (h, w, c), &Device::Cpu)
    }

    #[test]
    fn the_wrapped_floor_is_floor_then_rem_euclid_bit_for_bit() {
        let reference = |x: f64, n: usize| {
            let f = x.floor();
            ((f as i64).rem_euclid(n as i64) as usize, x - f)
        };
        let mut rng = Sampler::new(7, 0);
        let mut xs: Vec<f64> = vec![0.0, 0.5, -0.5, 1.0, -1.0, 511.5, 512.0, -512.0, -512.5, 1023.99, 1e9 + 0.25, -1e9 - 0.25, 4.6e15, -4.6e15, 1e300, -1e300];
        xs.extend([f64::from_bits(1), -f64::from_bits(1), 1.0 - f64::EPSILON, -(1.0 - f64::EPSILON)]);
        // UVs as the lookups make them: around [0, 1] and a few periods out.
        xs.extend((0..20_000).map(|_| (rng.next_f32() as f64 * 6.0 - 3.0) * 512.0 - 0.5));
        for n in [1, 2, 3, 5, 512] {
            for &x in &xs {
                let (got, want) = (wrapped_floor(x, n), reference(x, n));
                assert!(got.0 == want.0 && got.1.to_bits() == want.1.to_bits(), "x = {x:e}, n = {n}: {got:?} against {want:?}");
            }
        }
    }

    #[test]
    fn texel_centres_return_the_texel_and_the_seam_averages_both_edges() -> Result<()> {
        let (h, w) = (4, 5);
        let tex = texture(h, w, 2)?;
        let vals = tex.to_vec3::<f32>()?;
        // Centre of texel (row j, column i).
        let (i, j) = (3usize, 1usize);
        let centre = [(i as f32 + 0.5) / w as f32, 1.0 - (j as f32 + 0.5) / h as f32];
        // u = 0 lies half-way between the last and the first column (wrap), on row j's centre.
        let seam = [0.0, centre[1]];
        let uv: Arc<[[f32; 2]]> = vec![centre, seam, [centre[0] + 3.0, centre[1] - 2.0]].into();
        let out = sample_bilinear(&tex, &uv)?.to_vec2::<f32>()?;
        for k in 0..2 {
            assert!((out[0][k] - vals[j][i][k]).abs() < 1e-5);
            let expect = 0.5 * (vals[j][0][k] + vals[j][w - 1][k]);
            assert!((out[1][k] - expect).abs() < 1e-5, "{} vs {}", out[1][k], expect);
            // Integer UV shifts wrap to the same place.
            assert!((out[2][k] - vals[j][i][k]).abs() < 1e-4);
        }
        Ok(())
    }

    #[test]
    fn weights_sum_to_one_everywhere() {
        let mut s = Sampler::from_seed(3);
        for _ in 0..1000 {
            let uv = [s.next_f32() * 4.0 - 2.0, s.next_f32() * 4.0 - 2.0];
            let taps = bilinear_taps(uv, 7, 3);
            let sum: f64 = taps.iter().map(|t| t.1).sum();
            assert!((sum - 1.0).abs() < 1e-12);
            assert!(taps.iter().all(|t| t.0 < 21 && t.1 >= 0.0));
        }
    }

    #[test]
    fn f32_and_f64_agree() -> Result<()> {
        let tex = texture(6, 6, 3)?;
        let uv = jitter_uv(&[[0.3, 0.7], [0.0, 1.0], [0.99, 0.01]], 0.2, 5);
        let a = sample_bilinear(&tex, &uv)?;
        let b = sample_bilinear(&tex.to_dtype(DType::F64)?, &uv)?.to_dtype(DType::F32)?;
        let d = (a - b)?.abs()?.max_all()?.to_scalar::<f32>()?;
        assert!(d < 1e-5);
        Ok(())
    }

    #[test]
    fn non_finite_uv_is_a_clear_error() {
        let uv: Arc<[[f32; 2]]> = vec![[0.1, f32::NAN]].into();
        let err = sample_bilinear(&texture(2, 2, 1).expect("test setup"), &uv).unwrap_err().to_string();
        assert!(err.contains("uv #0"), "{err}");
    }
}

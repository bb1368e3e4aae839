//! A low-frequency light for the geometry pass: irradiance as 9 real spherical-harmonic
//! coefficients per colour channel (bands 0–2), and Lambertian shading under it, on the tape.
//!
//! Ramamoorthi and Hanrahan (2001) showed that the irradiance a Lambertian surface receives is
//! captured by the first three SH bands to within a few percent for any environment. The geometry
//! pass needs exactly that much light: enough that shading tells the normal's direction, cheap
//! enough to evaluate and differentiate per pixel, and with no visibility, which a moving mesh
//! could not afford per step. The material pass that follows uses the full cube-map light and BRDF.
//!
//! E(n) = Σₖ cₖ·Yₖ(n), with Yₖ the real SH basis (normalised, Y₀₀ = 0.282095); colour = kd·E(n).
//! One kernel per pixel row, forward and adjoint side by side:
//!   ∂colour_c/∂kd_c = E_c(n),   ∂L/∂c_kc = Σ_p Yₖ(n_p)·kd_pc·ḡ_pc,
//!   ∂L/∂n = Σₖ wₖ·∇Yₖ(n) with wₖ = Σ_c ḡ_c·kd_c·c_kc
//! (ḡ the incoming gradient). The light's adjoint sums over pixels in fixed chunks, then the chunks
//! in order, so it does not depend on the thread count.

use candle_core::{Result, Tensor};
use rayon::prelude::*;

use crate::optim::tape::{apply, Kernel, Real};

/// Coefficients per channel: bands 0, 1 and 2.
pub const SH_COEFFICIENTS: usize = 9;
/// Y₀₀: the constant basis function, 1/(2√π).
const Y00: f64 = 0.282_094_791_773_878_1;
/// Band-1 factor √(3/4π).
const Y1: f64 = 0.488_602_511_902_919_9;
/// Band-2 factors √(15/4π), √(5/16π), √(15/16π).
const Y2_XY: f64 = 1.092_548_430_592_079_2;
const Y2_ZZ: f64 = 0.315_391_565_252_52;
const Y2_XX_YY: f64 = 0.546_274_215_296_039_6;

/// Rows per partial sum of the light's adjoint: a fixed chunking keeps the sum's order, and so
/// its rounding, the same on any number of threads.
const LIGHT_SUM_ROWS: usize = 1024;

/// The basis at direction (x, y, z) (a unit vector; not renormalised here).
pub fn sh_basis([x, y, z]: [f64; 3]) -> [f64; SH_COEFFICIENTS] {
    [Y00, Y1 * y, Y1 * z, Y1 * x, Y2_XY * x * y, Y2_XY * y * z, Y2_ZZ * (3.0 * z * z - 1.0), Y2_XY * x * z, Y2_XX_YY * (x * x - y * y)]
}

/// Σₖ wₖ·∇Yₖ at (x, y, z): the adjoint of [`sh_basis`].
fn sh_basis_adjoint([x, y, z]: [f64; 3], w: &[f64; SH_COEFFICIENTS]) -> [f64; 3] {
    [
        Y1 * w[3] + Y2_XY * (y * w[4] + z * w[7]) + 2.0 * Y2_XX_YY * x * w[8],
        Y1 * w[1] + Y2_XY * (x * w[4] + z * w[5]) - 2.0 * Y2_XX_YY * y * w[8],
        Y1 * w[2] + Y2_XY * (y * w[5] + x * w[7]) + 6.0 * Y2_ZZ * z * w[6],
    ]
}

/// Coefficients [9, 3] of a constant irradiance `value` in every direction.
pub fn constant_light(value: f64) -> Vec<f32> {
    let mut c = vec![0.0f32; SH_COEFFICIENTS * 3];
    c[..3].fill((value / Y00) as f32);
    c
}

/// The shading kernel: inputs kd [N, 3], unit normals [N, 3], coefficients [9, 3]; output [N, 3].
struct ShDiffuse;

fn row<T: Real>(data: &[T], i: usize) -> [f64; 3] {
    [data[3 * i].to_f64(), data[3 * i + 1].to_f64(), data[3 * i + 2].to_f64()]
}

/// Irradiance per channel at basis values `y` under coefficients `light` [9·3].
fn irradiance<T: Real>(y: &[f64; SH_COEFFICIENTS], light: &[T]) -> [f64; 3] {
    let mut e = [0.0; 3];
    for (k, yk) in y.iter().enumerate() {
        for (c, ec) in e.iter_mut().enumerate() {
            *ec += yk * light[3 * k + c].to_f64();
        }
    }
    e
}

impl Kernel for ShDiffuse {
    fn name(&self) -> &'static str {
        "sh-diffuse"
    }

    fn output_shape(&self, shapes: &[&[usize]]) -> Result<Vec<usize>> {
        let ok = shapes.len() == 3 && shapes[0].len() == 2 && shapes[0][1] == 3 && shapes[1] == shapes[0] && shapes[2] == [SH_COEFFICIENTS, 3];
        if !ok {
            return Err(candle_core::Error::Msg(format!("sh-diffuse: expected kd [N, 3], normals [N, 3], light [9, 3]; got {shapes:?}")));
        }
        Ok(shapes[0].to_vec())
    }

    fn forward<T: Real>(&self, x: &[&[T]], _: &[&[usize]], out: &mut [T]) -> Result<()> {
        let (kd, n, light) = (x[0], x[1], x[2]);
        out.par_chunks_mut(3).enumerate().for_each(|(p, o)| {
            let e = irradiance(&sh_basis(row(n, p)), light);
            let k = row(kd, p);
            for c in 0..3 {
                o[c] = T::from_f64(k[c] * e[c]);
            }
        });
        Ok(())
    }

    fn backward<T: Real>(&self, x: &[&[T]], _: &[&[usize]], g: &[T], grads: &mut [Option<&mut [T]>]) -> Result<()> {
        let (kd, n, light) = (x[0], x[1], x[2]);
        let [g_kd, g_n, g_light] = grads else { return Ok(()) };
        if let Some(g_kd) = g_kd.as_deref_mut() {
            g_kd.par_chunks_mut(3).enumerate().for_each(|(p, out)| {
                let e = irradiance(&sh_basis(row(n, p)), light);
                for c in 0..3 {
                    out[c] += T::from_f64(g[3 * p + c].to_f64() * e[c]);
                }
            });
        }
        if let Some(g_n) = g_n.as_deref_mut() {
            g_n.par_chunks_mut(3).enumerate().for_each(|(p, out)| {
                let (k, gp) = (row(kd, p), row(g, p));
                let mut w = [0.0; SH_COEFFICIENTS];
                for (j, wj) in w.iter_mut().enumerate() {
                    *wj = (0..3).map(|c| gp[c] * k[c] * light[3 * j + c].to_f64()).sum();
                }
                let d = sh_basis_adjoint(row(n, p), &w);
                for c in 0..3 {
                    out[c] += T::from_f64(d[c]);
                }
            });
        }
        if let Some(g_light) = g_light.as_deref_mut() {
            let rows = kd.len() / 3;
            let partial: Vec<[f64; SH_COEFFICIENTS * 3]> = (0..rows.div_ceil(LIGHT_SUM_ROWS))
                .into_par_iter()
                .map(|chunk| {
                    let mut acc = [0.0; SH_COEFFICIENTS * 3];
                    for p in chunk * LIGHT_SUM_ROWS..((chunk + 1) * LIGHT_SUM_ROWS).min(rows) {
                        let (y, k, gp) = (sh_basis(row(n, p)), row(kd, p), row(g, p));
                        for (j, yj) in y.iter().enumerate() {
                            for c in 0..3 {
                                acc[3 * j + c] += yj * k[c] * gp[c];
                            }
                        }
                    }
                    acc
                })
                .collect();
            for acc in &partial {
                for (o, a) in g_light.iter_mut().zip(acc) {
                    *o += T::from_f64(*a);
                }
            }
        }
        Ok(())
    }
}

/// kd·E(n): `kd` [N, 3], unit normals `n` [N, 3], coefficients `light` [9, 3] → [N, 3], on the tape.
pub fn shade_diffuse(kd: &Tensor, n: &Tensor, light: &Tensor) -> Result<Tensor> {
    apply(ShDiffuse, &[kd, n, light])
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optim::gradcheck::check_gradient;
    use candle_core::Device;

    #[test]
    fn constant_light_is_constant_and_the_basis_is_orthonormal() -> anyhow::Result<()> {
        // Monte Carlo over the sphere (a Fibonacci lattice): ∫ Yᵢ Yⱼ = δᵢⱼ.
        let m = 4000;
        let dirs: Vec<f64> = (0..m)
            .flat_map(|i| {
                let z = 1.0 - 2.0 * (i as f64 + 0.5) / m as f64;
                let r = (1.0 - z * z).sqrt();
                let phi = i as f64 * 2.399_963_229_728_653;
                [r * phi.cos(), r * phi.sin(), z]
            })
            .collect();
        let basis: Vec<[f64; SH_COEFFICIENTS]> = dirs.chunks_exact(3).map(|d| sh_basis([d[0], d[1], d[2]])).collect();
        for i in 0..SH_COEFFICIENTS {
            for j in 0..SH_COEFFICIENTS {
                let v = basis.iter().map(|b| b[i] * b[j]).sum::<f64>() * 4.0 * std::f64::consts::PI / m as f64;
                let want = if i == j { 1.0 } else { 0.0 };
                assert!((v - want).abs() < 2e-3, "⟨Y{i}, Y{j}⟩ = {v}");
            }
        }
        let n = Tensor::from_vec(dirs, (m, 3), &Device::Cpu)?;
        let light = Tensor::from_vec(constant_light(0.7), (9, 3), &Device::Cpu)?.to_dtype(candle_core::DType::F64)?;
        let e = shade_diffuse(&n.ones_like()?, &n, &light)?.flatten_all()?.to_vec1::<f64>()?;
        assert!(e.iter().all(|v| (v - 0.7).abs() < 1e-6));
        Ok(())
    }

    #[test]
    fn gradients_match_finite_differences() -> anyhow::Result<()> {
        let d = &Device::Cpu;
        let n = Tensor::from_vec(vec![0.6, 0.0, 0.8, -0.48, 0.6, 0.64, 0.0, -1.0, 0.0f64], (3, 3), d)?;
        let kd = Tensor::from_vec(vec![0.2, 0.5, 0.9, 0.4, 0.4, 0.1, 0.7, 0.3, 0.6f64], (3, 3), d)?;
        let light = Tensor::from_vec((0..27).map(|i| ((i * 7 % 11) as f64 - 5.0) / 10.0).collect::<Vec<_>>(), (9, 3), d)?;
        check_gradient(|x| shade_diffuse(&x[0], &x[1], &x[2]), &[kd, n, light], 1e-6, 1e-6)?;
        Ok(())
    }

    #[test]
    fn single_coefficients_give_their_basis_function() -> anyhow::Result<()> {
        // Light in one coefficient and one channel: E is that basis function's value, by hand:
        // Y₁₀ = √(3/4π)·z at +z, Y₂₂ = √(15/16π)·(x² − y²) at +x, Y₂₀ = √(5/16π)·(3z² − 1) at +y.
        let d = &Device::Cpu;
        for (k, n, want) in [(2usize, [0.0, 0.0, 1.0], 0.488_602_5), (8, [1.0, 0.0, 0.0], 0.546_274_2), (6, [0.0, 1.0, 0.0], -0.315_391_6)] {
            let mut c = vec![0.0f64; 27];
            c[3 * k + 1] = 1.0; // green only
            let light = Tensor::from_vec(c, (9, 3), d)?;
            let out = shade_diffuse(&Tensor::ones((1, 3), candle_core::DType::F64, d)?, &Tensor::from_vec(n.to_vec(), (1, 3), d)?, &light)?.flatten_all()?.to_vec1::<f64>()?;
            assert!(out[0].abs() < 1e-12 && out[2].abs() < 1e-12 && (out[1] - want).abs() < 1e-6, "coefficient {k}: {out:?}");
        }
        Ok(())
    }

    #[test]
    fn the_light_gradient_sums_every_chunk() -> anyhow::Result<()> {
        // More rows than one partial sum holds: the light's adjoint against a plain f64 sum.
        let d = &Device::Cpu;
        let rows = 2 * LIGHT_SUM_ROWS + 77;
        let mut rng = crate::rng::Sampler::new(3, 0);
        let mut normal = || {
            let v = glam::DVec3::new(rng.next_f32() as f64 - 0.5, rng.next_f32() as f64 - 0.5, rng.next_f32() as f64 - 0.5).normalize();
            [v.x, v.y, v.z]
        };
        let n: Vec<[f64; 3]> = (0..rows).map(|_| normal()).collect();
        let kd: Vec<f64> = (0..3 * rows).map(|i| 0.1 + (i % 17) as f64 / 20.0).collect();
        let g: Vec<f64> = (0..3 * rows).map(|i| ((i * 13 % 7) as f64 - 3.0) / 5.0).collect();
        let light = candle_core::Var::from_tensor(&Tensor::from_vec(constant_light(0.5).iter().map(|&v| v as f64).collect::<Vec<_>>(), (9, 3), d)?)?;
        let out = shade_diffuse(&Tensor::from_vec(kd.clone(), (rows, 3), d)?, &Tensor::from_vec(n.concat(), (rows, 3), d)?, light.as_tensor())?;
        let grads = (out * Tensor::from_vec(g.clone(), (rows, 3), d)?)?.sum_all()?.backward()?;
        let got = grads.get(light.as_tensor()).expect("light gradient").flatten_all()?.to_vec1::<f64>()?;
        let mut want = [0.0f64; 27];
        for p in 0..rows {
            let y = sh_basis(n[p]);
            for k in 0..9 {
                for c in 0..3 {
                    want[3 * k + c] += y[k] * kd[3 * p + c] * g[3 * p + c];
                }
            }
        }
        for (a, b) in got.iter().zip(&want) {
            assert!((a - b).abs() <= 1e-9 * b.abs().max(1.0), "{a} against {b}");
        }
        Ok(())
    }
}

//! Every differentiable operator that does not need the renderer, against central finite
//! differences in f64 (metric: see `optim::gradcheck`), on random inputs and on hard cases.

use std::sync::Arc;

use candle_core::{DType, Device, Tensor, Var};
use glam::Vec3;
use reconstruct::optim::gradcheck::{check_gradient, check_gradient_with, GradCheckOptions};
use reconstruct::optim::{
    image_loss, jitter_uv, sample_bilinear, shading_regularizer, smoothness_regularizer, JitteredLookups, JitteredUv, srgb_encode, LossTarget,
    UniformLaplacian,
};
use reconstruct::render::denoise::{BilateralParams, CrossBilateral, DenoiseGuides};
use reconstruct::rng::Sampler;

const TOL: f64 = 1e-2;
const EPS: f64 = 1e-6;

fn rand_tensor(seed: u64, lo: f64, hi: f64, dims: &[usize]) -> Tensor {
    let mut s = Sampler::from_seed(seed);
    let n: usize = dims.iter().product();
    let v: Vec<f64> = (0..n).map(|_| lo + (hi - lo) * s.next_f32() as f64).collect();
    Tensor::from_vec(v, dims, &Device::Cpu).unwrap()
}

fn random_uv(seed: u64, n: usize, range: f32) -> Vec<[f32; 2]> {
    let mut s = Sampler::from_seed(seed);
    (0..n).map(|_| [(s.next_f32() - 0.5) * range + 0.5, (s.next_f32() - 0.5) * range + 0.5]).collect()
}

#[test]
fn texture_lookup_random_uvs() -> anyhow::Result<()> {
    let tex = rand_tensor(1, 0.0, 1.0, &[7, 9, 3]);
    // Includes UVs far outside [0, 1] (wrapping several times).
    let uv: Arc<[[f32; 2]]> = random_uv(2, 200, 5.0).into();
    let rep = check_gradient(|x| sample_bilinear(&x[0], &uv), &[tex], EPS, TOL)?;
    println!("texture random: {rep}");
    Ok(())
}

#[test]
fn texture_lookup_texel_centres_and_wrap_seam() -> anyhow::Result<()> {
    let (h, w) = (5usize, 6usize);
    let tex = rand_tensor(3, -1.0, 2.0, &[h, w, 2]);
    let mut uv = Vec::new();
    // Every texel centre exactly (bilinear weights (1, 0, 0, 0)).
    for j in 0..h {
        for i in 0..w {
            uv.push([(i as f32 + 0.5) / w as f32, 1.0 - (j as f32 + 0.5) / h as f32]);
        }
    }
    // The seam and the corners: u, v ∈ {0, 1} and just inside/outside.
    for &u in &[0.0f32, 1.0, 1e-7, 1.0 - 1e-7, -1e-7] {
        for &v in &[0.0f32, 1.0, 0.37, 1.0 - 1e-7] {
            uv.push([u, v]);
        }
    }
    let uv: Arc<[[f32; 2]]> = uv.into();
    let rep = check_gradient(|x| sample_bilinear(&x[0], &uv), std::slice::from_ref(&tex), EPS, TOL)?;
    println!("texture centres/seam: {rep}");
    // The adjoint at texel centres is exactly a copy of the output gradient into that texel.
    let var = Var::from_tensor(&tex)?;
    let centres: Arc<[[f32; 2]]> = uv[..h * w].to_vec().into();
    let out = sample_bilinear(var.as_tensor(), &centres)?;
    let g = out.sum_all()?.backward()?;
    let gt = g.get(var.as_tensor()).expect("texture grad").flatten_all()?.to_vec1::<f64>()?;
    assert!(gt.iter().all(|&v| (v - 1.0).abs() < 1e-6), "{gt:?}");
    Ok(())
}

#[test]
fn texture_lookup_f32_gradient_agrees_with_f64() -> anyhow::Result<()> {
    let tex64 = rand_tensor(4, 0.0, 1.0, &[16, 16, 3]);
    let uv: Arc<[[f32; 2]]> = random_uv(5, 3000, 1.0).into();
    let weights = rand_tensor(6, 0.5, 1.5, &[3000, 3]);
    let grad = |dtype: DType| -> anyhow::Result<Vec<f64>> {
        let v = Var::from_tensor(&tex64.to_dtype(dtype)?)?;
        let l = (sample_bilinear(v.as_tensor(), &uv)? * weights.to_dtype(dtype)?)?.sum_all()?;
        let g = l.backward()?;
        Ok(g.get(v.as_tensor()).expect("grad").to_dtype(DType::F64)?.flatten_all()?.to_vec1()?)
    };
    let (a, b) = (grad(DType::F32)?, grad(DType::F64)?);
    let scale = b.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let err = a.iter().zip(&b).fold(0.0f64, |m, (x, y)| m.max((x - y).abs()));
    assert!(err / scale < 1e-5, "f32 vs f64 texture gradient: {err} (scale {scale})");
    Ok(())
}

#[test]
fn srgb_curve_including_the_kink_at_zero() -> anyhow::Result<()> {
    // 0 is a kink of the curve alone (left slope 0): check only away from it here; the clamp
    // in the loss makes 0 itself consistent (next test).
    let x = Tensor::new(&[1e-5f64, 0.001, 0.003, 0.0032, 0.05, 0.5, 1.0, 4.0, 11.1], &Device::Cpu)?;
    check_gradient(|a| srgb_encode(&a[0]), &[x], 1e-8, TOL)?;
    Ok(())
}

#[test]
fn image_loss_random_inputs_and_alpha_term() -> anyhow::Result<()> {
    let rgb = rand_tensor(7, 0.0, 4.0, &[6, 5, 3]);
    let alpha = rand_tensor(8, 0.0, 1.0, &[6, 5, 1]);
    let target = LossTarget::new(&Tensor::cat(&[rgb, alpha], 2)?)?;
    let render = rand_tensor(9, 0.01, 5.0, &[6, 5, 3]);
    let ralpha = rand_tensor(10, 0.0, 1.0, &[6, 5, 1]);
    let rep = check_gradient(|x| image_loss(&x[0], Some(&x[1]), &target), &[render, ralpha], EPS, TOL)?;
    println!("image loss: {rep}");
    Ok(())
}

#[test]
fn image_loss_black_targets_black_renders_and_huge_hdr() -> anyhow::Result<()> {
    // Black target everywhere, alpha 1 on most pixels, 0 on some.
    let (h, w) = (4usize, 4usize);
    let mut rgba = vec![0.0f64; h * w * 4];
    for p in 0..h * w {
        rgba[p * 4 + 3] = if p % 5 == 0 { 0.0 } else { 1.0 };
    }
    let target = LossTarget::new(&Tensor::from_vec(rgba, (h, w, 4), &Device::Cpu)?)?;
    // Render: some exact zeros (the kink of abs and of the clamp at 0), some 1e5 (above the
    // 65535 clamp: gradient 0 and finite), the rest random.
    let mut s = Sampler::from_seed(11);
    let render: Vec<f64> = (0..h * w * 3)
        .map(|i| match i % 7 {
            0 => 0.0,
            3 => 1e5,
            _ => 0.05 + 2.0 * s.next_f32() as f64,
        })
        .collect();
    let render = Tensor::from_vec(render, (h, w, 3), &Device::Cpu)?;
    let l = image_loss(&render, None, &target)?.to_scalar::<f64>()?;
    assert!(l.is_finite());
    let rep = check_gradient(|x| image_loss(&x[0], None, &target), std::slice::from_ref(&render), 1e-7, TOL)?;
    println!("image loss hard cases: {rep}");
    // f32 with 1e5..1e30 stays finite, gradient too.
    let v = Var::from_tensor(&(render.to_dtype(DType::F32)? * 1e25)?)?;
    let l = image_loss(v.as_tensor(), None, &target)?;
    assert!(l.to_scalar::<f32>()?.is_finite());
    let g = l.backward()?;
    let g = g.get(v.as_tensor()).expect("grad").flatten_all()?.to_vec1::<f32>()?;
    assert!(g.iter().all(|x| x.is_finite()));
    Ok(())
}

#[test]
fn smoothness_regularizer_across_the_seam() -> anyhow::Result<()> {
    let tex = rand_tensor(12, 0.0, 1.0, &[8, 8, 3]);
    // Lookups right at the seam, jittered across it.
    let uv: Vec<[f32; 2]> = (0..60).map(|i| [if i % 2 == 0 { 0.0 } else { 0.999 }, i as f32 / 60.0]).collect();
    let uvj = jitter_uv(&uv, 0.02, 13);
    let uv: Arc<[[f32; 2]]> = uv.into();
    let wts = rand_tensor(14, 0.0, 1.0, &[60]);
    check_gradient(|x| smoothness_regularizer(&JitteredLookups::look_up(&x[0], &JitteredUv::from_pairs(&uv, &uvj)?)?, &wts), &[tex], EPS, TOL)?;
    Ok(())
}

#[test]
fn shading_regularizer_random() -> anyhow::Result<()> {
    let target = LossTarget::new(&rand_tensor(15, 0.0, 1.0, &[5, 4, 4]))?;
    let d = rand_tensor(16, 0.02, 2.0, &[5, 4, 3]);
    let s = rand_tensor(17, 0.0, 1.0, &[5, 4, 3]);
    check_gradient(|x| shading_regularizer(&x[0], &x[1], &target, 0.15, 0.0025), &[d, s], EPS, TOL)?;
    Ok(())
}

#[test]
fn laplacian_on_a_grid_with_a_degenerate_triangle() -> anyhow::Result<()> {
    // 4×4 vertex grid, two triangles per cell, plus a degenerate (repeated index) triangle.
    let n = 4u32;
    let mut tris = Vec::new();
    for y in 0..n - 1 {
        for x in 0..n - 1 {
            let i = y * n + x;
            tris.push([i, i + 1, i + n]);
            tris.push([i + 1, i + n + 1, i + n]);
        }
    }
    tris.push([0, 0, 5]);
    let lap = UniformLaplacian::new(16, &tris)?;
    let x = rand_tensor(18, -0.1, 0.1, &[16, 3]);
    check_gradient(|a| lap.regularizer(&a[0]), &[x], EPS, TOL)?;
    Ok(())
}

fn random_guides(w: usize, h: usize, seed: u64) -> anyhow::Result<DenoiseGuides> {
    let mut s = Sampler::from_seed(seed);
    let mut normal = Vec::new();
    let mut depth = Vec::new();
    let mut covered = Vec::new();
    for i in 0..w * h {
        // Two regions with different orientation, mild noise; a few holes and one zero normal.
        let base = if i % w < w / 2 { Vec3::Z } else { Vec3::new(0.6, 0.0, 0.8) };
        let n = base + 0.1 * Vec3::new(s.next_f32() - 0.5, s.next_f32() - 0.5, s.next_f32() - 0.5);
        normal.push(if i == 7 { Vec3::ZERO } else { n });
        depth.push(2.0 + 0.05 * (i % w) as f32 + 0.01 * s.next_f32());
        covered.push(i % 11 != 3);
    }
    DenoiseGuides::new(w, h, normal, depth, covered)
}

#[test]
fn denoiser_is_linear_and_its_backward_is_the_transpose() -> anyhow::Result<()> {
    let (w, h) = (9usize, 7usize);
    let f = CrossBilateral::new(Arc::new(random_guides(w, h, 19)?), BilateralParams { sigma: 1.5, radius: 3, normal_power: 16 });
    let x = rand_tensor(20, 0.0, 3.0, &[h, w, 3]);
    let rep = check_gradient_with(|a| f.apply(&a[0]), &[x], &GradCheckOptions { eps: EPS, tol: TOL, ..Default::default() })?;
    println!("denoiser: {rep}");
    Ok(())
}

#[test]
fn chained_texture_denoiser_loss_on_one_tape() -> anyhow::Result<()> {
    // texture → lookups at every pixel → denoise → image loss: the custom ops compose on the tape.
    let (w, h) = (6usize, 5usize);
    let tex = rand_tensor(21, 0.0, 1.0, &[4, 4, 3]);
    let uv: Arc<[[f32; 2]]> = random_uv(22, w * h, 1.0).into();
    let f = CrossBilateral::new(Arc::new(random_guides(w, h, 23)?), BilateralParams { sigma: 1.0, radius: 2, normal_power: 8 });
    let rgba = rand_tensor(24, 0.0, 1.0, &[h, w, 4]);
    let target = LossTarget::new(&rgba)?;
    let op = |x: &[Tensor]| {
        let img = sample_bilinear(&x[0], &uv)?.reshape((h, w, 3))?;
        image_loss(&(f.apply(&img)? * 2.0)?, None, &target)
    };
    check_gradient(op, &[tex], EPS, TOL)?;
    Ok(())
}

//! Adam driving the differentiable operators end to end: recover a texture from lookups through
//! the image loss, with the clamp holding and the schedule applied.

use std::sync::Arc;

use candle_core::{DType, Device, Tensor, Var};
use reconstruct::optim::{image_loss, sample_bilinear, Adam, GroupConfig, LossTarget, LrSchedule, UniformLaplacian};
use reconstruct::rng::Sampler;

#[test]
fn adam_recovers_a_texture_through_lookups_and_the_image_loss() -> anyhow::Result<()> {
    let dev = Device::Cpu;
    let (th, tw, n) = (8usize, 8usize, 4096usize);
    let mut s = Sampler::from_seed(31);
    let truth: Vec<f32> = (0..th * tw * 3).map(|_| 0.05 + 0.9 * s.next_f32()).collect();
    let truth = Tensor::from_vec(truth, (th, tw, 3), &dev)?;
    let uv: Arc<[[f32; 2]]> = (0..n).map(|_| [s.next_f32(), s.next_f32()]).collect::<Vec<_>>().into();
    // Target "image": n pixels in one row, fully covered.
    let seen = sample_bilinear(&truth, &uv)?.reshape((1, n, 3))?;
    let target = LossTarget::new(&Tensor::cat(&[seen, Tensor::ones((1, n, 1), DType::F32, &dev)?], 2)?)?;

    let tex = Var::from_tensor(&(Tensor::ones((th, tw, 3), DType::F32, &dev)? * 0.5)?)?;
    let mut adam = Adam::new(LrSchedule { warmup_steps: 20, decay_steps: 400, staircase: false });
    adam.add_group(GroupConfig::new("kd", 0.03).with_clamp(0.0, 1.0), vec![tex.clone()])?;
    let loss_of = |t: &Tensor| -> candle_core::Result<Tensor> {
        image_loss(&sample_bilinear(t, &uv)?.reshape((1, n, 3))?, None, &target)
    };
    let first = loss_of(tex.as_tensor())?.to_scalar::<f32>()?;
    for _ in 0..400 {
        let loss = loss_of(tex.as_tensor())?;
        adam.step(&loss.backward()?)?;
        let v = tex.as_tensor().flatten_all()?.to_vec1::<f32>()?;
        assert!(v.iter().all(|x| (0.0..=1.0).contains(x)));
    }
    let last = loss_of(tex.as_tensor())?.to_scalar::<f32>()?;
    assert!(last < 0.05 * first, "loss {first} -> {last}");
    let err = (tex.as_tensor() - &truth)?.abs()?.max_all()?.to_scalar::<f32>()?;
    assert!(err < 0.03, "max texel error {err}");
    assert!((adam.current_lr(0) - 0.03 * 10f64.powf(-380.0 / 400.0)).abs() < 1e-9);
    Ok(())
}

#[test]
fn laplacian_regulariser_with_adam_flattens_a_bump_but_keeps_translation() -> anyhow::Result<()> {
    let dev = Device::Cpu;
    // 5×5 vertex grid; offsets = translation + a bump in the middle.
    let n = 5u32;
    let mut tris = Vec::new();
    for y in 0..n - 1 {
        for x in 0..n - 1 {
            let i = y * n + x;
            tris.push([i, i + 1, i + n]);
            tris.push([i + 1, i + n + 1, i + n]);
        }
    }
    let lap = UniformLaplacian::new(25, &tris)?;
    let mut init = vec![0.0f64; 75];
    for v in 0..25 {
        init[v * 3] = 0.2;
    }
    init[12 * 3 + 2] = 0.5;
    let x = Var::from_tensor(&Tensor::from_vec(init, (25, 3), &dev)?)?;
    let mut adam = Adam::new(LrSchedule { warmup_steps: 0, decay_steps: 150, staircase: false });
    adam.add_group(GroupConfig::new("offsets", 0.01), vec![x.clone()])?;
    let before = lap.regularizer(x.as_tensor())?.to_scalar::<f64>()?;
    for _ in 0..300 {
        adam.step(&lap.regularizer(x.as_tensor())?.backward()?)?;
    }
    let after = lap.regularizer(x.as_tensor())?.to_scalar::<f64>()?;
    assert!(after < 0.01 * before, "{before} -> {after}");
    // The translation is in L's null space: the x-coordinates' mean stays 0.2.
    let mean_x = x.as_tensor().narrow(1, 0, 1)?.mean_all()?.to_scalar::<f64>()?;
    assert!((mean_x - 0.2).abs() < 1e-2, "{mean_x}");
    Ok(())
}

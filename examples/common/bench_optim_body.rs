// Shared body of the `bench_optim` examples (one built with mimalloc, one with the system
// allocator). Prints milliseconds per step, averaged after one warm-up iteration.

use std::sync::Arc;
use std::time::Instant;

use candle_core::{Device, Tensor, Var};
use candle_nn::Optimizer;
use reconstruct::optim::{build_pyramid, image_loss, sample_bilinear, sample_trilinear, Adam, GroupConfig, LossTarget, LrSchedule};
use reconstruct::render::denoise::{BilateralParams, CrossBilateral, DenoiseGuides};
use reconstruct::rng::Sampler;

fn time_ms(iters: usize, mut f: impl FnMut() -> anyhow::Result<()>) -> anyhow::Result<f64> {
    f()?; // warm-up: first-touch allocations, rayon pool start
    let t = Instant::now();
    for _ in 0..iters {
        f()?;
    }
    Ok(t.elapsed().as_secs_f64() * 1e3 / iters as f64)
}

pub fn run(allocator: &str) -> anyhow::Result<()> {
    let dev = Device::Cpu;
    let mut s = Sampler::from_seed(1);
    println!("allocator: {allocator}, rayon threads: {}", rayon::current_num_threads());

    // Texture lookups: 1024² RGB texture, 256² lookups, forward + backward.
    let tex = Var::from_tensor(&Tensor::rand(0f32, 1.0, (1024, 1024, 3), &dev)?)?;
    let uv: Arc<[[f32; 2]]> = (0..256 * 256).map(|_| [s.next_f32(), s.next_f32()]).collect::<Vec<_>>().into();
    let w = Tensor::rand(0f32, 1.0, (256 * 256, 3), &dev)?;
    let ms = time_ms(20, || {
        let l = (sample_bilinear(tex.as_tensor(), &uv)? * &w)?.sum_all()?;
        let g = l.backward()?;
        anyhow::ensure!(g.get(tex.as_tensor()).is_some());
        Ok(())
    })?;
    println!("texture sample fwd+bwd (1024² tex, 256² lookups): {ms:8.2} ms");
    let lod: Arc<[f32]> = (0..256 * 256).map(|_| 2.0 + s.next_f32()).collect::<Vec<_>>().into();
    let ms = time_ms(10, || {
        let (pyr, levels) = build_pyramid(tex.as_tensor())?;
        let l = (sample_trilinear(&pyr, &levels, &uv, &lod)? * &w)?.sum_all()?;
        let g = l.backward()?;
        anyhow::ensure!(g.get(tex.as_tensor()).is_some());
        Ok(())
    })?;
    println!("mip pyramid + trilinear fwd+bwd (same sizes):     {ms:8.2} ms");

    // Image loss on a 256² render, forward + backward.
    let render = Var::from_tensor(&Tensor::rand(0f32, 2.0, (256, 256, 3), &dev)?)?;
    let target = LossTarget::new(&Tensor::rand(0f32, 1.0, (256, 256, 4), &dev)?)?;
    let ralpha = Var::from_tensor(&Tensor::rand(0f32, 1.0, (256, 256, 1), &dev)?)?;
    let ms = time_ms(20, || {
        let l = image_loss(render.as_tensor(), Some(ralpha.as_tensor()), &target)?;
        l.backward()?;
        Ok(())
    })?;
    println!("image loss fwd+bwd (256²):                       {ms:8.2} ms");

    // Denoiser on a 256² RGB buffer, forward + backward (default σ = 2, radius 6).
    let (gw, gh) = (256usize, 256usize);
    let normal = (0..gw * gh).map(|i| glam::Vec3::new(((i % gw) as f32 / gw as f32) - 0.5, 0.0, 1.0)).collect();
    let depth = (0..gw * gh).map(|i| 2.0 + (i / gw) as f32 * 1e-3).collect();
    let guides = DenoiseGuides::new(gw, gh, normal, depth, vec![true; gw * gh])?;
    let guides = Arc::new(guides);
    let ms = time_ms(5, || {
        std::hint::black_box(CrossBilateral::new(guides.clone(), BilateralParams::default()));
        Ok(())
    })?;
    println!("denoiser setup (weights, 256²):                  {ms:8.2} ms");
    let den = CrossBilateral::new(guides, BilateralParams::default());
    let noisy = Var::from_tensor(&Tensor::rand(0f32, 1.0, (gh, gw, 3), &dev)?)?;
    let ms = time_ms(5, || {
        let l = den.apply(noisy.as_tensor())?.sum_all()?;
        l.backward()?;
        Ok(())
    })?;
    println!("denoiser fwd+bwd (256² RGB, 13×13 window):        {ms:8.2} ms");

    // Adam step on 1M parameters (gradient precomputed; the step alone is timed).
    let p = Var::from_tensor(&Tensor::rand(0f32, 1.0, 1 << 20, &dev)?)?;
    let c = Tensor::rand(-1f32, 1.0, 1 << 20, &dev)?;
    let grads = (p.as_tensor() * &c)?.sum_all()?.backward()?;
    let mut adam = Adam::new(LrSchedule::default());
    adam.add_group(GroupConfig::new("p", 1e-3).with_clamp(0.0, 1.0), vec![p.clone()])?;
    let ms = time_ms(50, || adam.step(&grads))?;
    println!("Adam step, ours (1M params, clamp):               {ms:8.2} ms");
    let p2 = Var::from_tensor(&Tensor::rand(0f32, 1.0, 1 << 20, &dev)?)?;
    let grads2 = (p2.as_tensor() * &c)?.sum_all()?.backward()?;
    let params = candle_nn::ParamsAdamW { lr: 1e-3, weight_decay: 0.0, ..Default::default() };
    let mut adamw = candle_nn::AdamW::new(vec![p2.clone()], params)?;
    let ms = time_ms(50, || Ok(adamw.step(&grads2)?))?;
    println!("Adam step, candle-nn AdamW wd=0 (1M params):      {ms:8.2} ms");
    Ok(())
}

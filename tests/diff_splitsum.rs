//! Differentiable split-sum shading: forward against `render::splitsum::shade`, every gradient
//! against central finite differences (f64), including the hard cases of the brief.

use std::sync::Arc;
use std::time::Instant;

use candle_core::{DType, Device, Tensor, Var};
use glam::{Vec2, Vec3};
use reconstruct::light::brdf_lut::BrdfLut;
use reconstruct::light::prefilter::{PrefilterOptions, SplitSumLight};
use reconstruct::light::CubeMap;
use reconstruct::material::SurfaceParams;
use reconstruct::optim::gradcheck::{check_gradient_with, GradCheckOptions};
use reconstruct::render::effects::Effects;
use reconstruct::render::gbuffer::{GBuffer, Surfel};
use reconstruct::render::splitsum;
use reconstruct::render::splitsum_op::{shade_splitsum, LightMaps, SplitSumShading};
use reconstruct::rng::Sampler;

fn random_dir(rng: &mut Sampler) -> Vec3 {
    let z = 2.0 * rng.next_f32() - 1.0;
    let phi = std::f32::consts::TAU * rng.next_f32();
    let r = (1.0 - z * z).max(0.0).sqrt();
    Vec3::new(r * phi.cos(), r * phi.sin(), z)
}

/// (normal, outgoing) pairs with n·v spread over (0, 1]; the first `grazing` pixels have n·v ≤ 1e-3
/// (one exactly 0, clamped by the shader).
fn random_geometry(n: usize, grazing: usize, rng: &mut Sampler) -> Vec<Option<(Vec3, Vec3)>> {
    (0..n)
        .map(|p| {
            let normal = random_dir(rng);
            let tangent = normal.any_orthonormal_vector();
            let cos = if p < grazing { 1e-3 * p as f32 / grazing.max(1) as f32 } else { 0.05 + 0.95 * rng.next_f32() };
            let wo = (normal * cos + tangent * (1.0 - cos * cos).sqrt()).normalize();
            // A miss every 7th pixel: zero output, zero gradient.
            (p % 7 != 6).then_some((normal, wo))
        })
        .collect()
}

fn random_light(res: usize, rng: &mut Sampler) -> CubeMap {
    let mut m = CubeMap::constant(res, Vec3::ZERO);
    for v in m.data.iter_mut() {
        *v = Vec3::new(0.1 + 2.0 * rng.next_f32(), 0.1 + rng.next_f32(), 0.1 + 3.0 * rng.next_f32());
    }
    m
}

fn light_tensor(m: &CubeMap) -> Tensor {
    let flat: Vec<f64> = m.data.iter().flat_map(|v| [v.x as f64, v.y as f64, v.z as f64]).collect();
    Tensor::from_vec(flat, (6, m.res, m.res, 3), &Device::Cpu).expect("light tensor")
}

fn lut() -> Arc<BrdfLut> {
    Arc::new(BrdfLut::compute(32, 64))
}

/// Materials: kd, ks = (occlusion, roughness, metallic) from the given generators.
fn materials(n: usize, rng: &mut Sampler, kd: impl Fn(&mut Sampler) -> [f64; 3], rough: impl Fn(&mut Sampler, usize) -> f64, metal: impl Fn(&mut Sampler, usize) -> f64) -> (Tensor, Tensor) {
    let mut kdv = Vec::new();
    let mut ksv = Vec::new();
    for p in 0..n {
        kdv.extend(kd(rng));
        ksv.extend([rng.next_f32() as f64, rough(rng, p), metal(rng, p)]);
    }
    (
        Tensor::from_vec(kdv, (n, 3), &Device::Cpu).expect("kd"),
        Tensor::from_vec(ksv, (n, 3), &Device::Cpu).expect("ks"),
    )
}

/// Roughness away from the piecewise-linear kinks' neighbourhood is what random draws give anyway;
/// these draws cover both level regimes (below and above 0.5).
fn any_roughness(rng: &mut Sampler, _p: usize) -> f64 {
    0.09 + 0.9 * rng.next_f32() as f64
}

fn check(op: &SplitSumShading, kd: Tensor, ks: Tensor, light: Tensor, what: &str) {
    let opts = GradCheckOptions { eps: 1e-6, tol: 1e-2, max_elements: 400, seed: 5 };
    let rep = check_gradient_with(|x| shade_splitsum(op, &x[0], &x[1], &x[2]), &[kd, ks, light], &opts)
        .unwrap_or_else(|e| panic!("{what}: {e}"));
    println!("{what}:\n{rep}");
}

fn op_for(res: usize, geometry: &[Option<(Vec3, Vec3)>]) -> SplitSumShading {
    let light = Arc::new(LightMaps::new(res, PrefilterOptions::default()));
    SplitSumShading::new(geometry, light, lut(), Effects::DIRECT)
}

#[test]
fn forward_equals_the_split_sum_renderer() {
    let mut rng = Sampler::from_seed(1);
    for res in [32usize, 64] {
        let (w, h) = (9, 7);
        let origin = Vec3::new(0.3, -0.2, 4.0);
        let surfels: Vec<Option<Surfel>> = (0..w * h)
            .map(|p| {
                let position = Vec3::new(rng.next_f32() - 0.5, rng.next_f32() - 0.5, rng.next_f32() - 0.5);
                let mut normal = random_dir(&mut rng);
                if normal.dot(origin - position) < 0.0 {
                    normal = -normal;
                }
                (p % 5 != 4).then_some(Surfel { position, normal, geo_normal: normal, uv: Vec2::ZERO, triangle: 0, bary: Vec2::ZERO, depth: 1.0 })
            })
            .collect();
        let gbuf = GBuffer { width: w, height: h, origin, surfels };
        let params: Vec<Option<SurfaceParams>> = (0..w * h)
            .map(|p| {
                // Include the floor, beyond-range roughness and metallic 0/1.
                let roughness = match p % 6 {
                    0 => 0.02,
                    1 => 1.3,
                    _ => rng.next_f32(),
                };
                let metallic = match p % 4 {
                    0 => 0.0,
                    1 => 1.0,
                    _ => rng.next_f32(),
                };
                Some(SurfaceParams { kd: Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()), roughness, metallic })
            })
            .collect();
        let base = random_light(res, &mut rng);
        let opts = PrefilterOptions::default();
        let lut = lut();
        for effects in [Effects::DIRECT, Effects { shadows: false, specular: false, indirect_bounces: 0 }] {
            let reference = splitsum::shade(&gbuf, &params, &SplitSumLight::with_options(&base, opts), &lut, effects);
            let op = SplitSumShading::from_gbuffer(&gbuf, Arc::new(LightMaps::new(res, opts)), lut.clone(), effects);
            let kd: Vec<f32> = params.iter().flat_map(|p| p.expect("params").kd.to_array()).collect();
            let ks: Vec<f32> = params.iter().flat_map(|p| p.map(|p| [1.0, p.roughness, p.metallic]).expect("params")).collect();
            let n = w * h;
            let kd = Tensor::from_vec(kd, (n, 3), &Device::Cpu).expect("kd");
            let ks = Tensor::from_vec(ks, (n, 3), &Device::Cpu).expect("ks");
            let light = light_tensor(&base).to_dtype(DType::F32).expect("f32");
            let out = shade_splitsum(&op, &kd, &ks, &light).expect("forward").to_vec2::<f32>().expect("vec");
            for (p, (got, want)) in out.iter().zip(&reference).enumerate() {
                let scale = want.abs().max_element().max(0.1);
                let err = (Vec3::from_slice(got) - *want).abs().max_element();
                assert!(err < 2e-4 * scale, "res {res}, pixel {p}: op {got:?} vs shade {want} (specular {})", effects.specular);
            }
        }
    }
}

#[test]
fn gradients_on_random_inputs() {
    let mut rng = Sampler::from_seed(2);
    for res in [32usize, 64] {
        let n = 40;
        let op = op_for(res, &random_geometry(n, 0, &mut rng));
        let (kd, ks) = materials(n, &mut rng, |r| [r.next_f32() as f64, r.next_f32() as f64, r.next_f32() as f64], any_roughness, |r, _| r.next_f32() as f64);
        let light = light_tensor(&random_light(res, &mut rng));
        check(&op, kd, ks, light, &format!("random, base {res}²"));
    }
}

#[test]
fn gradients_in_hard_cases() {
    let mut rng = Sampler::from_seed(3);
    let res = 32;
    let n = 42;
    // Grazing views (n·v ≤ 1e-3), metallic exactly 0 and 1, black albedo on a third of the pixels.
    let op = op_for(res, &random_geometry(n, 10, &mut rng));
    let (kd, ks) = materials(
        n,
        &mut rng,
        |r| if r.next_f32() < 0.33 { [0.0; 3] } else { [r.next_f32() as f64, r.next_f32() as f64, r.next_f32() as f64] },
        any_roughness,
        |r, p| match p % 3 {
            0 => 0.0,
            1 => 1.0,
            _ => r.next_f32() as f64,
        },
    );
    let mut base = random_light(res, &mut rng);
    check(&op, kd.clone(), ks.clone(), light_tensor(&base), "grazing / metallic 0, 1 / black albedo");
    // A sun: one texel of radiance 1e5.
    let k = base.texel_index(4, 11, 20);
    base.data[k] = Vec3::splat(1e5);
    check(&op, kd, ks, light_tensor(&base), "1e5-radiance texel");
}

#[test]
fn roughness_below_the_floor_only_moves_the_lut() {
    let mut rng = Sampler::from_seed(4);
    let res = 64;
    let n = 30;
    let op = op_for(res, &random_geometry(n, 0, &mut rng));
    let light = light_tensor(&random_light(res, &mut rng));
    let kd_gen = |r: &mut Sampler| [r.next_f32() as f64, r.next_f32() as f64, r.next_f32() as f64];
    // Between the LUT's first texel centre (1/64) and the 0.08 floor: the prefiltered level is
    // clamped but (A, B) still vary, and the gradient must agree with finite differences.
    let (kd, ks) = materials(n, &mut rng, kd_gen, |r, _| 0.02 + 0.055 * r.next_f32() as f64, |r, _| r.next_f32() as f64);
    check(&op, kd, ks, light.clone(), "roughness in (0.02, 0.075)");
    // Below the LUT's first texel centre every roughness dependence is clamped: exactly zero.
    let (kd, ks) = materials(n, &mut rng, kd_gen, |r, _| 0.014 * r.next_f32() as f64, |r, _| r.next_f32() as f64);
    let ks = Var::from_tensor(&ks).expect("var");
    let out = shade_splitsum(&op, &kd, ks.as_tensor(), &light).expect("forward");
    let grads = out.sum_all().and_then(|s| s.backward()).expect("backward");
    let g = grads.get(ks.as_tensor()).expect("ks grad").to_vec2::<f64>().expect("vec");
    assert!(g.iter().all(|row| row[0] == 0.0 && row[1] == 0.0), "roughness/occlusion gradients must vanish: {g:?}");
    assert!(g.iter().any(|row| row[2] != 0.0), "metallic gradient should not vanish");
}

#[test]
fn light_backward_is_the_exact_transpose_of_its_forward() {
    // ⟨forward(x), y⟩ = ⟨x, backward(y)⟩ for random x, y: every texel of every step, including a
    // copy-only chain (16²) and one that stops at an odd resolution (24² → 12²).
    let mut rng = Sampler::from_seed(7);
    for res in [16usize, 24, 32, 64] {
        let st = LightMaps::new(res, PrefilterOptions::default());
        let x: Vec<f64> = (0..18 * res * res).map(|_| rng.next_f32() as f64 - 0.5).collect();
        let lv = st.forward(&x);
        let ys: Vec<Vec<f64>> = lv.specular.iter().map(|l| l.iter().map(|_| rng.next_f32() as f64 - 0.5).collect()).collect();
        let yd: Vec<f64> = lv.diffuse.iter().map(|_| rng.next_f32() as f64 - 0.5).collect();
        let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(p, q)| p * q).sum::<f64>();
        let lhs: f64 = lv.specular.iter().zip(&ys).map(|(a, b)| dot(a, b)).sum::<f64>() + dot(&lv.diffuse, &yd);
        let rhs = dot(&x, &st.backward(&ys, &yd));
        assert!((lhs - rhs).abs() < 1e-10 * lhs.abs().max(1.0), "base {res}²: {lhs} vs {rhs}");
    }
}

#[test]
fn specular_light_gradient_on_the_texels_that_matter() {
    // Metallic 1 removes the diffuse path, low roughness concentrates the gradient on a few
    // texels; compare with central differences on the 40 largest and 40 random texel channels
    // (the generic checker's evenly spread picks would mostly land where the gradient is ~0).
    let mut rng = Sampler::from_seed(8);
    let res = 32;
    let n = 12;
    let op = op_for(res, &random_geometry(n, 0, &mut rng));
    let (kd, ks) = materials(n, &mut rng, |r| [0.2 + 0.8 * r.next_f32() as f64; 3], |r, _| 0.09 + 0.15 * r.next_f32() as f64, |_, _| 1.0);
    let base = light_tensor(&random_light(res, &mut rng));
    let weights: Vec<f64> = (0..3 * n).map(|_| 0.5 + rng.next_f32() as f64).collect();
    let weights = Tensor::from_vec(weights, (n, 3), &Device::Cpu).expect("weights");
    let loss = |light: &Tensor| -> f64 {
        let out = shade_splitsum(&op, &kd, &ks, light).expect("forward");
        (out * &weights).and_then(|t| t.sum_all()).and_then(|t| t.to_scalar::<f64>()).expect("loss")
    };
    let var = Var::from_tensor(&base).expect("var");
    let out = shade_splitsum(&op, &kd, &ks, var.as_tensor()).expect("forward");
    let grads = (out * &weights).and_then(|t| t.sum_all()).and_then(|t| t.backward()).expect("backward");
    let g = grads.get(var.as_tensor()).expect("grad").flatten_all().and_then(|t| t.to_vec1::<f64>()).expect("vec");
    let flat = base.flatten_all().and_then(|t| t.to_vec1::<f64>()).expect("vec");
    let mut order: Vec<usize> = (0..g.len()).collect();
    order.sort_by(|&a, &b| g[b].abs().total_cmp(&g[a].abs()));
    let mut picks: Vec<usize> = order[..40].to_vec();
    picks.extend((0..40).map(|_| (rng.next_f32() * g.len() as f32) as usize % g.len()));
    let gmax = g[order[0]].abs();
    assert!(gmax > 0.0);
    let eps = 1e-6;
    for &k in &picks {
        let at = |d: f64| {
            let mut v = flat.clone();
            v[k] += d;
            loss(&Tensor::from_vec(v, base.shape(), &Device::Cpu).expect("tensor"))
        };
        let fd = (at(eps) - at(-eps)) / (2.0 * eps);
        assert!((fd - g[k]).abs() <= 1e-2 * gmax, "texel channel {k}: analytic {} vs fd {fd} (max |g| {gmax})", g[k]);
    }
    // The gradient really is concentrated: most texels get nothing through the specular path.
    assert!(g.iter().filter(|v| **v != 0.0).count() < g.len() / 2);
}

#[test]
fn matrix_free_light_agrees_with_the_stored_stencils() {
    let mut rng = Sampler::from_seed(9);
    for res in [32usize, 64] {
        let (stored, free) = (LightMaps::new(res, PrefilterOptions::default()), LightMaps::matrix_free(res, PrefilterOptions::default()));
        let x: Vec<f64> = (0..18 * res * res).map(|_| 3.0 * rng.next_f32() as f64).collect();
        let (a, b) = (stored.forward(&x), free.forward(&x));
        let close = |p: &[f64], q: &[f64], what: &str| {
            let scale = p.iter().fold(0.0f64, |m, v| m.max(v.abs()));
            let err = p.iter().zip(q).fold(0.0f64, |m, (u, v)| m.max((u - v).abs()));
            assert!(err <= 1e-5 * scale, "base {res}², {what}: max error {err} vs scale {scale}");
        };
        for (k, (p, q)) in a.specular.iter().zip(&b.specular).enumerate() {
            close(p, q, &format!("specular level {k}"));
        }
        close(&a.diffuse, &b.diffuse, "diffuse");
        let ys: Vec<Vec<f64>> = a.specular.iter().map(|l| l.iter().map(|_| rng.next_f32() as f64 - 0.5).collect()).collect();
        let yd: Vec<f64> = a.diffuse.iter().map(|_| rng.next_f32() as f64 - 0.5).collect();
        close(&stored.backward(&ys, &yd), &free.backward(&ys, &yd), "adjoint");
        // The whole op: every input's gradient, stored vs matrix-free light (the stored one is the
        // one checked against finite differences above).
        let n = 30;
        let geometry = random_geometry(n, 3, &mut rng);
        let (kd, ks) = materials(n, &mut rng, |r| [r.next_f32() as f64, r.next_f32() as f64, r.next_f32() as f64], any_roughness, |r, _| r.next_f32() as f64);
        let light = light_tensor(&random_light(res, &mut rng));
        let grads = |maps: LightMaps| -> Vec<Vec<f64>> {
            let op = SplitSumShading::new(&geometry, Arc::new(maps), lut(), Effects::DIRECT);
            let vars: Vec<Var> = [&kd, &ks, &light].iter().map(|t| Var::from_tensor(t).expect("var")).collect();
            let out = shade_splitsum(&op, vars[0].as_tensor(), vars[1].as_tensor(), vars[2].as_tensor()).expect("forward");
            let g = out.sqr().and_then(|t| t.sum_all()).and_then(|t| t.backward()).expect("backward");
            vars.iter().map(|v| g.get(v.as_tensor()).expect("grad").flatten_all().and_then(|t| t.to_vec1::<f64>()).expect("vec")).collect()
        };
        let (gs, gf) = (grads(LightMaps::new(res, PrefilterOptions::default())), grads(LightMaps::matrix_free(res, PrefilterOptions::default())));
        for (i, (p, q)) in gs.iter().zip(&gf).enumerate() {
            close(p, q, &format!("op gradient of input {i}"));
        }
    }
}

/// Timing of the light rebuild and the op at larger base maps:
/// `cargo test --release --test diff_splitsum measure -- --ignored --nocapture`.
#[test]
#[ignore]
fn measure() {
    let mut rng = Sampler::from_seed(6);
    let n = 256 * 256;
    for (res, stored) in [(128usize, true), (128, false), (256, false), (512, false)] {
        let t0 = Instant::now();
        let opts = PrefilterOptions::default();
        let light = Arc::new(if stored { LightMaps::new(res, opts) } else { LightMaps::matrix_free(res, opts) });
        let build = t0.elapsed().as_secs_f64();
        let op = SplitSumShading::new(&random_geometry(n, 0, &mut rng), light.clone(), lut(), Effects::DIRECT);
        let (kd, ks) = materials(n, &mut rng, |r| [r.next_f32() as f64; 3], any_roughness, |r, _| r.next_f32() as f64);
        let (kd, ks) = (kd.to_dtype(DType::F32).expect("f32"), ks.to_dtype(DType::F32).expect("f32"));
        let kd = Var::from_tensor(&kd).expect("var");
        let lt = Var::from_tensor(&light_tensor(&random_light(res, &mut rng)).to_dtype(DType::F32).expect("f32")).expect("var");
        let t1 = Instant::now();
        let out = shade_splitsum(&op, kd.as_tensor(), &ks, lt.as_tensor()).expect("forward");
        let fwd = t1.elapsed().as_secs_f64();
        let t2 = Instant::now();
        let _g = out.sum_all().and_then(|s| s.backward()).expect("backward");
        let bwd = t2.elapsed().as_secs_f64();
        let t3 = Instant::now();
        let _ = SplitSumLight::new(&random_light(res, &mut rng));
        let plain = t3.elapsed().as_secs_f64();
        println!(
            "base 6×{res}² {}: build {build:.2} s ({} stencil entries), forward {fwd:.3} s, backward {bwd:.3} s ({n} pixels); SplitSumLight::new {plain:.2} s",
            if stored { "stored" } else { "matrix-free" },
            light.nnz()
        );
    }
}

//! Light importance sampling: the pdf integrates to 1, the histogram of samples matches it, and
//! extreme maps (all black, a 1e5 sun) give finite, unbiased estimates.

use glam::Vec3;
use reconstruct::light::cubemap::{face_dir, face_solid_angles};
use reconstruct::light::{CubeMap, LightSampler};
use reconstruct::rng::Sampler;

/// ∫ pdf over each texel's (sub × sub) sub-squares, by an n×n midpoint rule on the face plane
/// (dω = |d|⁻³ dA). Returned in data order, sub-squares row-major inside each texel.
fn pdf_per_subsquare(sampler: &LightSampler, res: usize, sub: usize, n: usize) -> Vec<f64> {
    let mut out = Vec::with_capacity(6 * res * res * sub * sub);
    let h = 2.0 / (res * sub * n) as f64;
    for face in 0..6 {
        for i in 0..res {
            for j in 0..res {
                for a in 0..sub {
                    for b in 0..sub {
                        let mut sum = 0.0;
                        for p in 0..n {
                            for q in 0..n {
                                let t = -1.0 + h * ((i * sub + a) * n + p) as f64 + 0.5 * h;
                                let s = -1.0 + h * ((j * sub + b) * n + q) as f64 + 0.5 * h;
                                let d = face_dir(face, s as f32, t as f32);
                                let dw = (1.0 + s * s + t * t).powf(-1.5) * h * h;
                                sum += sampler.pdf(d.normalize()) as f64 * dw;
                            }
                        }
                        out.push(sum);
                    }
                }
            }
        }
    }
    out
}

/// Which (texel, sub-square) a direction falls in, in the order of [`pdf_per_subsquare`].
fn subsquare_of(d: Vec3, res: usize, sub: usize) -> usize {
    let (face, s, t) = reconstruct::light::cubemap::dir_to_face(d);
    let k = |c: f32| ((((c + 1.0) * 0.5) * (res * sub) as f32) as usize).min(res * sub - 1);
    let (row, col) = (k(t), k(s));
    let texel = (face * res + row / sub) * res + col / sub;
    texel * sub * sub + (row % sub) * sub + col % sub
}

fn random_map(res: usize, seed: u64) -> CubeMap {
    let mut rng = Sampler::from_seed(seed);
    let mut map = CubeMap::constant(res, Vec3::ZERO);
    for v in map.data.iter_mut() {
        // Heavy-tailed values (a few bright texels), some exactly black.
        let x = rng.next_f32();
        *v = if x < 0.1 { Vec3::ZERO } else { Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) * (6.0 * x * x).exp() };
    }
    map
}

#[test]
fn pdf_integrates_to_one_and_histogram_matches() {
    let res = 6;
    let sub = 2;
    let map = random_map(res, 5);
    let sampler = LightSampler::new(&map);
    let expected = pdf_per_subsquare(&sampler, res, sub, 16);
    let total: f64 = expected.iter().sum();
    assert!((total - 1.0).abs() < 1e-4, "∫pdf = {total}");
    let n = 400_000usize;
    let mut counts = vec![0usize; expected.len()];
    let mut rng = Sampler::new(21, 0);
    for _ in 0..n {
        let s = sampler.sample(rng.next_2d());
        assert!(s.dir.is_finite() && s.pdf.is_finite() && s.pdf > 0.0);
        assert_eq!(s.radiance, sampler.radiance(s.dir));
        assert!(s.radiance != Vec3::ZERO, "a black texel was sampled");
        counts[subsquare_of(s.dir, res, sub)] += 1;
    }
    let (mut chi2, mut dof) = (0.0, 0usize);
    for (e, c) in expected.iter().zip(&counts) {
        let e = e * n as f64;
        if e >= 20.0 {
            chi2 += (*c as f64 - e).powi(2) / e;
            dof += 1;
        } else {
            assert!((*c as f64) < e + 5.0 * e.sqrt() + 5.0, "{c} samples where {e} expected");
        }
    }
    let limit = dof as f64 + 5.0 * (2.0 * dof as f64).sqrt();
    println!("light sampler: χ² = {chi2:.1} over {dof} bins (limit {limit:.1})");
    assert!(chi2 < limit);
}

#[test]
fn estimates_of_total_power_are_unbiased_even_with_a_sun() {
    for (name, map) in [
        ("random", random_map(8, 9)),
        ("sun", {
            let mut m = CubeMap::constant(16, Vec3::splat(0.1));
            m.data[3 * 256 + 5 * 16 + 9] = Vec3::new(1e5, 9e4, 8e4);
            m
        }),
    ] {
        let sampler = LightSampler::new(&map);
        let area = face_solid_angles(map.res);
        let exact: f64 = map.data.iter().enumerate().map(|(k, v)| v.x as f64 * area[k % (map.res * map.res)] as f64).sum();
        let n = 100_000;
        let mut rng = Sampler::new(22, 1);
        let mut est = 0.0f64;
        for _ in 0..n {
            let s = sampler.sample(rng.next_2d());
            assert!(s.dir.is_finite() && s.radiance.is_finite() && s.pdf.is_finite() && s.pdf > 0.0, "{name}: {s:?}");
            est += (s.radiance.x / s.pdf) as f64;
        }
        est /= n as f64;
        println!("{name}: ∫L dω = {exact:.4}, estimate {est:.4}");
        assert!((est - exact).abs() < 0.01 * exact, "{name}: {est} vs {exact}");
        // Every direction has a finite, non-negative pdf (MIS evaluates it for BSDF samples).
        let mut rng = Sampler::new(23, 0);
        for _ in 0..10_000 {
            let d = Vec3::new(rng.next_f32() - 0.5, rng.next_f32() - 0.5, rng.next_f32() - 0.5).normalize_or(Vec3::X);
            let p = sampler.pdf(d);
            assert!(p.is_finite() && p >= 0.0);
        }
    }
}

#[test]
fn black_map_falls_back_to_uniform_sampling() {
    let res = 4;
    let sampler = LightSampler::new(&CubeMap::constant(res, Vec3::ZERO));
    let total: f64 = pdf_per_subsquare(&sampler, res, 1, 16).iter().sum();
    assert!((total - 1.0).abs() < 1e-4, "∫pdf = {total}");
    let mut rng = Sampler::new(24, 0);
    let mut per_face = [0usize; 6];
    for _ in 0..60_000 {
        let s = sampler.sample(rng.next_2d());
        assert!(s.pdf.is_finite() && s.pdf > 0.0 && s.radiance == Vec3::ZERO);
        per_face[reconstruct::light::cubemap::dir_to_face(s.dir).0] += 1;
    }
    assert!(per_face.iter().all(|&c| (c as f64 - 10_000.0).abs() < 500.0), "{per_face:?}");
}

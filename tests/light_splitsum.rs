//! Split-sum light: prefiltered specular levels, diffuse irradiance and the BRDF table, each
//! against an independent brute-force integral.

use std::f64::consts::PI;
use std::time::Instant;

use glam::{DVec3, Vec3};
use reconstruct::light::brdf_lut::BrdfLut;
use reconstruct::light::prefilter::{PrefilterOptions, SplitSumLight};
use reconstruct::light::CubeMap;
use reconstruct::math::Frame;

/// A smooth light with a few degrees of variation per colour channel.
fn smooth_light(d: Vec3) -> Vec3 {
    Vec3::new(1.0 + 0.6 * d.x + 0.3 * d.z * d.z, 0.5 + 0.4 * d.y * d.z + 0.2 * d.x * d.y, 0.3 * (2.0 * d.z).exp())
}

/// ∫ g(l) over the sphere in spherical coordinates around `axis`, with θ = w·q/(1−q) (fine near
/// the axis when w is small), midpoint rule, in f64.
fn sphere_integral(axis: Vec3, w: f64, nq: usize, nphi: usize, g: impl Fn(Vec3) -> DVec3) -> DVec3 {
    let frame = Frame::from_normal(axis.normalize());
    let q_max = PI / (PI + w);
    let mut sum = DVec3::ZERO;
    for a in 0..nq {
        let q = q_max * (a as f64 + 0.5) / nq as f64;
        let theta = w * q / (1.0 - q);
        let jac = theta.sin() * w / ((1.0 - q) * (1.0 - q)) * (q_max / nq as f64) * (2.0 * PI / nphi as f64);
        for b in 0..nphi {
            let phi = 2.0 * PI * (b as f64 + 0.5) / nphi as f64;
            let local = Vec3::new((theta.sin() * phi.cos()) as f32, (theta.sin() * phi.sin()) as f32, theta.cos() as f32);
            sum += g(frame.to_world(local)) * jac;
        }
    }
    sum
}

/// GGX lobe of the prefilter for n = v = r, from the formula of docs/model.md (*Shading*) in f64:
/// (l·r)·D(h)/4.
fn lobe(l: Vec3, r: Vec3, roughness: f64) -> f64 {
    let c = l.dot(r) as f64;
    if c <= 0.0 {
        return 0.0;
    }
    let a2 = roughness.powi(4);
    let nh = ((1.0 + c) / 2.0).sqrt();
    let d = nh * nh * (a2 - 1.0) + 1.0;
    c * a2 / (PI * d * d) / 4.0
}

fn rel_err(a: Vec3, b: DVec3) -> f64 {
    (a.as_dvec3() - b).abs().max_element() / b.abs().max_element()
}

#[test]
fn constant_light_stays_constant() {
    let value = Vec3::new(0.5, 1.5, 3.0);
    let light = SplitSumLight::new(&CubeMap::constant(32, value));
    let dirs = [Vec3::X, Vec3::new(1.0, 1.0, 1.0), Vec3::new(-0.2, 0.7, -0.1), Vec3::new(1.0, -1.0, 0.3), -Vec3::Z];
    for d in dirs {
        for r in [0.0f32, 0.08, 0.2, 0.35, 0.5, 0.7, 1.0, 2.0] {
            let s = light.specular(d.normalize(), r);
            assert!((s - value).abs().max_element() < 1e-5 * 3.0, "specular({d}, {r}) = {s}");
        }
        let diffuse = light.diffuse(d.normalize());
        assert!((diffuse - value).abs().max_element() < 1e-5 * 3.0, "diffuse({d}) = {diffuse}");
    }
}

#[test]
fn prefiltered_levels_match_brute_force_ggx_integrals() {
    let light = SplitSumLight::new(&CubeMap::from_fn(64, smooth_light));
    assert_eq!(light.level_roughness, vec![0.08, 0.5, 1.0]);
    let dirs = [Vec3::new(0.3, -0.5, 0.8), Vec3::new(1.0, 1.0, 1.0), Vec3::new(-1.0, 0.02, -0.4), Vec3::new(0.0, -1.0, 0.0)];
    let mut worst = 0.0f64;
    for d in dirs {
        let r_dir = d.normalize();
        for &roughness in &light.level_roughness {
            let rough = roughness as f64;
            let w = (4.0 * rough * rough).max(0.02);
            let num = sphere_integral(r_dir, w, 1200, 96, |l| smooth_light(l).as_dvec3() * lobe(l, r_dir, rough));
            let den = sphere_integral(r_dir, w, 1200, 96, |l| DVec3::splat(lobe(l, r_dir, rough)));
            let reference = num / den.x;
            let got = light.specular(r_dir, roughness);
            let err = rel_err(got, reference);
            println!("specular r={roughness} dir={r_dir}: {got} vs brute force {reference} (rel {err:.2e})");
            worst = worst.max(err);
            assert!(err < 0.01, "specular r={roughness} dir={r_dir}: {got} vs {reference}");
        }
        let irr = sphere_integral(r_dir, 1.0, 400, 96, |l| smooth_light(l).as_dvec3() * (l.dot(r_dir).max(0.0) as f64)) / PI;
        let got = light.diffuse(r_dir);
        let err = rel_err(got, irr);
        println!("diffuse n={r_dir}: {got} vs brute force {irr} (rel {err:.2e})");
        assert!(err < 0.01, "diffuse n={r_dir}: {got} vs {irr}");
    }
    println!("worst specular relative error {worst:.2e}");
}

#[test]
fn sharp_light_is_blurred_by_the_right_amount() {
    // A small bright patch seen by the roughness-0.08 and the 0.5 level: compare with brute force
    // over the nearest-texel function (what the cube map holds), so only the filter is tested.
    let res = 64;
    let bright = Vec3::new(0.3, 0.2, 1.0).normalize();
    let base = CubeMap::from_fn(res, |d| if d.dot(bright) > 0.97 { Vec3::splat(10.0) } else { Vec3::splat(0.1) });
    for mass in [0.95f32, 0.999] {
        let light = SplitSumLight::with_options(&base, PrefilterOptions { kernel_mass: mass, texels_per_core: 4.0 });
        for (level, &roughness) in light.level_roughness.iter().enumerate().take(2) {
            let r_dir = (bright + Vec3::new(0.0, 0.15, 0.0)).normalize();
            let rough = roughness as f64;
            let w = (4.0 * rough * rough).max(0.02);
            let num = sphere_integral(r_dir, w, 2000, 256, |l| base.lookup_nearest(l).as_dvec3() * lobe(l, r_dir, rough));
            let den = sphere_integral(r_dir, w, 2000, 256, |l| DVec3::splat(lobe(l, r_dir, rough)));
            let reference = num / den.x;
            let got = light.specular[level].lookup(r_dir);
            let err = rel_err(got, reference);
            println!("mass {mass} level {level} (r={roughness}): {got} vs {reference} (rel {err:.2e})");
            assert!(err < 0.03, "{got} vs {reference}");
        }
    }
}

/// (A, B) by brute-force quadrature of the formulas of docs/model.md (*BRDF*), written out again here in f64
/// (clamped cosines, height-correlated G), over the hemisphere around the mirror direction.
fn brute_force_ab(nov: f64, roughness: f64) -> (f64, f64) {
    let r = roughness.clamp(0.08, 1.0);
    let a2 = r.powi(4);
    let clamp = |c: f64| c.clamp(1e-4, 1.0 - 1e-4);
    let lambda = |c: f64| {
        let c = clamp(c);
        0.5 * ((1.0 + a2 * (1.0 - c * c) / (c * c)).sqrt() - 1.0)
    };
    let nov = nov.max(1e-4);
    let wo = DVec3::new((1.0 - nov * nov).sqrt(), 0.0, nov);
    let mirror = DVec3::new(-wo.x, 0.0, wo.z);
    let integrand = |l: Vec3| {
        let l = l.as_dvec3();
        if l.z <= 0.0 {
            return DVec3::ZERO;
        }
        let h = (wo + l).normalize();
        let nh = h.z.clamp(0.0, 1.0);
        let d = a2 / (PI * (nh * nh * (a2 - 1.0) + 1.0).powi(2));
        let g = 1.0 / (1.0 + lambda(wo.z) + lambda(l.z));
        let f = d * g / (4.0 * clamp(wo.z));
        let fc = (1.0 - clamp(wo.dot(h))).powi(5);
        DVec3::new(f * (1.0 - fc), f * fc, 0.0)
    };
    let w = (4.0 * r * r).max(0.02);
    let s = sphere_integral(mirror.as_vec3(), w, 3000, 512, integrand);
    (s.x, s.y)
}

#[test]
fn brdf_lut_matches_brute_force_quadrature() {
    let t = Instant::now();
    let lut = BrdfLut::compute(32, 256);
    println!("BrdfLut::compute(32, 256): {:.1} ms", t.elapsed().as_secs_f64() * 1e3);
    let mut worst = 0.0f64;
    for (i, j) in [(0, 16), (2, 2), (5, 30), (10, 10), (16, 0), (16, 25), (31, 31), (24, 4), (8, 1)] {
        let (nov, rough) = ((j as f64 + 0.5) / 32.0, (i as f64 + 0.5) / 32.0);
        let (a, b) = brute_force_ab(nov, rough);
        let (la, lb) = lut.data[i * 32 + j];
        let err = ((la as f64 - a).abs()).max((lb as f64 - b).abs());
        println!("n·v={nov:.3} r={rough:.3}: LUT ({la:.5}, {lb:.5}) brute force ({a:.5}, {b:.5}) |Δ| {err:.1e}");
        worst = worst.max(err);
        assert!(err < 5e-3, "n·v={nov} r={rough}: ({la}, {lb}) vs ({a}, {b})");
    }
    println!("worst |Δ| = {worst:.1e}");
}

#[test]
fn sun_texel_and_degenerate_inputs_stay_finite() {
    let mut base = CubeMap::constant(64, Vec3::splat(0.05));
    let sun = base.texel_index(2, 7, 20);
    base.data[sun] = Vec3::new(1e5, 8e4, 6e4);
    let light = SplitSumLight::new(&base);
    let sun_dir = base.texel_dir(2, 7, 20);
    for level in &light.specular {
        assert!(level.data.iter().all(|v| v.is_finite() && v.min_element() >= 0.0));
    }
    assert!(light.diffuse.data.iter().all(|v| v.is_finite() && v.min_element() >= 0.0));
    for d in [sun_dir, -sun_dir, Vec3::ZERO, Vec3::new(f32::NAN, 0.0, 1.0), Vec3::new(1e30, -1e30, 3.0)] {
        for r in [0.0f32, 0.08, 0.3, 1.0, 5.0, f32::NAN] {
            let v = light.specular(d, r);
            assert!(v.is_finite() && v.min_element() >= 0.0, "specular({d}, {r}) = {v}");
        }
        assert!(light.diffuse(d).is_finite());
    }
    // The sharpest level sees the sun at full strength; rougher levels spread it out.
    assert!(light.specular(sun_dir, 0.08).x > light.specular(sun_dir, 0.5).x);
    assert!(light.specular(sun_dir, 0.5).x > light.specular(sun_dir, 1.0).x);
    let lut = BrdfLut::compute(16, 64);
    for nov in [0.0f32, 1e-6, 0.5, 1.0, f32::NAN] {
        for r in [0.0f32, 0.08, 1.0, 3.0, f32::NAN] {
            let (a, b) = lut.lookup(nov, r);
            assert!(a.is_finite() && b.is_finite() && a >= 0.0 && b >= 0.0, "lut({nov}, {r}) = ({a}, {b})");
        }
    }
}

/// Prefilter cost at the sizes the pipeline may use; run with `--ignored --nocapture`.
#[test]
#[ignore]
fn measure_prefilter_time() {
    for res in [128usize, 256, 512] {
        let base = CubeMap::from_fn(res, smooth_light);
        for mass in [0.9f32, 0.95, 0.99] {
            let t = Instant::now();
            let light = SplitSumLight::with_options(&base, PrefilterOptions { kernel_mass: mass, texels_per_core: 4.0 });
            println!("6x{res}² base, kernel mass {mass}: {} levels in {:.3} s", light.specular.len(), t.elapsed().as_secs_f64());
        }
    }
    for (size, samples) in [(32usize, 256u32), (64, 512), (128, 1024)] {
        let t = Instant::now();
        let _ = BrdfLut::compute(size, samples);
        println!("BrdfLut::compute({size}, {samples}): {:.1} ms", t.elapsed().as_secs_f64() * 1e3);
    }
}

/// Per-level prefilter cost for a 6×512² base; run with `--ignored --nocapture`.
#[test]
#[ignore]
fn measure_prefilter_levels_512() {
    use reconstruct::light::prefilter::{level_roughness, mip_chain, prefilter_specular};
    let chain = mip_chain(&CubeMap::from_fn(512, smooth_light));
    let rough = level_roughness(chain.len());
    for (k, level) in chain.iter().enumerate() {
        for src in &chain[k..] {
            let t = Instant::now();
            let _ = prefilter_specular(src, level.res, rough[k], 0.95);
            println!("level {k} ({}², r={:.3}) from {}²: {:.3} s", level.res, rough[k], src.res, t.elapsed().as_secs_f64());
            if t.elapsed().as_secs_f64() < 0.05 {
                break;
            }
        }
    }
}

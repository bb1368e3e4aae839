//! Physics of the two shading modes: Monte Carlo converges to a brute-force integral, split-sum and
//! MC agree under a constant light (white furnace), and hard cases stay finite.

use glam::{Vec2, Vec3};
use reconstruct::geometry::bvh::Bvh;
use reconstruct::geometry::Mesh;
use reconstruct::image::Image;
use reconstruct::light::sampler::LightSampler;
use reconstruct::light::CubeMap;
use reconstruct::material::brdf;
use reconstruct::material::SurfaceParams;
use reconstruct::math::Frame;
use reconstruct::render::effects::Effects;
use reconstruct::render::gbuffer::Surfel;
use reconstruct::render::montecarlo::{shade_point, McSettings, TraceScene};
use reconstruct::render::splitsum;
use reconstruct::render::view::PreparedLight;
use reconstruct::rng::Sampler;

/// A smooth, strongly varying lat-long light (a bright lobe plus a gradient).
fn smooth_light(w: usize, h: usize) -> Image {
    let mut img = Image::new(w, h, 3);
    for y in 0..h {
        for x in 0..w {
            let d = reconstruct::light::latlong::dir_from_uv((x as f32 + 0.5) / w as f32, (y as f32 + 0.5) / h as f32);
            let lobe = (3.0 * (d.dot(Vec3::new(0.5, 0.3, 0.8).normalize()) - 1.0)).exp() * 4.0;
            img.set_rgb(y * w + x, Vec3::new(0.3 + 0.2 * d.x, 0.4, 0.5 - 0.2 * d.y) + Vec3::splat(lobe));
        }
    }
    img
}

/// A mesh far away from the shading point: nothing occludes it.
fn far_triangle() -> Mesh {
    let mut m = Mesh::default();
    m.positions = vec![Vec3::new(100.0, 100.0, -100.0), Vec3::new(100.1, 100.0, -100.0), Vec3::new(100.0, 100.1, -100.0)];
    m.normals = vec![Vec3::Z; 3];
    m.uvs = vec![Vec2::ZERO; 3];
    m.triangles = vec![[0, 1, 2]];
    m.triangle_part = vec![0];
    m
}

fn surfel(normal: Vec3) -> Surfel {
    Surfel { position: Vec3::ZERO, normal, geo_normal: normal, uv: Vec2::ZERO, triangle: 0, bary: Vec2::ZERO, depth: 1.0 }
}

/// ∫ f(wo, wi) L(wi) dwi over the hemisphere by a fine midpoint rule in (cos θ, φ).
fn brute_force(n: Vec3, wo: Vec3, p: &SurfaceParams, light: &LightSampler) -> Vec3 {
    let frame = Frame::from_normal(n);
    let wo_l = frame.to_local(wo);
    let (nt, np) = (400, 800);
    let mut sum = Vec3::ZERO;
    for i in 0..nt {
        let cos_t = (i as f32 + 0.5) / nt as f32;
        let sin_t = (1.0 - cos_t * cos_t).sqrt();
        for j in 0..np {
            let phi = 2.0 * std::f32::consts::PI * (j as f32 + 0.5) / np as f32;
            let wi_l = Vec3::new(sin_t * phi.cos(), sin_t * phi.sin(), cos_t);
            let f = brdf::eval(p, wo_l, wi_l);
            sum += (f.diffuse + f.specular) * light.radiance(frame.to_world(wi_l));
        }
    }
    sum * (2.0 * std::f32::consts::PI / (nt * np) as f32)
}

#[test]
fn monte_carlo_converges_to_brute_force_integral() {
    let cube = CubeMap::from_latlong(&smooth_light(64, 32), 32);
    let light = LightSampler::new(&cube);
    let mesh = far_triangle();
    let bvh = Bvh::build(&mesh);
    let settings = McSettings { spp: 8192, seed: 3, effects: Effects::DIRECT, ray_epsilon: 1e-4 };
    for (k, (rough, metal)) in [(0.3f32, 0.0f32), (0.6, 0.0), (0.4, 1.0)].into_iter().enumerate() {
        let p = SurfaceParams { kd: Vec3::new(0.7, 0.5, 0.3), roughness: rough, metallic: metal };
        let n = Vec3::new(0.2, -0.1, 1.0).normalize();
        let wo = Vec3::new(-0.5, 0.3, 0.8).normalize();
        let mut rng = Sampler::new(11, k as u64);
        let (d, s, _) = shade_point(&surfel(n), wo, &p, &light, &TraceScene { mesh: &mesh, bvh: &bvh, materials: &mesh }, &settings, &mut rng);
        let mc = p.kd * (1.0 - p.metallic) * d + s;
        let reference = brute_force(n, wo, &p, &light);
        let rel = ((mc - reference).abs() / reference.max(Vec3::splat(1e-3))).max_element();
        println!("roughness {rough} metallic {metal}: MC {mc:?} vs brute force {reference:?}, max rel err {rel:.4}");
        assert!(rel < 0.02, "MC {mc:?} vs brute force {reference:?}");
    }
}

#[test]
fn white_furnace_both_modes() {
    // Constant light L = 1, white Lambert (metallic 0, specular off): outgoing radiance = 1 exactly.
    let cube = CubeMap::constant(16, Vec3::ONE);
    let prepared = PreparedLight::new(cube);
    let mesh = far_triangle();
    let bvh = Bvh::build(&mesh);
    let p = SurfaceParams { kd: Vec3::ONE, roughness: 0.5, metallic: 0.0 };
    let diffuse_only = Effects { shadows: false, specular: false, indirect_bounces: 0 };
    let n = Vec3::new(0.3, 0.1, 1.0).normalize();
    let wo = Vec3::new(0.1, 0.4, 0.9).normalize();
    let (ss, lut) = prepared.split_sum();
    let (d, s) = splitsum::shade_point(n, wo, &p, ss, lut, diffuse_only);
    assert!(((d + s) - Vec3::ONE).abs().max_element() < 0.01, "split-sum furnace {:?}", d + s);
    let settings = McSettings { spp: 1024, seed: 1, effects: diffuse_only, ray_epsilon: 1e-4 };
    let (d, s, rays) = shade_point(&surfel(n), wo, &p, prepared.sampler(), &TraceScene { mesh: &mesh, bvh: &bvh, materials: &mesh }, &settings, &mut Sampler::new(0, 0));
    assert!(((d + s) - Vec3::ONE).abs().max_element() < 0.01, "MC furnace {:?}", d + s);
    assert_eq!(rays, 0, "shadows off must trace no shadow rays");
}

#[test]
fn split_sum_matches_monte_carlo_under_constant_light_with_specular() {
    // Under a constant light split-sum is exact up to the LUT and prefilter resolution: both modes
    // compute ∫ f·cos for the same BRDF.
    let prepared = PreparedLight::new(CubeMap::constant(32, Vec3::splat(0.8)));
    let mesh = far_triangle();
    let bvh = Bvh::build(&mesh);
    let (ss, lut) = prepared.split_sum();
    let settings = McSettings { spp: 4096, seed: 5, effects: Effects { shadows: false, specular: true, indirect_bounces: 0 }, ray_epsilon: 1e-4 };
    for (rough, metal, nov) in [(0.1f32, 0.0f32, 0.9f32), (0.5, 0.0, 0.5), (0.3, 1.0, 0.7), (1.0, 0.5, 0.2)] {
        let p = SurfaceParams { kd: Vec3::new(0.6, 0.4, 0.2), roughness: rough, metallic: metal };
        let n = Vec3::Z;
        let wo = Vec3::new((1.0 - nov * nov).sqrt(), 0.0, nov);
        let (d, s) = splitsum::shade_point(n, wo, &p, ss, lut, settings.effects);
        let (md, msp, _) = shade_point(&surfel(n), wo, &p, prepared.sampler(), &TraceScene { mesh: &mesh, bvh: &bvh, materials: &mesh }, &settings, &mut Sampler::new(2, 0));
        let mc = p.kd * (1.0 - metal) * md + msp;
        let rel = (((d + s) - mc).abs() / mc.max(Vec3::splat(1e-3))).max_element();
        println!("r {rough} m {metal} n·v {nov}: split-sum {:?} MC {mc:?} rel {rel:.4}", d + s);
        assert!(rel < 0.03, "split-sum {:?} vs MC {mc:?}", d + s);
    }
}

#[test]
fn hard_cases_stay_finite() {
    // A 1e5 sun texel in an otherwise dim probe.
    let mut probe = Image::filled(32, 16, &[0.05, 0.05, 0.05]);
    probe.set_rgb(5 * 32 + 3, Vec3::splat(1e5));
    let prepared = PreparedLight::new(CubeMap::from_latlong(&probe, 32));
    let mesh = far_triangle();
    let bvh = Bvh::build(&mesh);
    let (ss, lut) = prepared.split_sum();
    let normals = [Vec3::Z, Vec3::new(1.0, 0.0, 1e-6).normalize()];
    // wo nearly tangent, exactly tangent, and below the shading normal (back-facing normal).
    let wos = [Vec3::Z, Vec3::new(1.0, 0.0, 1e-5).normalize(), Vec3::X, Vec3::new(0.3, 0.0, -0.95).normalize()];
    for rough in [0.0f32, 0.08, 0.5, 1.0, 1.7] {
        for metal in [0.0f32, 1.0] {
            for kd in [Vec3::ZERO, Vec3::ONE] {
                let p = SurfaceParams { kd, roughness: rough, metallic: metal };
                for n in normals {
                    for wo in wos {
                        let (d, s) = splitsum::shade_point(n, wo, &p, ss, lut, Effects::DIRECT);
                        assert!(d.is_finite() && s.is_finite(), "split-sum r {rough} n {n:?} wo {wo:?}");
                        let settings = McSettings { spp: 8, seed: 1, effects: Effects::DIRECT, ray_epsilon: 1e-4 };
                        let (d, s, _) = shade_point(&surfel(n), wo, &p, prepared.sampler(), &TraceScene { mesh: &mesh, bvh: &bvh, materials: &mesh }, &settings, &mut Sampler::new(1, 2));
                        assert!(d.is_finite() && s.is_finite(), "MC r {rough} n {n:?} wo {wo:?}: {d:?} {s:?}");
                    }
                }
            }
        }
    }
}

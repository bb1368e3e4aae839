//! Physics of the two shading modes: Monte Carlo converges to a brute-force integral, split-sum and
//! MC agree under a constant light (white furnace), interreflection conserves energy (a white
//! concave object in a white furnace disappears), and hard cases stay finite.

use glam::{Quat, Vec2, Vec3};
use reconstruct::geometry::bvh::Bvh;
use reconstruct::geometry::primitives::MeshBuilder;
use reconstruct::geometry::Mesh;
use reconstruct::image::Image;
use reconstruct::light::sampler::LightSampler;
use reconstruct::light::CubeMap;
use reconstruct::material::brdf;
use reconstruct::material::{BaseColor, PartMaterial, Scalar, SurfaceParams};
use reconstruct::math::Frame;
use reconstruct::render::effects::Effects;
use reconstruct::render::gbuffer::Surfel;
use reconstruct::render::gbuffer::GBuffer;
use reconstruct::render::montecarlo::{shade, shade_point, McSettings, TraceScene};
use reconstruct::render::splitsum;
use reconstruct::render::view::PreparedLight;
use reconstruct::rng::Sampler;
use reconstruct::scene::Camera;

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
    Mesh {
        positions: vec![Vec3::new(100.0, 100.0, -100.0), Vec3::new(100.1, 100.0, -100.0), Vec3::new(100.0, 100.1, -100.0)],
        normals: vec![Vec3::Z; 3],
        uvs: vec![Vec2::ZERO; 3],
        triangles: vec![[0, 1, 2]],
        triangle_part: vec![0],
        ..Mesh::default()
    }
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
    assert_eq!(rays.total(), 0, "shadows off must trace no shadow rays");
}

/// Per covered pixel of a view of a white Lambert ball resting in a white bowl-like dip (a ball on
/// a disc with a rim), under constant light 1: outgoing radiance, Monte Carlo with `bounces`.
fn furnace_radiance(bounces: u32, spp: u32) -> Vec<f32> {
    let mut b = MeshBuilder::new();
    let white = b.part(PartMaterial { name: "white".into(), base_color: BaseColor::Constant(Vec3::ONE), roughness: Scalar::Constant(1.0), metallic: Scalar::Constant(0.0) });
    b.ellipsoid(white, Vec3::new(0.0, 0.0, 0.4), Vec3::splat(0.4), Quat::IDENTITY, 32, 16);
    b.cylinder(white, Vec2::ZERO, 1.0, -0.1, 0.0, 48);
    for k in 0..6 {
        let a = k as f32 * std::f32::consts::TAU / 6.0;
        b.ellipsoid(white, Vec3::new(0.75 * a.cos(), 0.75 * a.sin(), 0.15), Vec3::new(0.2, 0.2, 0.3), Quat::IDENTITY, 16, 8);
    }
    let mesh = b.build();
    let bvh = Bvh::build(&mesh);
    let camera = Camera::look_at(Vec3::new(1.6, 0.9, 1.5), Vec3::new(0.0, 0.0, 0.2), Vec3::Z, 0.9, 24, 24);
    let gbuf = GBuffer::trace(&mesh, &bvh, &camera);
    let params = gbuf.material_params(&mesh);
    let light = PreparedLight::new(CubeMap::constant(8, Vec3::ONE));
    let settings = McSettings { spp, seed: 4, effects: Effects { shadows: true, specular: false, indirect_bounces: bounces }, ray_epsilon: 1e-4 };
    let scene = TraceScene { mesh: &mesh, bvh: &bvh, materials: &mesh };
    let out = shade(&gbuf, &params, light.sampler(), &scene, &settings, 0).radiance(&params);
    out.iter().zip(&gbuf.surfels).filter(|(_, s)| s.is_some()).map(|(c, _)| c.x).collect()
}

/// The pixels where direct light is darkest (a tenth of them: the ball's contact, between the
/// bumps), chosen on `direct` so the noise of the values averaged does not pick them.
fn darkest_tenth(direct: &[f32]) -> Vec<usize> {
    let mut order: Vec<usize> = (0..direct.len()).collect();
    order.sort_by(|&a, &b| direct[a].total_cmp(&direct[b]));
    order.truncate((direct.len() / 10).max(1));
    order
}

#[test]
fn white_furnace_with_interreflection_conserves_energy() {
    // A white object in a white furnace reflects every bit of light it receives, from the sky or
    // from itself: with enough bounces its radiance is 1 everywhere, concavities included. Direct
    // light alone leaves the occluded parts dark, which shows the test can fail.
    let direct = furnace_radiance(0, 64);
    let bounced = furnace_radiance(12, 64);
    let mean = |v: &[f32]| v.iter().sum::<f32>() / v.len() as f32;
    let dark = darkest_tenth(&direct);
    let mean_at = |v: &[f32]| dark.iter().map(|&i| v[i]).sum::<f32>() / dark.len() as f32;
    let (dark_direct, dark_bounced) = (mean_at(&direct), mean_at(&bounced));
    println!(
        "{} pixels: direct mean {:.4}, darkest tenth {dark_direct:.4}; 12 bounces mean {:.4}, darkest tenth {dark_bounced:.4}",
        bounced.len(),
        mean(&direct),
        mean(&bounced)
    );
    assert!(bounced.len() > 200, "too few covered pixels: {}", bounced.len());
    assert!(dark_direct < 0.85, "the scene is not concave enough to test anything: {dark_direct}");
    assert!((mean(&bounced) - 1.0).abs() < 0.01, "mean radiance {} with interreflection", mean(&bounced));
    assert!(dark_bounced > 0.97, "occluded pixels reach only {dark_bounced} with interreflection");
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
                        for effects in [Effects::DIRECT, Effects::with_bounces(3)] {
                            let settings = McSettings { spp: 8, seed: 1, effects, ray_epsilon: 1e-4 };
                            let (d, s, _) = shade_point(&surfel(n), wo, &p, prepared.sampler(), &TraceScene { mesh: &mesh, bvh: &bvh, materials: &mesh }, &settings, &mut Sampler::new(1, 2));
                            assert!(d.is_finite() && s.is_finite(), "MC r {rough} n {n:?} wo {wo:?} {effects:?}: {d:?} {s:?}");
                        }
                    }
                }
            }
        }
    }
}

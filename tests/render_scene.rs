//! Whole-view rendering: finite output on hard geometry, effects chosen per scene, reproducibility.

use std::sync::Arc;

use glam::{Quat, Vec2, Vec3};
use reconstruct::geometry::bvh::Bvh;
use reconstruct::geometry::primitives::MeshBuilder;
use reconstruct::geometry::Mesh;
use reconstruct::image::Image;
use reconstruct::light::CubeMap;
use reconstruct::material::{BaseColor, PartMaterial, Scalar};
use reconstruct::render::effects::{choose, interreflection_share, visible_self_occlusion, Effects, DEFAULT_INDIRECT_BOUNCES};
use reconstruct::scene::{EffectSwitches, Switch};
use reconstruct::render::gbuffer::GBuffer;
use reconstruct::render::view::{render_view, PreparedLight, RenderSettings, ShadingMode};
use reconstruct::scene::Camera;

fn material(name: &str, roughness: f32, metallic: f32) -> PartMaterial {
    PartMaterial::constant(name, Vec3::new(0.6, 0.5, 0.4), roughness, metallic)
}

/// A sphere resting on a slab: the slab is shadowed by the sphere.
fn sphere_on_slab(sphere_roughness: f32) -> Mesh {
    let mut b = MeshBuilder::new();
    let slab = b.part(material("slab", 0.95, 0.0));
    b.cylinder(slab, Vec2::ZERO, 1.5, -0.1, 0.0, 64);
    let ball = b.part(material("ball", sphere_roughness, 0.0));
    b.ellipsoid(ball, Vec3::new(0.0, 0.0, 0.5), Vec3::splat(0.5), Quat::IDENTITY, 32, 16);
    b.build()
}

fn lone_sphere() -> Mesh {
    let mut b = MeshBuilder::new();
    let ball = b.part(material("ball", 0.95, 0.0));
    b.ellipsoid(ball, Vec3::ZERO, Vec3::splat(0.5), Quat::IDENTITY, 32, 16);
    b.build()
}

fn cameras() -> Vec<Camera> {
    [Vec3::new(3.0, -2.0, 2.5), Vec3::new(-2.0, 3.0, 1.5)]
        .into_iter()
        .map(|eye| Camera::look_at(eye, Vec3::new(0.0, 0.0, 0.2), Vec3::Z, 0.7, 48, 48))
        .collect()
}

#[test]
fn auto_effects_follow_the_scene() {
    let switches = EffectSwitches::default();
    let occluding = sphere_on_slab(0.95);
    let bvh = Bvh::build(&occluding);
    let views: Vec<GBuffer> = cameras().iter().map(|c| GBuffer::trace(&occluding, &bvh, c)).collect();
    let choice = choose(switches, &occluding, &bvh, &views, true);
    println!("{choice}");
    assert!(choice.effects.shadows, "a sphere on a slab casts shadows");
    assert!(!choice.effects.specular, "every part has roughness ≥ 0.9");

    let lone = lone_sphere();
    let bvh = Bvh::build(&lone);
    let views: Vec<GBuffer> = cameras().iter().map(|c| GBuffer::trace(&lone, &bvh, c)).collect();
    let choice = choose(switches, &lone, &bvh, &views, true);
    println!("{choice}");
    assert!(!choice.effects.shadows, "a convex object cannot shadow itself");

    let glossy = sphere_on_slab(0.2);
    let choice = choose(switches, &glossy, &Bvh::build(&glossy), &[], true);
    assert!(choice.effects.specular);
    let forced = EffectSwitches { shadows: Switch::Off, specular: Switch::On, ..Default::default() };
    let choice = choose(forced, &occluding, &Bvh::build(&occluding), &[], true);
    assert_eq!(choice.effects, Effects { shadows: false, specular: true, indirect_bounces: 0 });
}

#[test]
fn auto_interreflection_weighs_the_blocked_sky_by_the_albedo_blocking_it() {
    let occluding = sphere_on_slab(0.95);
    let bvh = Bvh::build(&occluding);
    let views: Vec<GBuffer> = cameras().iter().map(|c| GBuffer::trace(&occluding, &bvh, c)).collect();
    let occlusion = visible_self_occlusion(&bvh, &views, 4000, 2);
    // Same rays: unknown materials count every blocker as white; known ones by their albedo
    // (both parts have kd (0.6, 0.5, 0.4), luminance 0.5130).
    let unknown = interreflection_share(&occluding, &bvh, None, &views, 4000, 2);
    let known = interreflection_share(&occluding, &bvh, Some(&occluding), &views, 4000, 2);
    println!("occlusion {occlusion:.4}, share unknown {unknown:.4}, known {known:.4}");
    assert!(occlusion > 0.05, "the scene must occlude itself: {occlusion}");
    assert!((unknown - occlusion).abs() < 1e-6);
    assert!((known - 0.5130 * occlusion).abs() < 2e-3 * occlusion, "{known} vs {}", 0.5130 * occlusion);
    let choice = choose(EffectSwitches::default(), &occluding, &bvh, &views, true);
    println!("{choice}");
    assert_eq!(choice.effects.indirect_bounces, DEFAULT_INDIRECT_BOUNCES, "{:.1}% comes back from the object", 100.0 * known);

    // A convex object reflects nothing onto itself; interreflection forced on brings shadows.
    let lone = lone_sphere();
    let lone_bvh = Bvh::build(&lone);
    let lone_views: Vec<GBuffer> = cameras().iter().map(|c| GBuffer::trace(&lone, &lone_bvh, c)).collect();
    assert_eq!(interreflection_share(&lone, &lone_bvh, None, &lone_views, 4000, 2), 0.0);
    assert_eq!(choose(EffectSwitches::default(), &lone, &lone_bvh, &lone_views, true).effects.indirect_bounces, 0);
    let forced = EffectSwitches { shadows: Switch::Off, interreflection: Switch::On, bounces: Some(2), ..Default::default() };
    let choice = choose(forced, &lone, &lone_bvh, &lone_views, true);
    assert_eq!(choice.effects, Effects { shadows: true, specular: false, indirect_bounces: 2 });
    assert!(choice.reasons.iter().any(|r| r.contains("interreflection needs them")), "{choice}");
}

#[test]
fn shadows_darken_the_occluded_slab() {
    let mesh = sphere_on_slab(0.95);
    let bvh = Bvh::build(&mesh);
    // Light from straight above: the sphere's shadow falls under it.
    let mut sky = Image::filled(64, 32, &[0.02, 0.02, 0.02]);
    for x in 0..64 {
        sky.set_rgb(x, Vec3::splat(200.0));
    }
    let light = PreparedLight::new(CubeMap::from_latlong(&sky, 32));
    // Seen from the side-above, so the shadow under the sphere is visible.
    let cam = Camera::look_at(Vec3::new(2.5, -2.5, 2.5), Vec3::ZERO, Vec3::Z, 0.9, 48, 48);
    let settings = |shadows| RenderSettings { mode: ShadingMode::MonteCarlo, spp: 16, supersample: 1, seed: 1, effects: Effects { shadows, specular: false, indirect_bounces: 0 } };
    let with = render_view(&mesh, &bvh, &light, &cam, &settings(true));
    let without = render_view(&mesh, &bvh, &light, &cam, &settings(false));
    // The light from straight above puts a shadow under the sphere: total brightness drops.
    let mean = |img: &Image| img.data.chunks_exact(4).map(|p| p[0] * p[3]).sum::<f32>();
    assert!(mean(&with) < 0.98 * mean(&without), "shadows must remove light: {} vs {}", mean(&with), mean(&without));
}

#[test]
fn degenerate_geometry_and_extreme_materials_render_finite() {
    let mut mesh = sphere_on_slab(0.08);
    // Degenerate triangles: repeated vertex and collinear vertices, plus a zero normal.
    let base = mesh.positions.len() as u32;
    mesh.positions.extend([Vec3::new(0.0, 0.0, 1.2), Vec3::new(0.0, 0.0, 1.2), Vec3::new(0.5, 0.5, 1.2), Vec3::new(1.0, 1.0, 1.2)]);
    mesh.normals.extend([Vec3::Z, Vec3::ZERO, Vec3::Z, Vec3::Z]);
    mesh.uvs.extend([Vec2::ZERO; 4]);
    mesh.triangles.extend([[base, base + 1, base + 2], [base, base + 2, base + 3]]);
    mesh.triangle_part.extend([0, 0]);
    mesh.materials[0].roughness = Scalar::Constant(1.7); // above 1: clamped
    mesh.materials[1].metallic = Scalar::Constant(1.0);
    mesh.materials[1].base_color = BaseColor::Texture(Arc::new(Image::filled(4, 4, &[0.0, 0.0, 0.0])));
    let bvh = Bvh::build(&mesh);
    let mut probe = Image::filled(32, 16, &[0.1, 0.1, 0.1]);
    probe.set_rgb(4 * 32 + 7, Vec3::splat(1e5));
    let light = PreparedLight::new(CubeMap::from_latlong(&probe, 32));
    for cam in cameras() {
        for mode in [ShadingMode::SplitSum, ShadingMode::MonteCarlo] {
            let settings = RenderSettings { mode, spp: 4, supersample: 1, seed: 2, effects: Effects::DIRECT };
            let img = render_view(&mesh, &bvh, &light, &cam, &settings);
            assert!(img.data.iter().all(|v| v.is_finite()), "{mode:?} produced NaN/Inf");
        }
    }
}

#[test]
fn renders_are_reproducible_for_a_seed() {
    let mesh = sphere_on_slab(0.3);
    let bvh = Bvh::build(&mesh);
    let light = PreparedLight::new(CubeMap::from_latlong(&Image::filled(32, 16, &[0.5, 0.4, 0.3]), 16));
    let cam = &cameras()[0];
    let s = RenderSettings { mode: ShadingMode::MonteCarlo, spp: 2, supersample: 1, seed: 9, effects: Effects::DIRECT };
    let a = render_view(&mesh, &bvh, &light, cam, &s);
    let b = render_view(&mesh, &bvh, &light, cam, &s);
    let c = render_view(&mesh, &bvh, &light, cam, &RenderSettings { seed: 10, ..s });
    assert_eq!(a, b);
    assert_ne!(a, c);
}

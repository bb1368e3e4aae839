//! The learned normal map (`material::normal_map`, `--normal-map`): what the renderer does with it,
//! against a reference that needs no normal map, and its files.
//!
//! - On a flat plane every MikkTSpace frame is the same, so a constant map m must render exactly
//!   like the same plane whose vertex normals are m turned into world space by hand (T = ±x along
//!   u, B = +y along v, N = +z). Checked for a tilt along u, along v, and with u mirrored (the
//!   frame's handedness flips, the tangent turns round).
//! - Saved textures with a map load back for the same mesh with the same frames; the exported
//!   OBJ/MTL and glTF name the map where Blender and glTF viewers look for it.

use std::sync::Arc;

use glam::{Vec2, Vec3};
use reconstruct::fit::export::write_model;
use reconstruct::geometry::bvh::Bvh;
use reconstruct::geometry::tangents::corner_tangents;
use reconstruct::geometry::{Mesh, Part};
use reconstruct::light::CubeMap;
use reconstruct::material::normal_map::NormalMap;
use reconstruct::material::texture_maps::MaterialTextures;
use reconstruct::material::{BaseColor, PartMaterial, Scalar};
use reconstruct::render::effects::Effects;
use reconstruct::render::view::{render_view_with, PreparedLight, RenderSettings, ShadingMode};
use reconstruct::scene::Camera;

/// A 2×2 square in the xy plane facing +z, as an n×n grid, u along +x (or −x when `mirror_u`),
/// v along +y, every vertex normal `normal`.
fn plane(n: usize, mirror_u: bool, normal: Vec3) -> Mesh {
    let mut m = Mesh::default();
    for j in 0..=n {
        for i in 0..=n {
            let (s, t) = (i as f32 / n as f32, j as f32 / n as f32);
            m.positions.push(Vec3::new(2.0 * s - 1.0, 2.0 * t - 1.0, 0.0));
            m.normals.push(normal);
            m.uvs.push(Vec2::new(if mirror_u { 1.0 - s } else { s }, t));
        }
    }
    let idx = |i: usize, j: usize| (j * (n + 1) + i) as u32;
    for j in 0..n {
        for i in 0..n {
            m.triangles.push([idx(i, j), idx(i + 1, j), idx(i + 1, j + 1)]);
            m.triangles.push([idx(i, j), idx(i + 1, j + 1), idx(i, j + 1)]);
        }
    }
    m.triangle_part = vec![0; m.triangles.len()];
    m.parts = vec![Part { name: "plane".into(), material: 0, has_uv: true }];
    m.materials = vec![PartMaterial { name: "m".into(), base_color: BaseColor::Constant(Vec3::splat(0.6)), roughness: Scalar::Constant(0.35), metallic: Scalar::Constant(0.0) }];
    m
}

fn textures() -> MaterialTextures {
    MaterialTextures::constant(16, Vec3::new(0.6, 0.5, 0.4), 0.35, 0.1)
}

fn with_map(mesh: &Mesh, m: Vec3) -> MaterialTextures {
    let mut t = textures();
    let mut map = NormalMap::flat(16, corner_tangents(mesh).expect("frames").into());
    map.map.data.chunks_exact_mut(3).for_each(|c| c.copy_from_slice(&m.to_array()));
    t.normal = Some(map);
    t
}

fn render(mesh: &Mesh, materials: &MaterialTextures) -> Vec<f32> {
    // A light that changes with direction, so a tilt changes the shading (diffuse and specular).
    let light = PreparedLight::new(CubeMap::from_fn(16, |d| Vec3::new(1.0 + d.x, 1.0 + 0.8 * d.y, 0.6 + 0.5 * d.z).max(Vec3::ZERO) * 1.5));
    let camera = Camera::look_at(Vec3::new(0.3, -0.4, 3.0), Vec3::ZERO, Vec3::Y, 0.8, 24, 24);
    let settings = RenderSettings { mode: ShadingMode::MonteCarlo, spp: 16, supersample: 1, seed: 3, effects: Effects::DIRECT };
    render_view_with(mesh, &Bvh::build(mesh), &light, &camera, &settings, materials).data
}

fn max_difference(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max)
}

#[test]
fn a_constant_map_renders_like_the_vertex_normals_it_stands_for() {
    let theta = 0.5f32;
    let (s, c) = theta.sin_cos();
    let flat = render(&plane(4, false, Vec3::Z), &textures());
    for (mirror_u, m, world) in [
        (false, Vec3::new(s, 0.0, c), Vec3::new(s, 0.0, c)),
        (false, Vec3::new(0.0, s, c), Vec3::new(0.0, s, c)),
        (true, Vec3::new(s, 0.0, c), Vec3::new(-s, 0.0, c)),
        (true, Vec3::new(0.0, s, c), Vec3::new(0.0, s, c)),
    ] {
        let mesh = plane(4, mirror_u, Vec3::Z);
        let mapped = render(&mesh, &with_map(&mesh, m));
        let reference = render(&plane(4, mirror_u, world), &textures());
        let d = max_difference(&mapped, &reference);
        assert!(d < 1e-3, "mirror_u {mirror_u}, m {m}: max difference {d} against normals {world}");
        // The tilt matters: otherwise the check above would prove nothing.
        assert!(max_difference(&mapped, &flat) > 0.05, "mirror_u {mirror_u}, m {m}: the tilt changed nothing");
    }
}

#[test]
fn textures_with_a_map_round_trip_and_the_exports_name_it() {
    let dir = std::env::temp_dir().join(format!("reconstruct-normal-map-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let mesh = plane(3, false, Vec3::Z);
    let mut t = with_map(&mesh, Vec3::new(0.3, -0.2, 0.9).normalize());
    t.normal.as_mut().expect("map").map.data[0..3].copy_from_slice(&Vec3::new(-0.6, 0.0, 0.8).to_array());
    write_model(&dir, &mesh, &t).expect("export");

    let back = MaterialTextures::load_for(&dir, &mesh).expect("load");
    let (a, b) = (t.normal.as_ref().expect("map"), back.normal.as_ref().expect("the map is read back"));
    assert_eq!(a.tangents, b.tangents);
    // 8-bit PNG: each component within one step of 2/255, then renormalised.
    let d = max_difference(&a.map.data, &b.map.data);
    assert!(d < 0.012, "normal map differs by {d} after the round trip");
    assert!(MaterialTextures::load(&dir).expect("kd/ks").normal.is_none());

    let mtl = std::fs::read_to_string(dir.join("model.mtl")).expect("mtl");
    assert!(mtl.contains("map_Bump normal.png"), "{mtl}");
    let gltf: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(dir.join("model.gltf")).expect("gltf")).expect("json");
    let material = &gltf["materials"][0];
    let image_of = |tex: &serde_json::Value| -> String {
        let source = gltf["textures"][tex["index"].as_u64().expect("index") as usize]["source"].as_u64().expect("source");
        gltf["images"][source as usize]["uri"].as_str().expect("uri").to_string()
    };
    assert_eq!(image_of(&material["normalTexture"]), "normal.png");
    assert_eq!(image_of(&material["pbrMetallicRoughness"]["metallicRoughnessTexture"]), "ks.png");
    assert_eq!(image_of(&material["pbrMetallicRoughness"]["baseColorTexture"]), "kd.png");
    // A mesh the map was not learned on has other frames; the same mesh gives the same ones.
    let other = plane(3, true, Vec3::Z);
    let moved: Arc<[_]> = corner_tangents(&other).expect("frames").into();
    assert_ne!(moved, b.tangents);
    let _ = std::fs::remove_dir_all(&dir);
}

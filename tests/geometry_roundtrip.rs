//! Write → load round trips of OBJ/MTL and glTF (.gltf + .bin and .glb): geometry per triangle
//! corner, vertex sharing, UVs (including glTF's flipped v), parts and material factors.

use std::path::PathBuf;
use std::sync::Arc;

use glam::{Mat4, Quat, Vec2, Vec3};
use reconstruct::geometry::gltf_io::{load_gltf, write_gltf};
use reconstruct::geometry::obj::{load_obj, write_obj, MaterialTextureNames};
use reconstruct::geometry::texture_file::save_srgb_texture;
use reconstruct::geometry::{Mesh, Part};
use reconstruct::image::Image;
use reconstruct::material::{BaseColor, PartMaterial, Scalar};

fn tmp_dir(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("reconstruct-rt-{tag}-{}", std::process::id()));
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// A small gradient texture (linear values that survive 8-bit sRGB to about 1e-2).
fn texture() -> Image {
    let mut img = Image::new(8, 4, 3);
    for y in 0..4 {
        for x in 0..8 {
            img.set_rgb(y * 8 + x, Vec3::new(x as f32 / 7.0, y as f32 / 3.0, 0.25));
        }
    }
    img
}

/// Three parts: a bumpy grid with UVs, a tetrahedron without UVs, a second grid sharing the
/// textured material. Vertices are shared within parts, not across.
fn test_mesh() -> Mesh {
    let mut mesh = Mesh::default();
    let add_grid = |mesh: &mut Mesh, offset: Vec3, part: u32| {
        let base = mesh.positions.len() as u32;
        let n = 5;
        for j in 0..n {
            for i in 0..n {
                let (u, v) = (i as f32 / (n - 1) as f32, j as f32 / (n - 1) as f32);
                mesh.positions.push(offset + Vec3::new(u, v, 0.1 * (3.0 * u).sin() * v));
                mesh.uvs.push(Vec2::new(u, 0.3 + 0.6 * v));
            }
        }
        for j in 0..n - 1 {
            for i in 0..n - 1 {
                let a = base + j * n + i;
                mesh.triangles.push([a, a + 1, a + n + 1]);
                mesh.triangles.push([a, a + n + 1, a + n]);
                mesh.triangle_part.extend([part, part]);
            }
        }
    };
    add_grid(&mut mesh, Vec3::ZERO, 0);
    let base = mesh.positions.len() as u32;
    mesh.positions.extend([Vec3::new(2.0, 0.0, 0.0), Vec3::new(3.0, 0.0, 0.0), Vec3::new(2.5, 1.0, 0.0), Vec3::new(2.5, 0.5, 1.0)]);
    mesh.uvs.extend([Vec2::ZERO; 4]);
    for t in [[0, 2, 1], [0, 1, 3], [1, 2, 3], [2, 0, 3]] {
        mesh.triangles.push(t.map(|i| i + base));
        mesh.triangle_part.push(1);
    }
    add_grid(&mut mesh, Vec3::new(0.0, 0.0, -2.0), 2);
    mesh.recompute_normals();
    mesh.parts = vec![
        Part { name: "grid".into(), material: 0, has_uv: true },
        Part { name: "tetra".into(), material: 1, has_uv: false },
        Part { name: "grid2".into(), material: 0, has_uv: true },
    ];
    mesh.materials = vec![
        PartMaterial { name: "textured".into(), base_color: BaseColor::Texture(Arc::new(texture())), roughness: Scalar::Constant(0.35), metallic: Scalar::Constant(0.0) },
        PartMaterial { name: "plain".into(), base_color: BaseColor::Constant(Vec3::new(0.7, 0.2, 0.05)), roughness: Scalar::Constant(0.8), metallic: Scalar::Constant(0.6) },
    ];
    mesh.validate().unwrap();
    mesh
}

/// Same parts, materials, triangle order, corner attributes and vertex sharing.
fn assert_same_mesh(a: &Mesh, b: &Mesh, tex_tol: f32) {
    b.validate().unwrap();
    assert_eq!(a.parts.len(), b.parts.len());
    assert_eq!(a.triangles.len(), b.triangles.len());
    assert_eq!(a.positions.len(), b.positions.len(), "vertex count");
    for (pa, pb) in a.parts.iter().zip(&b.parts) {
        assert_eq!((&pa.name, pa.has_uv), (&pb.name, pb.has_uv));
        let (ma, mb) = (&a.materials[pa.material], &b.materials[pb.material]);
        assert_eq!(ma.name, mb.name);
        assert!((ma.roughness.mean() - mb.roughness.mean()).abs() < 1e-5 && (ma.metallic.mean() - mb.metallic.mean()).abs() < 1e-5, "{}", ma.name);
        match (&ma.base_color, &mb.base_color) {
            (BaseColor::Constant(x), BaseColor::Constant(y)) => assert!((*x - *y).abs().max_element() < 1e-5),
            (BaseColor::Texture(x), BaseColor::Texture(y)) => {
                assert_eq!((x.width, x.height), (y.width, y.height));
                let err = x.data.iter().zip(&y.data).map(|(p, q)| (p - q).abs()).fold(0.0, f32::max);
                assert!(err < tex_tol, "texture error {err}");
            }
            _ => panic!("{}: base colour kind changed", ma.name),
        }
    }
    // Materials shared by parts stay shared.
    assert_eq!(b.parts[0].material, b.parts[2].material);
    assert_eq!(a.triangle_part, b.triangle_part);
    let mut first_seen_a = std::collections::HashMap::new();
    let mut first_seen_b = std::collections::HashMap::new();
    for (ta, tb) in a.triangles.iter().zip(&b.triangles) {
        for (&ia, &ib) in ta.iter().zip(tb) {
            let (ia, ib) = (ia as usize, ib as usize);
            assert!((a.positions[ia] - b.positions[ib]).length() < 1e-6);
            assert!((a.normals[ia] - b.normals[ib]).length() < 1e-5);
            assert!((a.uvs[ia] - b.uvs[ib]).length() < 1e-6, "uv {} vs {}", a.uvs[ia], b.uvs[ib]);
            // Index structure: corners share a vertex in `a` exactly when they do in `b`.
            assert_eq!(*first_seen_a.entry(ia).or_insert(ib), ib);
            assert_eq!(*first_seen_b.entry(ib).or_insert(ia), ia);
        }
    }
}

#[test]
fn obj_write_then_load_round_trips() {
    let dir = tmp_dir("obj");
    let mesh = test_mesh();
    let BaseColor::Texture(tex) = &mesh.materials[0].base_color else { unreachable!() };
    save_srgb_texture(&dir.join("kd.png"), tex).unwrap();
    let names = [MaterialTextureNames { base_color: Some("kd.png".into()), ..Default::default() }];
    write_obj(dir.join("m.obj"), &mesh, &names).unwrap();
    let back = load_obj(dir.join("m.obj")).unwrap();
    // 8-bit sRGB quantisation: at most half a code step of the steepest part of the curve (≈ 2e-3 near 1).
    assert_same_mesh(&mesh, &back, 3e-3);
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn gltf_and_glb_write_then_load_round_trip() {
    for ext in ["gltf", "glb"] {
        let dir = tmp_dir(ext);
        let mesh = test_mesh();
        let BaseColor::Texture(tex) = &mesh.materials[0].base_color else { unreachable!() };
        save_srgb_texture(&dir.join("kd.png"), tex).unwrap();
        let file = dir.join(format!("m.{ext}"));
        write_gltf(&file, &mesh, &[MaterialTextureNames { base_color: Some("kd.png".into()), ..Default::default() }, MaterialTextureNames::default()]).unwrap();
        let back = load_gltf(&file).unwrap();
        assert_same_mesh(&mesh, &back, 3e-3);
        // The stored TEXCOORD_0 is glTF's v (0 at the top): 1 − our v.
        let json: serde_json::Value = if ext == "gltf" {
            serde_json::from_str(&std::fs::read_to_string(&file).unwrap()).unwrap()
        } else {
            let bytes = std::fs::read(&file).unwrap();
            let len = u32::from_le_bytes(bytes[12..16].try_into().unwrap()) as usize;
            serde_json::from_slice(&bytes[20..20 + len]).unwrap()
        };
        let uv_acc = json["meshes"][0]["primitives"][0]["attributes"]["TEXCOORD_0"].as_u64().unwrap() as usize;
        let view = &json["bufferViews"][json["accessors"][uv_acc]["bufferView"].as_u64().unwrap() as usize];
        let bin = if ext == "gltf" {
            std::fs::read(dir.join("m.bin")).unwrap()
        } else {
            let bytes = std::fs::read(&file).unwrap();
            let len = u32::from_le_bytes(bytes[12..16].try_into().unwrap()) as usize;
            bytes[20 + len + 8..].to_vec()
        };
        let off = view["byteOffset"].as_u64().unwrap() as usize;
        let v0 = f32::from_le_bytes(bin[off + 4..off + 8].try_into().unwrap());
        let first = mesh.triangles[0][0] as usize;
        assert!((v0 - (1.0 - mesh.uvs[first].y)).abs() < 1e-6, "stored v {v0}");
        std::fs::remove_dir_all(&dir).ok();
    }
}

#[test]
fn gltf_node_transforms_are_applied() {
    let dir = tmp_dir("xform");
    let mesh = test_mesh();
    let file = dir.join("m.gltf");
    write_gltf(&file, &mesh, &[]).unwrap();
    // Put every node under a transform: translate · rotate 90° about z · scale (2, 2, 2).
    let mut json: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&file).unwrap()).unwrap();
    let q = Quat::from_rotation_z(std::f32::consts::FRAC_PI_2);
    for node in json["nodes"].as_array_mut().unwrap() {
        node["translation"] = serde_json::json!([1.0, 2.0, 3.0]);
        node["rotation"] = serde_json::json!([q.x, q.y, q.z, q.w]);
        node["scale"] = serde_json::json!([2.0, 2.0, 2.0]);
    }
    std::fs::write(&file, serde_json::to_string(&json).unwrap()).unwrap();
    let back = load_gltf(&file).unwrap();
    let m = Mat4::from_scale_rotation_translation(Vec3::splat(2.0), q, Vec3::new(1.0, 2.0, 3.0));
    for (ta, tb) in mesh.triangles.iter().zip(&back.triangles) {
        for (&ia, &ib) in ta.iter().zip(tb) {
            let (ia, ib) = (ia as usize, ib as usize);
            assert!((m.transform_point3(mesh.positions[ia]) - back.positions[ib]).length() < 1e-5);
            assert!((q * mesh.normals[ia] - back.normals[ib]).length() < 1e-5);
        }
    }
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn broken_files_give_errors_naming_the_file() {
    let dir = tmp_dir("bad");
    let file = dir.join("bad.gltf");
    std::fs::write(&file, "{ not json").unwrap();
    let err = format!("{:#}", load_gltf(&file).unwrap_err());
    assert!(err.contains("bad.gltf"), "{err}");
    std::fs::write(dir.join("bad.obj"), "v 0 0 0\nv 1 0 0\nf 1 2 7\n").unwrap();
    let err = format!("{:#}", load_obj(dir.join("bad.obj")).unwrap_err());
    assert!(err.contains("bad.obj"), "{err}");
    std::fs::remove_dir_all(&dir).ok();
}

//! The hotdog's ground-truth mesh loads with the counts the dataset README states, its bounds
//! match materials.json, and every part carries the material materials.json assigns.

mod common;

use std::path::PathBuf;

use glam::Vec3;
use reconstruct::geometry::bvh::Bvh;
use reconstruct::geometry::ground_truth::load_ground_truth;
use reconstruct::geometry::obj::load_obj;
use reconstruct::material::BaseColor;

fn gt_dir(test: &str) -> Option<PathBuf> {
    common::shared_data::require(test).map(|shared| shared.join("data/nerfactor/hotdog_2163/gt"))
}

#[test]
fn hotdog_ground_truth_matches_readme_and_materials_json() {
    let Some(gt) = gt_dir("geometry_hotdog_gt::hotdog_ground_truth_matches_readme_and_materials_json") else { return };
    let mesh = load_ground_truth(&gt).unwrap();
    mesh.validate().unwrap();
    assert_eq!(mesh.parts.len(), 13);
    assert_eq!(mesh.triangles.len(), 66_000);
    assert_eq!(mesh.positions.len(), 38_217);

    let json: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(gt.join("materials.json")).unwrap()).unwrap();
    let v3 = |v: &serde_json::Value| Vec3::new(v[0].as_f64().unwrap() as f32, v[1].as_f64().unwrap() as f32, v[2].as_f64().unwrap() as f32);
    let (lo, hi) = mesh.bounds().unwrap();
    assert!((lo - v3(&json["bbox_min"])).abs().max_element() < 1e-5, "bbox min {lo}");
    assert!((hi - v3(&json["bbox_max"])).abs().max_element() < 1e-5, "bbox max {hi}");

    // Per part: vertex/face counts, UV presence and material as listed.
    let counts = mesh.part_triangle_counts();
    for jp in json["parts"].as_array().unwrap() {
        let name = jp["name"].as_str().unwrap();
        let (k, part) = mesh.parts.iter().enumerate().find(|(_, p)| p.name == name).unwrap_or_else(|| panic!("part {name} missing"));
        assert_eq!(counts[k] as u64, jp["faces"].as_u64().unwrap(), "{name} faces");
        assert_eq!(part.has_uv, jp["has_uv"].as_bool().unwrap(), "{name} has_uv");
        let mut used: Vec<u32> = mesh.triangles.iter().zip(&mesh.triangle_part).filter(|(_, &p)| p as usize == k).flat_map(|(t, _)| *t).collect();
        used.sort_unstable();
        used.dedup();
        assert_eq!(used.len() as u64, jp["vertices"].as_u64().unwrap(), "{name} vertices");

        let mat_name = jp["material"].as_str().unwrap();
        let m = &mesh.materials[part.material];
        assert_eq!(m.name, mat_name);
        let jm = &json["materials"][mat_name];
        assert!((m.roughness.constant().unwrap() - jm["roughness"].as_f64().unwrap() as f32).abs() < 1e-6, "{name} roughness");
        assert!((m.metallic.constant().unwrap() - jm["metallic"].as_f64().unwrap() as f32).abs() < 1e-6, "{name} metallic");
        match (&m.base_color, &jm["base_color"]) {
            (BaseColor::Constant(c), serde_json::Value::Array(_)) => {
                assert!((*c - v3(&jm["base_color"])).abs().max_element() < 1e-6, "{name} base colour")
            }
            (BaseColor::Texture(img), serde_json::Value::Object(o)) => {
                assert!(o["texture"].as_str().unwrap().starts_with(mat_name));
                assert_eq!((img.width, img.height, img.channels), (1024, 1024, 3));
            }
            (got, want) => panic!("{name}: base colour {got:?} vs {want}"),
        }
    }

    // The README's albedo check: train_000 pixel (78, 135) hits Pan2 at vt = (0.3319, 0.5179)
    // whose texture value is (0.84349, 0.31770, 0.03586).
    let pan2 = mesh.materials.iter().find(|m| m.name == "Pan2").unwrap();
    let kd = pan2.eval(glam::Vec2::new(0.3319, 0.5179)).kd;
    assert!((kd - Vec3::new(0.84349, 0.31770, 0.03586)).abs().max_element() < 0.01, "{kd}");

    // A BVH over it builds and a ray down the z axis hits the plate from above.
    let bvh = Bvh::build(&mesh);
    let hit = bvh.closest_hit(Vec3::new(0.0, 0.0, 4.0), -Vec3::Z, 0.0, f32::INFINITY).expect("plate below");
    assert!(hit.t > 3.6 && hit.t < 4.2);
}

#[test]
fn plain_obj_loader_reads_the_mtl_like_materials_json() {
    // The MTL's Pr/Pm/Kd/map_Kd must give the same materials as materials.json for this scene.
    let Some(gt) = gt_dir("geometry_hotdog_gt::plain_obj_loader_reads_the_mtl_like_materials_json") else { return };
    let from_mtl = load_obj(gt.join("hotdog.obj")).unwrap();
    let from_json = load_ground_truth(&gt).unwrap();
    assert_eq!(from_mtl.parts.len(), from_json.parts.len());
    assert_eq!(from_mtl.positions, from_json.positions);
    for (a, b) in from_mtl.parts.iter().zip(&from_json.parts) {
        let (ma, mb) = (&from_mtl.materials[a.material], &from_json.materials[b.material]);
        assert_eq!(ma.name, mb.name);
        assert!((ma.roughness.mean() - mb.roughness.mean()).abs() < 1e-5 && ma.metallic.constant() == mb.metallic.constant(), "{}", ma.name);
        match (&ma.base_color, &mb.base_color) {
            (BaseColor::Constant(x), BaseColor::Constant(y)) => assert!((*x - *y).abs().max_element() < 1e-5),
            (BaseColor::Texture(x), BaseColor::Texture(y)) => assert_eq!(x.data, y.data),
            _ => panic!("{}: base colour kinds differ", ma.name),
        }
    }
}

//! The shared NeRFactor-layout hotdog dataset: loading, and the camera convention checked against
//! facts that do not come from the camera code (depth map, scene bounding box, the GT mesh's
//! silhouette, the README's statements). Skips when the shared data folder is absent.

mod common;

use std::path::PathBuf;

use glam::{Vec2, Vec3};
use reconstruct::scene::{Dataset, Layout, View};

const TEST_PROBES: [&str; 8] = ["city", "courtyard", "forest", "interior", "night", "studio", "sunrise", "sunset"];

fn hotdog_dir(test: &str) -> Option<PathBuf> {
    Some(common::shared_data::require(&format!("scene_hotdog::{test}"))?.join("data/nerfactor/hotdog_2163"))
}

/// The shared hotdog for test `test` (None: skipped, see tests/common/shared_data.rs).
fn load(test: &str) -> Option<Dataset> {
    hotdog_dir(test).map(|d| Dataset::load(&d).expect("hotdog dataset loads"))
}

#[test]
fn hotdog_has_the_documented_views_sizes_and_files() {
    let Some(ds) = load("hotdog_has_the_documented_views_sizes_and_files") else { return };
    assert_eq!(ds.layout, Layout::NeRFactor);
    assert_eq!((ds.train.len(), ds.val.len(), ds.test.len()), (100, 8, 8));
    assert_eq!(ds.train[0].name, "train_000");
    assert_eq!(ds.train[99].name, "train_099");
    assert_eq!(ds.val[7].name, "val_007");
    let test_names: Vec<&str> = ds.test.iter().map(|v| v.name.as_str()).collect();
    assert_eq!(test_names, ["test_024", "test_049", "test_074", "test_099", "test_124", "test_149", "test_174", "test_199"]);
    for v in ds.all_views() {
        assert_eq!((v.camera.width, v.camera.height), (256, 256), "{}", v.name);
        assert!((v.camera.fov_x - 0.691_111_2).abs() < 1e-6);
        assert!(v.has_albedo() && v.has_normal() && v.has_roughness() && v.has_metallic() && v.has_depth());
    }
    for v in &ds.test {
        assert_eq!(v.relit_probes().unwrap(), TEST_PROBES);
        for p in TEST_PROBES {
            assert!(v.has_relit(p));
        }
    }
    assert!(!ds.train[0].has_relit("city"));
    let relit = ds.test[0].load_relit("night").unwrap();
    assert_eq!((relit.width, relit.height, relit.channels), (256, 256, 4));
}

#[test]
fn metadata_repeats_the_transforms() {
    let Some(ds) = load("metadata_repeats_the_transforms") else { return };
    for v in ds.all_views() {
        let m = v.metadata.as_ref().expect("metadata.json present");
        let mat = m.cam_transform_mat.expect("cam_transform_mat present");
        assert!(mat.abs_diff_eq(v.camera.c2w, 1e-6), "{}: {mat:?} vs {:?}", v.name, v.camera.c2w);
        assert!((m.cam_angle_x.unwrap() - v.camera.fov_x).abs() < 1e-7);
        assert_eq!((m.imw, m.imh), (Some(256), Some(256)));
        assert_eq!(m.envmap.as_deref(), Some("2163.hdr"));
        assert_eq!(m.envmap_inten, Some(3.0));
    }
}

#[test]
fn cameras_sit_on_the_documented_sphere_and_look_at_the_origin() {
    let Some(ds) = load("cameras_sit_on_the_documented_sphere_and_look_at_the_origin") else { return };
    for v in ds.all_views() {
        let o = v.camera.origin();
        assert!((o.length() - 4.03).abs() < 0.01, "{}: distance {}", v.name, o.length());
        assert!(v.camera.forward().dot(-o.normalize()) > 0.9999, "{} does not look at the origin", v.name);
        let (centre, depth) = v.camera.project(Vec3::ZERO);
        assert!((centre - Vec2::splat(128.0)).length() < 0.5 && depth > 0.0);
    }
    // README: "In train_000, −x is image-right" and it looks almost straight down (+z is toward the camera).
    let cam = &ds.train[0].camera;
    let (minus_x, _) = cam.project(Vec3::new(-1.0, 0.0, 0.0));
    let (plus_x, _) = cam.project(Vec3::new(1.0, 0.0, 0.0));
    assert!(minus_x.x > 200.0 && plus_x.x < 56.0, "{minus_x} {plus_x}");
    assert!(cam.forward().z < -0.95);
}

/// The world point seen at pixel (i, j) with planar depth `z`.
fn back_project(v: &View, i: usize, j: usize, z: f32) -> Vec3 {
    let d = v.camera.ray_dir(i as f32 + 0.5, j as f32 + 0.5);
    v.camera.origin() + d * (z / d.dot(v.camera.forward()))
}

#[test]
fn depth_back_projects_into_the_scene_box_and_projects_back_to_its_pixel() {
    let Some(ds) = load("depth_back_projects_into_the_scene_box_and_projects_back_to_its_pixel") else { return };
    let (lo, hi) = (Vec3::new(-1.198, -1.286, -0.190), Vec3::new(1.198, 1.110, 0.312));
    let mut union = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
    for v in [&ds.train[0], &ds.train[37], &ds.val[3], &ds.test[5]] {
        let depth = v.load_depth().unwrap();
        let alpha = v.load_alpha().unwrap();
        let mut covered = 0;
        for j in 0..256 {
            for i in 0..256 {
                let (z, a) = (depth.pixel(i, j)[0], alpha.pixel(i, j)[0]);
                assert_eq!(z > 0.0, a > 0.0, "{} ({i},{j}): depth {z} but alpha {a}", v.name);
                if a < 1.0 {
                    continue;
                }
                covered += 1;
                let p = back_project(v, i, j, z);
                let (px, pz) = v.camera.project(p);
                assert!((px - Vec2::new(i as f32 + 0.5, j as f32 + 0.5)).length() < 1e-2 && (pz - z).abs() < 1e-4 * z);
                let tol = Vec3::splat(0.02);
                assert!(p.cmpge(lo - tol).all() && p.cmple(hi + tol).all(), "{} ({i},{j}) → {p} outside the box", v.name);
                union = (union.0.min(p), union.1.max(p));
            }
        }
        assert!(covered > 5000, "{}: only {covered} covered pixels", v.name);
    }
    // The plate rim spans the box in x and y, and the top of the food reaches its top.
    assert!(union.0.x < -1.1 && union.1.x > 1.1 && union.0.y < -1.15 && union.1.y > 1.0, "{union:?}");
    assert!(union.1.z > 0.25, "{union:?}");
}

fn obj_vertices(path: &std::path::Path) -> Vec<Vec3> {
    let text = std::fs::read_to_string(path).unwrap();
    text.lines()
        .filter_map(|l| l.strip_prefix("v "))
        .map(|l| {
            let c: Vec<f32> = l.split_whitespace().take(3).map(|t| t.parse().unwrap()).collect();
            Vec3::new(c[0], c[1], c[2])
        })
        .collect()
}

#[test]
fn gt_mesh_vertices_project_onto_the_silhouette_and_behind_the_visible_depth() {
    let Some(ds) = load("gt_mesh_vertices_project_onto_the_silhouette_and_behind_the_visible_depth") else { return };
    let obj = ds.root.join("gt/hotdog.obj");
    let vertices = obj_vertices(&obj);
    assert_eq!(vertices.len(), 38_217);
    for v in [&ds.train[0], &ds.train[63], &ds.test[2]] {
        let alpha = v.load_alpha().unwrap();
        let depth = v.load_depth().unwrap();
        let near = |i: usize, j: usize, f: &dyn Fn(usize, usize) -> bool| {
            (j.saturating_sub(1)..=(j + 1).min(255)).any(|y| (i.saturating_sub(1)..=(i + 1).min(255)).any(|x| f(x, y)))
        };
        let (mut off_silhouette, mut in_front, mut interior) = (0, 0, 0);
        for &p in &vertices {
            let (px, z) = v.camera.project(p);
            assert!(z > 0.0 && px.x >= 0.0 && px.y >= 0.0 && px.x < 256.0 && px.y < 256.0, "{}: {p} → {px}", v.name);
            let (i, j) = (px.x as usize, px.y as usize);
            if !near(i, j, &|x, y| alpha.pixel(x, y)[0] > 0.0) {
                off_silhouette += 1;
            }
            if !near(i, j, &|x, y| alpha.pixel(x, y)[0] < 1.0) {
                interior += 1;
                let min_depth = (j - 1..=j + 1)
                    .flat_map(|y| (i - 1..=i + 1).map(move |x| (x, y)))
                    .map(|(x, y)| depth.pixel(x, y)[0])
                    .fold(f32::INFINITY, f32::min);
                if z < min_depth - 0.01 {
                    in_front += 1;
                }
            }
        }
        assert_eq!(off_silhouette, 0, "{}: vertices outside the silhouette", v.name);
        assert!(interior > vertices.len() / 2);
        assert!(in_front * 1000 <= interior, "{}: {in_front} of {interior} vertices in front of the visible surface", v.name);
    }
}

#[test]
fn ground_truth_maps_decode_to_sensible_values() {
    let Some(ds) = load("ground_truth_maps_decode_to_sensible_values") else { return };
    let v = &ds.train[0];
    let rgba = v.load_rgba().unwrap();
    let albedo = v.load_albedo().unwrap();
    let normal = v.load_normal().unwrap();
    let rough = v.load_roughness().unwrap();
    let metal = v.load_metallic().unwrap();
    // README: all GT passes share rgba's coverage exactly; metallic is 0 everywhere.
    let (mut full, mut on_a_material) = (0, 0);
    let roughness_values: [f32; 5] = [0.8, 0.5, 0.208333, 0.118182, 0.166667];
    for i in 0..rgba.pixel_count() {
        let a = rgba.data[4 * i + 3];
        assert_eq!(albedo.data[4 * i + 3], a);
        assert_eq!(metal.data[i], 0.0);
        let n = Vec3::from_slice(&normal.data[4 * i..4 * i + 3]);
        if a > 0.0 {
            assert!((n.length() - 1.0).abs() < 1e-5);
            // Shading normals face the camera.
            let to_cam = -v.camera.ray_dir((i % 256) as f32 + 0.5, (i / 256) as f32 + 0.5);
            assert!(n.dot(to_cam) > -0.2, "pixel {i}: normal {n} faces away");
        } else {
            assert_eq!(n, Vec3::ZERO);
            assert_eq!(rough.data[i], 0.0);
        }
        if a == 1.0 {
            full += 1;
            let r = rough.data[i];
            // Pixels straddling two materials average them; the rest hold one material's value.
            if roughness_values.iter().any(|&x| (x - r).abs() < 0.006) {
                on_a_material += 1;
            }
        }
    }
    assert!(on_a_material * 100 > full * 90, "{on_a_material} of {full} pixels hold a material's roughness");
    // Looking almost straight down on a flat plate: most normals point up (+z).
    let up = (0..rgba.pixel_count()).filter(|&i| normal.data[4 * i + 2] > 0.9).count();
    let covered = (0..rgba.pixel_count()).filter(|&i| rgba.data[4 * i + 3] > 0.0).count();
    assert!(up * 2 > covered, "{up} of {covered} normals point up");
}

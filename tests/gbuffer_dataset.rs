//! The traced G-buffer against the hotdog dataset's own ground-truth passes (rendered by
//! Mitsuba from the same mesh): coverage (rgba.png alpha), planar depth (depth.exr), shading
//! normal (normal.png) and bun albedo (albedo.png, linear) for a few views.

mod common;

use std::path::Path;

use glam::{Mat4, Vec3};
use reconstruct::geometry::bvh::Bvh;
use reconstruct::geometry::ground_truth::load_ground_truth;
use reconstruct::render::gbuffer::GBuffer;
use reconstruct::scene::camera::Camera;

/// The camera of view `folder` (e.g. "test_049") from `transforms_<split>.json`.
fn camera_of(scene: &Path, split: &str, folder: &str, size: usize) -> Camera {
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(scene.join(format!("transforms_{split}.json"))).unwrap()).unwrap();
    let fov_x = json["camera_angle_x"].as_f64().unwrap() as f32;
    let frame = json["frames"]
        .as_array()
        .unwrap()
        .iter()
        .find(|f| f["file_path"].as_str().unwrap().contains(&format!("{folder}/")))
        .unwrap();
    let rows: Vec<[f32; 4]> = frame["transform_matrix"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| {
            let r = r.as_array().unwrap();
            [0, 1, 2, 3].map(|k| r[k].as_f64().unwrap() as f32)
        })
        .collect();
    // transform_matrix is row-major; glam takes columns.
    let c2w = Mat4::from_cols_array_2d(&[rows[0], rows[1], rows[2], rows[3]]).transpose();
    Camera { c2w, fov_x, width: size, height: size }
}

fn read_rgba8(path: &Path) -> (usize, usize, Vec<[f32; 4]>) {
    let img = image::open(path).unwrap().to_rgba32f();
    let (w, h) = (img.width() as usize, img.height() as usize);
    (w, h, img.pixels().map(|p| p.0).collect())
}

fn read_depth(path: &Path) -> Vec<f32> {
    let img = exr::prelude::read_first_flat_layer_from_file(path).unwrap();
    let ch = img.layer_data.channel_data.list.iter().find(|c| c.name.to_string() == "Z").unwrap();
    ch.sample_data.values_as_f32().collect()
}

fn median(mut v: Vec<f32>) -> f32 {
    v.sort_by(f32::total_cmp);
    v[v.len() / 2]
}

struct ViewStats {
    mask_agreement: f64,
    depth_median_abs: f32,
    normal_mean_deg: f32,
    bun_albedo_mean_abs: f32,
    /// Mean |roughness − roughness.png| on interior pixels: checks every part's material mapping.
    roughness_mean_abs: f32,
    /// Mean |coverage − alpha| over pixels with 0 < alpha < 1, with 4×4 supersampled coverage.
    edge_coverage_mean_abs: f32,
    interior: usize,
    bun_pixels: usize,
    /// Per bun part (Pan1, Pan2, Pan1_001, Pan2_001): mean |Δ| and pixel count. The `_001` parts
    /// come after the UV-less parts in hotdog.obj, so they check the OBJ texture-index repair.
    bun_parts: std::collections::BTreeMap<String, (f32, usize)>,
}

fn compare_view(scene: &Path, split: &str, folder: &str, mesh: &reconstruct::geometry::Mesh, bvh: &Bvh) -> ViewStats {
    let view = scene.join(folder);
    let (w, h, rgba) = read_rgba8(&view.join("rgba.png"));
    assert_eq!((w, h), (256, 256));
    let camera = camera_of(scene, split, folder, w);
    let gb = GBuffer::trace(mesh, bvh, &camera);
    let mask = gb.mask();

    // (a) Coverage: decided pixels only (alpha ≥ 0.99 hit, ≤ 0.01 miss).
    let (mut agree, mut decided) = (0usize, 0usize);
    for (i, px) in rgba.iter().enumerate() {
        let a = px[3];
        if a >= 0.99 || a <= 0.01 {
            decided += 1;
            agree += ((a >= 0.99) == mask[i]) as usize;
        }
    }

    // Interior: the pixel and its 8 neighbours are fully covered in the dataset, so the pixel
    // footprint average the dataset stores is close to the centre sample we trace.
    let full = |x: i64, y: i64| x >= 0 && y >= 0 && x < w as i64 && y < h as i64 && rgba[y as usize * w + x as usize][3] >= 1.0;
    let gt_depth = read_depth(&view.join("depth.exr"));
    assert_eq!(gt_depth.len(), w * h);
    let (_, _, gt_normal) = read_rgba8(&view.join("normal.png"));
    let (_, _, gt_albedo) = read_rgba8(&view.join("albedo.png"));
    let gt_rough: Vec<f32> = image::open(view.join("roughness.png")).unwrap().to_luma32f().into_raw();
    let mut rough_diffs = Vec::new();
    let params = gb.material_params(mesh);
    let (mut depth_diffs, mut angles, mut albedo_diffs) = (Vec::new(), Vec::new(), Vec::new());
    let mut bun_parts = std::collections::BTreeMap::new();
    for y in 0..h as i64 {
        for x in 0..w as i64 {
            let interior = (-1..=1).all(|dy| (-1..=1).all(|dx| full(x + dx, y + dy)));
            let i = y as usize * w + x as usize;
            let Some(s) = gb.surfels[i] else { continue };
            if !interior {
                continue;
            }
            depth_diffs.push((s.depth - gt_depth[i]).abs());
            rough_diffs.push((params[i].unwrap().roughness - gt_rough[i]).abs());
            let n = gt_normal[i];
            let gt_n = (Vec3::new(n[0], n[1], n[2]) * 2.0 - Vec3::ONE).normalize();
            angles.push(gt_n.dot(s.normal).clamp(-1.0, 1.0).acos().to_degrees());
            let part_material = &mesh.materials[mesh.parts[mesh.triangle_part[s.triangle as usize] as usize].material].name;
            if part_material.starts_with("Pan") {
                let kd = params[i].unwrap().kd;
                let a = gt_albedo[i];
                let d = (kd - Vec3::new(a[0], a[1], a[2])).abs().element_sum() / 3.0;
                albedo_diffs.push(d);
                let part = &mesh.parts[mesh.triangle_part[s.triangle as usize] as usize].name;
                let e = bun_parts.entry(part.clone()).or_insert((0.0, 0));
                e.0 += d;
                e.1 += 1;
            }
        }
    }
    // Fractional coverage from a 4×4 supersampled trace (the caller-side supersampling the
    // G-buffer is designed for) against the dataset's alpha on silhouette pixels.
    let cov = GBuffer::trace(mesh, bvh, &camera.resized(4 * w, 4 * h)).coverage_image().downsample_box(4);
    let edge: Vec<f32> = (0..w * h).filter(|&i| rgba[i][3] > 0.0 && rgba[i][3] < 1.0).map(|i| (cov.data[i] - rgba[i][3]).abs()).collect();
    ViewStats {
        roughness_mean_abs: rough_diffs.iter().sum::<f32>() / rough_diffs.len() as f32,
        edge_coverage_mean_abs: edge.iter().sum::<f32>() / edge.len() as f32,
        mask_agreement: agree as f64 / decided as f64,
        depth_median_abs: median(depth_diffs.clone()),
        normal_mean_deg: angles.iter().sum::<f32>() / angles.len() as f32,
        bun_albedo_mean_abs: albedo_diffs.iter().sum::<f32>() / albedo_diffs.len().max(1) as f32,
        interior: angles.len(),
        bun_pixels: albedo_diffs.len(),
        bun_parts: bun_parts.into_iter().map(|(k, (sum, n))| (k, (sum / n as f32, n))).collect(),
    }
}

#[test]
fn gbuffer_matches_dataset_ground_truth_passes() {
    let Some(shared) = common::shared_data::require("gbuffer_dataset::gbuffer_matches_dataset_ground_truth_passes") else { return };
    let scene = shared.join("data/nerfactor/hotdog_2163");
    let mesh = load_ground_truth(scene.join("gt")).unwrap();
    let bvh = Bvh::build(&mesh);
    for (split, folder) in [("train", "train_000"), ("train", "train_037"), ("val", "val_003"), ("test", "test_149")] {
        let s = compare_view(&scene, split, folder, &mesh, &bvh);
        println!(
            "{folder}: mask agreement {:.4}%, depth median |Δ| {:.2e}, normal mean error {:.3}°, bun albedo mean |Δ| {:.4} \
             ({} interior px, {} bun px)",
            100.0 * s.mask_agreement,
            s.depth_median_abs,
            s.normal_mean_deg,
            s.bun_albedo_mean_abs,
            s.interior,
            s.bun_pixels
        );
        println!("  bun parts (mean |Δ|, px): {:?}", s.bun_parts);
        println!(
            "  roughness mean |Δ| {:.4} (interior); silhouette coverage (4×4 ss) mean |Δα| {:.4}",
            s.roughness_mean_abs, s.edge_coverage_mean_abs
        );
        // Floors, from the numbers measured on these views (see the report in the commit):
        // coverage 100 % agreement on decided pixels; depth median |Δ| ≤ 7.1e-5 (the dataset stores
        // a pixel-footprint average, we trace the centre); normal mean error 1.47–1.64° (8-bit
        // quantisation plus footprint averaging); bun albedo 0.008–0.011, which the dataset README
        // predicts (0.009–0.010) from box filtering, while a v-flip would give 0.087–0.14.
        assert!(s.mask_agreement >= 0.99, "{folder}: mask agreement {}", s.mask_agreement);
        assert!(s.interior > 5000 && s.bun_pixels > 500, "{folder}: too few pixels to judge");
        assert!(s.depth_median_abs < 1e-3, "{folder}: depth median {}", s.depth_median_abs);
        assert!(s.normal_mean_deg < 2.5, "{folder}: normal error {}°", s.normal_mean_deg);
        assert!(s.bun_albedo_mean_abs < 0.02, "{folder}: bun albedo {}", s.bun_albedo_mean_abs);
        // Roughness 0.006–0.007 (8-bit quantisation ≤ 0.002 plus pixels straddling two parts);
        // swapping any two parts' materials would add ≥ 0.03 over thousands of pixels.
        assert!(s.roughness_mean_abs < 0.02, "{folder}: roughness {}", s.roughness_mean_abs);
        // Silhouette alpha: 16 centred samples vs the dataset's 64-spp estimate, 0.027 measured.
        assert!(s.edge_coverage_mean_abs < 0.05, "{folder}: edge coverage {}", s.edge_coverage_mean_abs);
        for (part, (err, n)) in &s.bun_parts {
            assert!(*n < 100 || *err < 0.03, "{folder}: bun part {part} albedo {err} over {n} px");
        }
    }
}

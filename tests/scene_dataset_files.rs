//! The dataset loader on tiny synthetic datasets written by the test itself: both layouts,
//! 8- and 16-bit PNGs, what each map decodes to, and a clear error naming the file for each kind
//! of broken input.

use std::path::{Path, PathBuf};

use glam::{Mat4, Vec3};
use reconstruct::color::srgb_to_linear;
use reconstruct::image::io::{write_exr_channels, write_png, write_png16};
use reconstruct::image::Image;
use reconstruct::scene::{Camera, Dataset, Layout};

const W: usize = 8;
const H: usize = 6;

/// A fresh empty folder under the system temp dir.
fn temp_dir(tag: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("reconstruct-scene-{}-{tag}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn c2w(k: usize) -> Mat4 {
    let eye = Vec3::new(4.0 * (k as f32).cos(), 4.0 * (k as f32).sin(), 1.0);
    Camera::look_at(eye, Vec3::ZERO, Vec3::Z, 0.7, W, H).c2w
}

fn rows(m: Mat4) -> Vec<Vec<f32>> {
    let t = m.transpose().to_cols_array_2d();
    t.iter().map(|r| r.to_vec()).collect()
}

/// The encoded normal (n+1)/2 of pixel (x, y): a unit vector that varies over the image.
fn true_normal(x: usize, y: usize) -> Vec3 {
    Vec3::new(x as f32 - 3.5, y as f32 - 2.5, 4.0).normalize()
}

fn write(path: &Path, img: &Image, deep: bool) {
    if deep { write_png16(path, img) } else { write_png(path, img) }.unwrap();
}

fn write_view(dir: &Path, k: usize, relit: bool, deep: bool) {
    std::fs::create_dir_all(dir).unwrap();
    let mut rgba = Image::new(W, H, 4);
    let mut albedo = Image::new(W, H, 4);
    let mut normal = Image::new(W, H, 4);
    let mut rough = Image::new(W, H, 1);
    let mut depth = Image::new(W, H, 1);
    for y in 0..H {
        for x in 0..W {
            let a = if x == 0 { 0.0 } else if x == 1 { 128.0 / 255.0 } else { 1.0 };
            rgba.pixel_mut(x, y).copy_from_slice(&[188.0 / 255.0, x as f32 / 255.0, 1.0, a]);
            albedo.pixel_mut(x, y).copy_from_slice(&[0.5, 0.25, 1.0, a]);
            let n = if a > 0.0 { (true_normal(x, y) + 1.0) / 2.0 } else { Vec3::ZERO };
            normal.pixel_mut(x, y).copy_from_slice(&[n.x, n.y, n.z, a]);
            rough.pixel_mut(x, y)[0] = if a > 0.0 { 0.4 } else { 0.0 };
            depth.pixel_mut(x, y)[0] = if a > 0.0 { 3.0 + 0.01 * (x + W * y) as f32 } else { 0.0 };
        }
    }
    write(&dir.join("rgba.png"), &rgba, deep);
    write(&dir.join("albedo.png"), &albedo, deep);
    write(&dir.join("normal.png"), &normal, deep);
    write(&dir.join("roughness.png"), &rough, deep);
    write(&dir.join("metallic.png"), &Image::new(W, H, 1), deep);
    write_exr_channels(&dir.join("depth.exr"), &depth, &["Z"]).unwrap();
    if relit {
        write(&dir.join("rgba_city.png"), &rgba, deep);
        // NeRFactor's one-light-at-a-time renders are not probes.
        write(&dir.join("rgba_olat-0000-0000.png"), &rgba, deep);
    }
    let flat: Vec<String> = rows(c2w(k)).concat().iter().map(|v| v.to_string()).collect();
    let meta = serde_json::json!({
        "scene": "tiny.blend", "cam_transform_mat": flat.join(","), "cam_angle_x": 0.7,
        "envmap": "2163.hdr", "envmap_inten": 3.0, "imh": H, "imw": W, "spp": 4
    });
    std::fs::write(dir.join("metadata.json"), meta.to_string()).unwrap();
}

fn write_transforms(root: &Path, split: &str, paths: &[(String, usize)]) {
    let frames: Vec<_> = paths
        .iter()
        .map(|(p, k)| serde_json::json!({"file_path": p, "rotation": 0.0125, "transform_matrix": rows(c2w(*k))}))
        .collect();
    let json = serde_json::json!({"camera_angle_x": 0.7, "frames": frames});
    std::fs::write(root.join(format!("transforms_{split}.json")), serde_json::to_string_pretty(&json).unwrap()).unwrap();
}

/// NeRFactor layout: train_000, train_001, val_000, test_005 (with a relit image).
fn nerfactor_dataset(tag: &str, deep: bool) -> PathBuf {
    let root = temp_dir(tag);
    let mut k = 0;
    for (split, names) in [("train", vec!["train_000", "train_001"]), ("val", vec!["val_000"]), ("test", vec!["test_005"])] {
        let mut paths = Vec::new();
        for n in names {
            write_view(&root.join(n), k, split == "test", deep);
            paths.push((format!("./{n}/rgba"), k));
            k += 1;
        }
        write_transforms(&root, split, &paths);
    }
    root
}

fn error_text(r: anyhow::Result<impl std::fmt::Debug>) -> String {
    let msg = format!("{:#}", r.expect_err("expected an error"));
    println!("error as reported: {msg}");
    msg
}

#[test]
fn nerfactor_layout_loads_and_every_map_decodes() {
    for deep in [false, true] {
        let root = nerfactor_dataset(if deep { "ok16" } else { "ok8" }, deep);
        let ds = Dataset::load(&root).unwrap();
        assert_eq!(ds.layout, Layout::NeRFactor);
        let names: Vec<&str> = ds.all_views().map(|v| v.name.as_str()).collect();
        assert_eq!(names, ["train_000", "train_001", "val_000", "test_005"]);
        let v = &ds.train[1];
        assert_eq!((v.camera.width, v.camera.height), (W, H));
        assert!(v.camera.c2w.abs_diff_eq(c2w(1), 1e-6) && (v.camera.fov_x - 0.7).abs() < 1e-7);
        assert_eq!(v.rotation, Some(0.0125));
        assert!(v.metadata.as_ref().unwrap().cam_transform_mat.unwrap().abs_diff_eq(c2w(1), 1e-6));
        let tol = if deep { 1e-4 } else { 1e-6 };

        let rgba = v.load_rgba().unwrap();
        let p = rgba.pixel(3, 2);
        assert!((p[0] - srgb_to_linear(188.0 / 255.0)).abs() < tol && (p[1] - srgb_to_linear(3.0 / 255.0)).abs() < tol);
        assert!((p[2] - 1.0).abs() < tol && (p[3] - 1.0).abs() < tol);
        // Alpha is straight and not decoded.
        assert!((rgba.pixel(1, 0)[3] - 128.0 / 255.0).abs() < tol);

        // Albedo is linear as stored (0.5 is 128/255 at 8 bits, not decoded).
        let albedo = v.load_albedo().unwrap();
        let q = if deep { 0.5 } else { 128.0 / 255.0 };
        assert!((albedo.pixel(4, 4)[0] - q).abs() < tol && (albedo.pixel(1, 1)[3] - 128.0 / 255.0).abs() < tol);

        let normal = v.load_normal().unwrap();
        for y in 0..H {
            for x in 0..W {
                let n = Vec3::from_slice(normal.pixel(x, y));
                if x == 0 {
                    assert_eq!(normal.pixel(x, y), &[0.0; 4], "background normal is zero");
                } else {
                    assert!((n.length() - 1.0).abs() < 1e-5 && n.dot(true_normal(x, y)) > 0.9999, "({x},{y}) {n}");
                }
            }
        }
        let rough = v.load_roughness().unwrap();
        assert!((rough.pixel(5, 5)[0] - 0.4).abs() < 0.5 / 255.0 && rough.pixel(0, 5)[0] == 0.0);
        assert!(v.load_metallic().unwrap().data.iter().all(|&m| m == 0.0));
        let depth = v.load_depth().unwrap();
        assert_eq!(depth.pixel(7, 5)[0], 3.0 + 0.01 * (7 + W * 5) as f32);

        let t = &ds.test[0];
        assert_eq!(t.relit_probes().unwrap(), ["city"]);
        assert!(t.has_relit("olat-0000-0000") && t.load_relit("olat-0000-0000").is_ok());
        assert_eq!(t.load_relit("city").unwrap(), t.load_rgba().unwrap());
        let msg = error_text(t.load_relit("forest"));
        assert!(msg.contains("rgba_forest.png") && msg.contains("not found"), "{msg}");
    }
}

#[test]
fn nerf_synthetic_layout_is_detected() {
    let root = temp_dir("nerf");
    std::fs::create_dir_all(root.join("train")).unwrap();
    let mut img = Image::new(W, H, 4);
    img.data.iter_mut().for_each(|v| *v = 1.0);
    for i in 0..3 {
        write_png(&root.join(format!("train/r_{i}.png")), &img).unwrap();
    }
    write_transforms(&root, "train", &(0..3).map(|i| (format!("./train/r_{i}"), i)).collect::<Vec<_>>());
    let ds = Dataset::load(&root).unwrap();
    assert_eq!(ds.layout, Layout::NerfSynthetic);
    assert_eq!((ds.train.len(), ds.val.len(), ds.test.len()), (3, 0, 0));
    let v = &ds.train[2];
    assert_eq!(v.name, "train_r_2");
    assert_eq!(v.image_path, root.join("train/r_2.png"));
    assert_eq!(v.load_rgba().unwrap().pixel(0, 0), &[1.0; 4]);
    assert!(!v.has_albedo() && !v.has_depth() && v.load_roughness_if_present().unwrap().is_none());
    let msg = error_text(v.load_albedo());
    assert!(msg.contains("r_2.png") && msg.contains("NeRF-synthetic"), "{msg}");
}

#[test]
fn missing_dataset_or_view_folder_is_named() {
    let msg = error_text(Dataset::load(Path::new("/no/such/dataset")));
    assert!(msg.contains("/no/such/dataset"), "{msg}");

    let root = nerfactor_dataset("nofolder", false);
    std::fs::remove_dir_all(root.join("train_001")).unwrap();
    let msg = error_text(Dataset::load(&root));
    assert!(msg.contains("view folder not found") && msg.contains("train_001"), "{msg}");
    assert!(msg.contains("transforms_train.json"), "{msg}");
}

#[test]
fn an_unknown_view_name_is_refused_listing_the_views_there_are() {
    let root = nerfactor_dataset("viewname", false);
    let ds = Dataset::load(&root).unwrap();
    assert_eq!(ds.view("val_000").unwrap().name, "val_000");
    let msg = error_text(ds.view("test_000"));
    assert!(msg.contains("\"test_000\"") && msg.contains(&root.display().to_string()), "{msg}");
    assert!(msg.contains("1 test view (test_005)") && msg.contains("2 train views (train_000, train_001)") && msg.contains("1 val view (val_000)"), "{msg}");
}

#[test]
fn missing_images_are_named() {
    let root = nerfactor_dataset("noimage", false);
    std::fs::remove_file(root.join("val_000/rgba.png")).unwrap();
    let msg = error_text(Dataset::load(&root));
    assert!(msg.contains("val_000/rgba.png") && msg.contains("not found"), "{msg}");

    let root = nerfactor_dataset("noalbedo", false);
    std::fs::remove_file(root.join("train_000/albedo.png")).unwrap();
    std::fs::remove_file(root.join("train_000/depth.exr")).unwrap();
    let ds = Dataset::load(&root).unwrap();
    let v = &ds.train[0];
    assert!(!v.has_albedo() && !v.has_depth() && v.has_normal());
    let msg = error_text(v.load_albedo());
    assert!(msg.contains("train_000/albedo.png") && msg.contains("not found"), "{msg}");
    assert!(v.load_depth_if_present().unwrap().is_none());
    assert!(error_text(v.load_depth()).contains("train_000/depth.exr"));
}

#[test]
fn wrong_image_sizes_are_named_with_both_sizes() {
    let root = nerfactor_dataset("size", false);
    write_png(&root.join("train_001/normal.png"), &Image::new(W - 1, H, 4)).unwrap();
    let msg = error_text(Dataset::load(&root));
    assert!(msg.contains("train_001/normal.png") && msg.contains("7×6") && msg.contains("8×6"), "{msg}");

    let root = nerfactor_dataset("exrsize", false);
    write_exr_channels(&root.join("test_005/depth.exr"), &Image::new(W, H + 2, 1), &["Z"]).unwrap();
    let msg = error_text(Dataset::load(&root));
    assert!(msg.contains("test_005/depth.exr") && msg.contains("8×8"), "{msg}");

    let root = nerfactor_dataset("metasize", false);
    let meta = root.join("val_000/metadata.json");
    let text = std::fs::read_to_string(&meta).unwrap().replace("\"imw\":8", "\"imw\":16");
    std::fs::write(&meta, text).unwrap();
    let msg = error_text(Dataset::load(&root));
    assert!(msg.contains("val_000/metadata.json") && msg.contains("16×6"), "{msg}");
}

#[test]
fn bad_json_is_named() {
    let root = nerfactor_dataset("json", false);
    let file = root.join("transforms_val.json");
    let text = std::fs::read_to_string(&file).unwrap();
    std::fs::write(&file, &text[..text.len() / 2]).unwrap();
    let msg = error_text(Dataset::load(&root));
    assert!(msg.contains("transforms_val.json") && msg.contains("parse"), "{msg}");

    let root = nerfactor_dataset("json2", false);
    std::fs::write(root.join("transforms_test.json"), r#"{"frames": []}"#).unwrap();
    let msg = error_text(Dataset::load(&root));
    assert!(msg.contains("transforms_test.json") && msg.contains("camera_angle_x"), "{msg}");

    let root = nerfactor_dataset("json3", false);
    std::fs::write(root.join("train_000/metadata.json"), "{ not json").unwrap();
    let msg = error_text(Dataset::load(&root));
    assert!(msg.contains("train_000/metadata.json"), "{msg}");

    let root = nerfactor_dataset("nojson", false);
    std::fs::remove_file(root.join("transforms_train.json")).unwrap();
    let msg = error_text(Dataset::load(&root));
    assert!(msg.contains("transforms_train.json") && msg.contains("not found"), "{msg}");
}

#[test]
fn corrupt_png_is_named() {
    let root = nerfactor_dataset("corrupt", false);
    std::fs::write(root.join("train_000/roughness.png"), b"\x89PNG\r\n\x1a\n garbage").unwrap();
    let msg = error_text(Dataset::load(&root));
    assert!(msg.contains("train_000/roughness.png"), "{msg}");
}

/// A `transform_matrix` that is not a rigid camera pose (scaled, sheared, mirrored) is refused,
/// naming the transforms file and the frame; a pose rounded to JSON's digits passes.
#[test]
fn a_camera_matrix_that_is_not_rigid_is_refused_naming_the_file_and_frame() {
    for (tag, bad, needle) in [
        ("scaled", c2w(1) * Mat4::from_scale(Vec3::splat(1.05)), "not orthonormal"),
        ("sheared", Mat4::from_cols(c2w(1).x_axis, c2w(1).y_axis + 0.2 * c2w(1).x_axis, c2w(1).z_axis, c2w(1).w_axis), "not orthonormal"),
        ("mirrored", c2w(1) * Mat4::from_scale(Vec3::new(1.0, 1.0, -1.0)), "determinant"),
    ] {
        let root = nerfactor_dataset(&format!("rigid-{tag}"), false);
        let file = root.join("transforms_train.json");
        let mut json: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&file).unwrap()).unwrap();
        json["frames"][1]["transform_matrix"] = serde_json::json!(rows(bad));
        std::fs::write(&file, json.to_string()).unwrap();
        let msg = error_text(Dataset::load(&root));
        assert!(msg.contains("transforms_train.json") && msg.contains("frame 1") && msg.contains("train_001") && msg.contains(needle), "{tag}: {msg}");
    }
    // The unmodified poses are look-at frames written with f32's shortest round-trip digits: accepted.
    Dataset::load(&nerfactor_dataset("rigid-ok", false)).unwrap();
}

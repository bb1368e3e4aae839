//! Scenes the team did not make by hand load with no code change: a ground-truth folder whose mesh
//! has any name (an OBJ `cow.obj`, a glTF `statue.gltf`) and whose `materials.json` gives roughness
//! and metallic as textures or constants; a NeRF-synthetic folder without any ground-truth map;
//! NeRFactor scene files whose data is missing. Every scene is made here, in a temporary folder, by
//! the project's own writers (a few 40² views), then read back through the public entry points.

use std::path::{Path, PathBuf};

use glam::{Quat, Vec2, Vec3};
use reconstruct::color::srgb_to_linear;
use reconstruct::eval::protocol::{evaluate, EvalSettings};
use reconstruct::geometry::bvh::Bvh;
use reconstruct::geometry::gltf_io::write_gltf;
use reconstruct::geometry::obj::write_obj;
use reconstruct::geometry::primitives::MeshBuilder;
use reconstruct::geometry::texture_file::save_srgb_texture;
use reconstruct::geometry::Mesh;
use reconstruct::image::{io, Image};
use reconstruct::jobs::render::{run, RenderOptions};
use reconstruct::light::CubeMap;
use reconstruct::material::texture_maps::MaterialTextures;
use reconstruct::material::{BaseColor, PartMaterial, Scalar};
use reconstruct::prior::idarb_sim::depth_points;
use reconstruct::prior::oracle::view_labels;
use reconstruct::prior::source::{make_prior, PriorContext, PriorSource};
use reconstruct::render::effects::Effects;
use reconstruct::render::gbuffer::GBuffer;
use reconstruct::render::view::{render_view, PreparedLight, RenderSettings, ShadingMode};
use reconstruct::scene::{Camera, Dataset, Layout, Probe, SceneSpec};
use reconstruct::scene_data::default_scene::fixture_probe_dir;
use reconstruct::scene_data::synthetic::{encode_srgb, write_nerfactor, SyntheticScene};
use reconstruct::scene_data::{ground_truth_mesh, ground_truth_mesh_path, ground_truth_source, GroundTruthSource};

const RES: usize = 40;

fn tmp_dir(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("reconstruct-scene-any-{tag}-{}", std::process::id()));
    std::fs::remove_dir_all(&d).ok();
    std::fs::create_dir_all(&d).expect("test setup");
    d
}

/// A fresh temporary folder and its `data/gt` folder.
fn root_with_gt_folder(tag: &str) -> (PathBuf, PathBuf) {
    let root = tmp_dir(tag);
    let gt = root.join("data/gt");
    std::fs::create_dir_all(&gt).expect("test setup");
    (root, gt)
}

/// 4×4 texture codes: distinct 8-bit values so that a texel read back names its place.
fn codes(offset: u8) -> Vec<u8> {
    (0..16u8).map(|i| offset + 11 * i).collect()
}

/// An object of two parts (a body and a stand), both with UVs; materials are placeholders (the
/// ground truth's materials come from materials.json).
fn object() -> Mesh {
    let mut b = MeshBuilder::new();
    let body = b.part(PartMaterial::constant("Body", Vec3::ONE, 0.5, 0.0));
    b.ellipsoid(body, Vec3::new(0.0, 0.0, 0.35), Vec3::new(0.6, 0.45, 0.4), Quat::IDENTITY, 24, 12);
    let stand = b.part(PartMaterial::constant("Stand", Vec3::ONE, 0.5, 0.0));
    b.cylinder(stand, Vec2::ZERO, 0.8, -0.1, 0.0, 24);
    b.build()
}

fn cameras(count: usize, offset: f32) -> Vec<Camera> {
    (0..count)
        .map(|i| {
            let a = offset + std::f32::consts::TAU * i as f32 / count as f32;
            Camera::look_at(Vec3::new(3.0 * a.cos(), 3.0 * a.sin(), 1.6), Vec3::new(0.0, 0.0, 0.15), Vec3::Z, 0.7, RES, RES)
        })
        .collect()
}

fn sky() -> Image {
    let mut img = Image::new(16, 8, 3);
    for i in 0..img.pixel_count() {
        let up = 1.0 - (i / 16) as f32 / 8.0;
        img.set_rgb(i, Vec3::new(0.4 + 0.8 * up, 0.5 + 0.7 * up, 0.7 + 0.5 * up));
    }
    img
}

/// Render `mesh` into `data` (NeRFactor layout, split-sum: deterministic) and write a spec beside it.
fn write_scene(root: &Path, mesh: Mesh, gt_folder: Option<&str>) -> PathBuf {
    let data = root.join("data");
    let city = Probe::load(&fixture_probe_dir().join("city.hdr"), 1.0).expect("fixture probe");
    let scene = SyntheticScene {
        mesh,
        train_probe: Probe { name: "sky".into(), image: sky(), strength: 1.0 },
        train: cameras(3, 0.0),
        val: cameras(1, 0.5),
        test: cameras(1, 1.3),
        test_probes: vec![city],
    };
    let settings = RenderSettings { mode: ShadingMode::SplitSum, spp: 1, supersample: 1, seed: 3, effects: Effects::DIRECT };
    write_nerfactor(&scene, &data, &settings).expect("dataset written");
    let gt = gt_folder.map(|g| format!("[ground_truth]\nfolder = \"{g}\"\n")).unwrap_or_default();
    let spec = format!(
        "data = \"data\"\n[train_probe]\nfile = \"data/sky.exr\"\n[test_probes]\nnames = [\"city\"]\nfolders = [\"{{crate}}/tests/fixtures/probes\"]\n{gt}"
    );
    let path = root.join("scene.toml");
    std::fs::write(&path, spec).expect("test setup");
    path
}

/// The material of the mesh part named `part`.
fn material_of<'a>(mesh: &'a Mesh, part: &str) -> &'a PartMaterial {
    &mesh.materials[mesh.parts.iter().find(|p| p.name == part).unwrap_or_else(|| panic!("part {part} missing")).material]
}

/// Render views of `mesh` into `root/data` beside its gt/ folder, check that the render job
/// reproduces them from the ground truth it loads, and remove `root`.
fn render_with_views_then_remove(root: &Path, mesh: Mesh) {
    let spec_path = write_scene(root, mesh, Some("gt"));
    render_and_compare(&spec_path, &root.join("render"));
    std::fs::remove_dir_all(root).ok();
}

/// The render job reproduces the stored images from the ground truth it loads.
fn render_and_compare(spec_path: &Path, out: &Path) {
    let opts = RenderOptions {
        scene: spec_path.display().to_string(),
        data: None,
        views: vec![],
        probes: vec![],
        modes: vec![ShadingMode::SplitSum],
        spp: 1,
        supersample: 1,
        seed: 3,
        out: out.to_path_buf(),
    };
    let report = run(&opts).expect("render job");
    assert_eq!(report.renders.len(), 2, "one test view under the training probe and city");
    for r in &report.renders {
        let psnr = r.psnr_db.expect("the dataset has this image");
        println!("{} under {}: {psnr:.2} dB", r.view, r.probe);
        // Same renderer, same deterministic mode: only 8-bit quantisation separates the two.
        assert!(psnr > 40.0, "{} under {}: {psnr:.2} dB", r.view, r.probe);
    }
}

#[test]
fn differently_named_obj_with_textured_roughness_and_metallic_loads_renders_and_keeps_its_materials() {
    let (root, gt) = root_with_gt_folder("cow");
    write_obj(gt.join("cow.obj"), &object(), &[]).expect("test setup");
    let (rough, metal) = (codes(20), codes(60));
    image::GrayImage::from_raw(4, 4, rough.clone()).expect("test setup").save(gt.join("hide_rough.png")).expect("test setup");
    image::GrayImage::from_raw(4, 4, metal.clone()).expect("test setup").save(gt.join("hide_metal.png")).expect("test setup");
    let mut colour = Image::new(4, 4, 3);
    for i in 0..16 {
        colour.set_rgb(i, Vec3::new(0.1 + 0.05 * i as f32, 0.3, 0.8 - 0.04 * i as f32));
    }
    save_srgb_texture(&gt.join("hide.png"), &colour).expect("test setup");
    let json = r#"{
        "parts": [ { "name": "Body", "material": "Hide" }, { "name": "Stand", "material": "Wood" } ],
        "materials": {
            "Hide": { "base_color": { "texture": "hide.png", "colorspace": "sRGB" },
                      "roughness": { "texture": "hide_rough.png" }, "metallic": { "texture": "hide_metal.png", "colorspace": "linear" },
                      "specular": 0.5, "note": "extra keys are ignored" },
            "Wood": { "base_color": [0.45, 0.3, 0.15], "roughness": 0.35, "metallic": 0.0 }
        } }"#;
    std::fs::write(gt.join("materials.json"), json).expect("test setup");

    // Loaded before any view exists: the ground truth alone.
    let spec = SceneSpec::parse("data = \"data\"\n[ground_truth]\nfolder = \"gt\"\n", &root, "cow").expect("spec");
    assert_eq!(ground_truth_mesh_path(&spec).expect("found"), Some(gt.join("cow.obj")));
    let mesh = ground_truth_mesh(&spec).expect("ground truth loads");
    let hide = material_of(&mesh, "Body");
    let (Scalar::Texture(r), Scalar::Texture(m), BaseColor::Texture(c)) = (&hide.roughness, &hide.metallic, &hide.base_color) else {
        panic!("Hide should be textured: {hide:?}")
    };
    for (img, want) in [(r, &rough), (m, &metal)] {
        assert_eq!((img.width, img.height, img.channels), (4, 4, 1));
        for (got, code) in img.data.iter().zip(want.iter()) {
            assert!((got - *code as f32 / 255.0).abs() < 1e-6, "texel {got} vs code {code}");
        }
    }
    // The base colour is decoded from sRGB: each texel is the linear value of its 8-bit code.
    let decoded = image::open(gt.join("hide.png")).expect("written").to_rgb8();
    for (got, code) in c.data.iter().zip(decoded.as_raw()) {
        assert!((got - srgb_to_linear(*code as f32 / 255.0)).abs() < 1e-6);
    }
    // Evaluated at a texel centre (4×4: u = 0.375 is column 1; v = 0.875 is row 0, the top row).
    let p = hide.eval(Vec2::new(0.375, 0.875));
    assert!((p.roughness - rough[1] as f32 / 255.0).abs() < 1e-6 && (p.metallic - metal[1] as f32 / 255.0).abs() < 1e-6, "{p:?}");
    let wood = material_of(&mesh, "Stand");
    assert_eq!((wood.roughness.constant(), wood.metallic.constant()), (Some(0.35), Some(0.0)));
    assert!(matches!(wood.base_color, BaseColor::Constant(c) if c == Vec3::new(0.45, 0.3, 0.15)));

    render_with_views_then_remove(&root, mesh);
}

#[test]
fn gltf_named_by_materials_json_beside_another_mesh_with_packed_roughness_metallic() {
    let (root, gt) = root_with_gt_folder("statue");
    write_gltf(gt.join("statue.gltf"), &object(), &[]).expect("test setup");
    // A second mesh in the folder: materials.json must say which one is the object.
    std::fs::write(gt.join("proxy.obj"), "o p\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n").expect("test setup");
    // One RGB image packing roughness (green) and metallic (blue), as glTF's metallicRoughness does.
    let packed: Vec<u8> = (0..16u8).flat_map(|i| [0, 30 + 10 * i, 200 - 12 * i]).collect();
    image::RgbImage::from_raw(4, 4, packed.clone()).expect("test setup").save(gt.join("orm.png")).expect("test setup");
    let json = r#"{ "mesh": "statue.gltf",
        "materials": {
            "Body": { "base_color": [0.7, 0.2, 0.1], "roughness": { "texture": "orm.png", "channel": 1 }, "metallic": { "texture": "orm.png", "channel": 2 } },
            "Stand": { "base_color": [0.2, 0.2, 0.25], "roughness": 0.9, "metallic": 1.0 }
        } }"#;
    std::fs::write(gt.join("materials.json"), json).expect("test setup");

    let spec = SceneSpec::parse("data = \"data\"\n[ground_truth]\nfolder = \"gt\"\n", &root, "statue").expect("spec");
    assert_eq!(ground_truth_source(&spec).expect("found"), Some(GroundTruthSource::File(gt.join("statue.gltf"))));
    let mesh = ground_truth_mesh(&spec).expect("ground truth loads");
    // No `parts` list: each part takes the material named like it.
    let body = material_of(&mesh, "Body");
    let (Scalar::Texture(r), Scalar::Texture(m)) = (&body.roughness, &body.metallic) else { panic!("Body should be textured") };
    for (k, px) in packed.chunks_exact(3).enumerate() {
        assert!((r.data[k] - px[1] as f32 / 255.0).abs() < 1e-6 && (m.data[k] - px[2] as f32 / 255.0).abs() < 1e-6, "texel {k}");
    }
    let stand = material_of(&mesh, "Stand");
    assert_eq!((stand.roughness.constant(), stand.metallic.constant()), (Some(0.9), Some(1.0)));

    render_with_views_then_remove(&root, mesh);
}

#[test]
fn simulated_labels_come_from_the_views_depth_maps_without_a_ground_truth_folder() {
    let root = tmp_dir("sim");
    let mesh = object();
    let bvh = Bvh::build(&mesh);
    write_scene(&root, mesh.clone(), None);
    let dataset = Dataset::load(&root.join("data")).expect("loads");
    // depth.exr back-projects onto the surface the camera sees (interior pixels: full coverage).
    let view = &dataset.train[0];
    let points = depth_points(view).expect("readable").expect("the view has depth.exr");
    let g = GBuffer::trace(&mesh, &bvh, &view.camera);
    let alpha = view.load_alpha().expect("alpha");
    let mut compared = 0;
    for (i, (p, s)) in points.iter().zip(&g.surfels).enumerate() {
        if let (Some(p), Some(s), true) = (p, s, alpha.data[i] > 0.999) {
            assert!((*p - s.position).length() < 1e-3, "pixel {i}: {p} vs {}", s.position);
            compared += 1;
        }
    }
    assert!(compared > RES * RES / 10, "only {compared} pixels compared");
    // The simulator needs no mesh and no gt/ folder; at level 0 it is the oracle.
    let ctx = PriorContext { idarb_weights: None, cache_dir: root.clone(), idarb: Default::default(), seed: 5 };
    let zero = make_prior(&PriorSource::IdarbSim(0.0), &ctx).expect("prior").labels(&dataset, &[0, 2]).expect("labels");
    let one = make_prior(&PriorSource::IdarbSim(1.0), &ctx).expect("prior").labels(&dataset, &[0, 2]).expect("labels");
    let truth = view_labels(&dataset.train[0]).expect("oracle");
    let (z, o) = (zero[0].as_ref().expect("labelled"), one[0].as_ref().expect("labelled"));
    let diff = |a: &Image, b: &Image| a.data.iter().zip(&b.data).map(|(x, y)| (x - y).abs()).fold(0.0f32, f32::max);
    assert!(diff(&z.roughness, &truth.roughness) < 1e-6 && diff(&z.albedo, &truth.albedo) < 1e-4);
    assert!(diff(&o.roughness, &truth.roughness) > 0.01, "level 1 changed nothing");
    std::fs::remove_dir_all(&root).ok();
}

#[test]
fn nerf_synthetic_scene_without_maps_loads_and_evaluation_says_what_it_cannot_compute() {
    let root = tmp_dir("nerf");
    let mesh = object();
    let bvh = Bvh::build(&mesh);
    let light = CubeMap::constant(16, Vec3::splat(0.8));
    let prepared = PreparedLight::new(light.clone());
    let settings = RenderSettings { mode: ShadingMode::SplitSum, spp: 1, supersample: 1, seed: 1, effects: Effects::DIRECT };
    for (split, cams) in [("train", cameras(3, 0.0)), ("val", cameras(1, 0.5)), ("test", cameras(1, 1.3))] {
        std::fs::create_dir_all(root.join(split)).expect("test setup");
        let mut frames = Vec::new();
        for (i, cam) in cams.iter().enumerate() {
            io::write_png(&root.join(format!("{split}/r_{i}.png")), &encode_srgb(&render_view(&mesh, &bvh, &prepared, cam, &settings))).expect("test setup");
            let rows = cam.c2w.transpose().to_cols_array_2d();
            frames.push(serde_json::json!({ "file_path": format!("./{split}/r_{i}"), "rotation": 0.0, "transform_matrix": rows }));
        }
        let json = serde_json::json!({ "camera_angle_x": 0.7, "frames": frames });
        std::fs::write(root.join(format!("transforms_{split}.json")), json.to_string()).expect("test setup");
    }
    let spec = SceneSpec::parse("data = \".\"\n[ground_truth]\nfolder = \"gt\"\n", &root, "nerf").expect("spec");
    let dataset = spec.load_dataset().expect("a NeRF-synthetic folder loads");
    assert!(dataset.train.iter().all(|v| v.layout == Layout::NerfSynthetic));
    // No gt/ folder in the data: no ground truth, and asking for the mesh says so.
    assert_eq!(ground_truth_source(&spec).expect("no error"), None);
    let msg = format!("{:#}", ground_truth_mesh(&spec).unwrap_err());
    assert!(msg.contains("no ground-truth mesh") && msg.contains("gt"), "{msg}");

    let textures = MaterialTextures::constant(8, Vec3::splat(0.5), 0.5, 0.0);
    let mut atlas_mesh = mesh.clone();
    atlas_mesh.uvs.iter_mut().for_each(|uv| *uv = Vec2::splat(0.5));
    let city = Probe::load(&fixture_probe_dir().join("city.hdr"), 1.0).expect("fixture probe");
    let eval_settings = EvalSettings {
        relight_mode: ShadingMode::SplitSum,
        spp: 1,
        supersample: 1,
        seed: 1,
        effects: Effects::DIRECT,
        train_mode: ShadingMode::SplitSum,
        train_view_stride: 1,
        max_test_views: None,
    };
    let e = evaluate(&dataset, &atlas_mesh, &Bvh::build(&atlas_mesh), &textures, &light, &[city], &eval_settings).expect("evaluation runs").metrics;
    assert!(e.train_psnr.is_some_and(f64::is_finite) && e.val_psnr.is_some(), "what the images allow is computed");
    assert!(e.albedo_psnr_raw.is_none() && e.roughness_mse.is_none() && e.relight_psnr_raw.is_none());
    let said = e.not_computed.join("\n");
    assert!(said.contains("albedo.png") && said.contains("rgba_<probe>.png") && said.contains("city"), "{said}");
    std::fs::remove_dir_all(&root).ok();
}

#[test]
fn nerfactor_scene_files_name_the_missing_data_folder_and_point_at_data() {
    for name in ["nerfactor_hotdog", "nerfactor_ficus", "nerfactor_lego", "nerfactor_drums"] {
        let spec = SceneSpec::find(name).expect("scene file parses");
        assert_eq!(spec.gt_dir(), Some(spec.data_dir.join("gt")));
        let missing = std::env::temp_dir().join(format!("reconstruct-no-such-data-{name}"));
        let msg = format!("{:#}", spec.with_data_dir(&missing).load_dataset().unwrap_err());
        assert!(msg.contains(&missing.display().to_string()) && msg.contains("--data"), "{name}: {msg}");
    }
}

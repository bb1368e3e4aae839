//! Every loader on random and mutated input (proptest, a fixed number of cases per loader, stated in
//! `CASES` and printed when the test ends). Mutations start from small valid files the project's own
//! writers make (PNG, EXR, OBJ/MTL, glTF/GLB, checkpoints; the JSON and TOML text the formats define;
//! the committed CC0 probe for Radiance HDR) and flip bits, overwrite bytes, truncate, delete, insert,
//! splice a chunk from elsewhere in the file, or replace a number by an extreme one. For each case:
//! the loader must not panic (caught with `catch_unwind`), and when it refuses the file, its error
//! must name the file. Headers claiming 2³¹ × 2³¹ pixels are refused before allocation (their own
//! tests below). A hang would stop the suite (there is no timed assertion). The random source has a
//! fixed seed, so every run tries the same cases.

use std::io::Write;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

use anyhow::Result;
use candle_core::{DType, Device, Tensor};
use glam::{Quat, Vec2, Vec3};
use proptest::prelude::*;
use proptest::test_runner::{Config, TestRng, TestRunner};
use reconstruct::fit::checkpoint::{self, Progress};
use reconstruct::geometry::gltf_io::{load_gltf, write_gltf};
use reconstruct::geometry::ground_truth::load_ground_truth;
use reconstruct::geometry::obj::{load_obj, write_obj, MaterialTextureNames};
use reconstruct::geometry::primitives::MeshBuilder;
use reconstruct::geometry::Mesh;
use reconstruct::image::io::{read_exr, read_hdr, read_png, write_exr, write_exr_channels, write_png, write_png16};
use reconstruct::image::Image;
use reconstruct::material::{BaseColor, PartMaterial, Scalar};
use reconstruct::optim::adam::AdamState;
use reconstruct::prior::idarb::autoencoder_kl::AutoencoderKLConfig;
use reconstruct::prior::idarb::unet_dr2d_condition::UNetDR2DConfig;
use reconstruct::prior::idarb::weights::{build_pipeline, load_text_embeddings, TEXT_EMBEDDINGS_KEY};
use reconstruct::prior::labels_dir::LabelsDir;
use reconstruct::prior::source::Prior;
use reconstruct::scene::{crate_dir, Dataset, SceneSpec};

/// Cases per loader: enough that every mutation kind hits every region of the small seed files many
/// times, few enough that this file runs in seconds in release. (The IDArb weights case builds a
/// small network per case, so it gets fewer.)
const CASES: u32 = 500;
const CASES_WEIGHTS: u32 = 200;

/// A fresh folder for one test.
fn tmp(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("reconstruct-fuzz-{tag}-{}", std::process::id()));
    std::fs::remove_dir_all(&d).ok();
    std::fs::create_dir_all(&d).expect("test setup");
    d
}

/// One edit of a file's bytes; positions are taken modulo the length.
#[derive(Clone, Debug)]
enum Mutation {
    FlipBit(usize, u8),
    SetByte(usize, u8),
    Truncate(usize),
    Delete(usize, usize),
    Insert(usize, Vec<u8>),
    /// Copy `len` bytes from `from` over `to` (chunks and headers in the wrong place).
    Splice(usize, usize, usize),
    /// Replace the k-th run of ASCII digits by an extreme number (text formats).
    Number(usize, &'static str),
}

const EXTREMES: [&str; 10] = ["0", "-1", "4294967295", "2147483648", "99999999999999999999", "1e39", "-1e39", "nan", "inf", "1e-45"];

fn mutation() -> impl Strategy<Value = Mutation> {
    prop_oneof![
        (any::<usize>(), 0u8..8).prop_map(|(p, b)| Mutation::FlipBit(p, b)),
        (any::<usize>(), prop_oneof![Just(0u8), Just(0xff), Just(0x7f), Just(0x80), any::<u8>()]).prop_map(|(p, v)| Mutation::SetByte(p, v)),
        any::<usize>().prop_map(Mutation::Truncate),
        (any::<usize>(), 1usize..64).prop_map(|(p, n)| Mutation::Delete(p, n)),
        (any::<usize>(), prop::collection::vec(any::<u8>(), 1..16)).prop_map(|(p, b)| Mutation::Insert(p, b)),
        (any::<usize>(), any::<usize>(), 1usize..64).prop_map(|(a, b, n)| Mutation::Splice(a, b, n)),
        (any::<usize>(), prop::sample::select(EXTREMES.to_vec())).prop_map(|(k, s)| Mutation::Number(k, s)),
    ]
}

fn apply(seed: &[u8], edits: &[Mutation]) -> Vec<u8> {
    let mut b = seed.to_vec();
    for e in edits {
        let n = b.len().max(1);
        match e {
            Mutation::FlipBit(p, bit) if !b.is_empty() => b[p % n] ^= 1 << bit,
            Mutation::SetByte(p, v) if !b.is_empty() => b[p % n] = *v,
            Mutation::Truncate(p) => b.truncate(p % n),
            Mutation::Delete(p, len) if !b.is_empty() => {
                let start = p % n;
                b.drain(start..(start + len).min(b.len()));
            }
            Mutation::Insert(p, bytes) => {
                let at = p % (b.len() + 1);
                b.splice(at..at, bytes.iter().copied());
            }
            Mutation::Splice(from, to, len) if !b.is_empty() => {
                let (from, to) = (from % n, to % n);
                let len = (*len).min(b.len() - from).min(b.len() - to);
                let chunk = b[from..from + len].to_vec();
                b[to..to + len].copy_from_slice(&chunk);
            }
            Mutation::Number(k, s) => {
                let runs: Vec<(usize, usize)> = digit_runs(&b);
                if !runs.is_empty() {
                    let (start, end) = runs[k % runs.len()];
                    b.splice(start..end, s.bytes());
                }
            }
            _ => {}
        }
    }
    b
}

fn digit_runs(b: &[u8]) -> Vec<(usize, usize)> {
    let mut runs = Vec::new();
    let mut i = 0;
    while i < b.len() {
        if b[i].is_ascii_digit() {
            let start = i;
            while i < b.len() && b[i].is_ascii_digit() {
                i += 1;
            }
            runs.push((start, i));
        } else {
            i += 1;
        }
    }
    runs
}

/// Input bytes: mostly the seed mutated 1–4 times, sometimes random bytes (after the seed's first
/// `magic` bytes, so the format is still recognised and the decoder gets past its signature).
fn input(seed: Vec<u8>, magic: usize) -> impl Strategy<Value = Vec<u8>> {
    let head = seed[..magic.min(seed.len())].to_vec();
    prop_oneof![
        4 => prop::collection::vec(mutation(), 1..5).prop_map(move |m| apply(&seed, &m)),
        1 => prop::collection::vec(any::<u8>(), 0..512).prop_map(move |r| [head.clone(), r].concat()),
    ]
}

thread_local! {
    /// Cases the loader refused, in the current test (each test runs on its own thread).
    static REFUSED: std::cell::Cell<usize> = const { std::cell::Cell::new(0) };
}

/// Runs `load` on a case: it must not panic, and an error must name one of `names`.
fn check<T>(what: &str, names: &[&str], load: impl FnOnce() -> Result<T>) {
    match catch_unwind(AssertUnwindSafe(load)) {
        Err(_) => panic!("{what}: the loader panicked (message above)"),
        Ok(Ok(_)) => {}
        Ok(Err(e)) => {
            REFUSED.with(|r| r.set(r.get() + 1));
            let msg = format!("{e:#}");
            assert!(names.iter().any(|n| msg.contains(n)), "{what}: the error does not name {names:?}: {msg}");
        }
    }
}

/// Runs `cases` cases of `strategy` through `body`, counts them and prints the count.
fn fuzz<S: Strategy>(what: &str, cases: u32, strategy: S, body: impl FnMut(S::Value)) {
    let count = AtomicUsize::new(0);
    // The runner takes a `Fn`; the bodies keep per-case state.
    let body = std::cell::RefCell::new(body);
    let config = Config { cases, failure_persistence: None, ..Config::default() };
    // A fixed seed: the same cases every run, so a failure reproduces and the counts below are stable.
    let rng = TestRng::deterministic_rng(config.rng_algorithm);
    let mut runner = TestRunner::new_with_rng(config, rng);
    runner
        .run(&strategy, |v| {
            count.fetch_add(1, Ordering::Relaxed);
            (body.borrow_mut())(v);
            Ok(())
        })
        .unwrap_or_else(|e| panic!("{what}: {e}"));
    let (n, refused) = (count.load(Ordering::Relaxed), REFUSED.with(|r| r.get()));
    let _ = writeln!(std::io::stderr(), "fuzz_loaders: {what}: {n} cases ({refused} refused, {} loaded), no panic, every refusal named the file", n - refused);
}

fn ramp(w: usize, h: usize, c: usize) -> Image {
    let mut img = Image::new(w, h, c);
    for (i, v) in img.data.iter_mut().enumerate() {
        *v = (i as f32 * 0.37).sin().abs();
    }
    img
}

#[test]
fn png_files() {
    let dir = tmp("png");
    let (rgba, grey16) = (dir.join("seed_rgba.png"), dir.join("seed_grey16.png"));
    write_png(&rgba, &ramp(5, 4, 4)).expect("test setup");
    write_png16(&grey16, &ramp(3, 6, 1)).expect("test setup");
    let seeds = [std::fs::read(&rgba).expect("test setup"), std::fs::read(&grey16).expect("test setup")];
    let path = dir.join("case.png");
    let strategy = prop_oneof![input(seeds[0].clone(), 8), input(seeds[1].clone(), 8)];
    fuzz("PNG (read_png)", CASES, strategy, |bytes| {
        std::fs::write(&path, &bytes).expect("test setup");
        check("PNG", &["case.png"], || read_png(&path));
    });
}

#[test]
fn radiance_hdr_files() {
    let dir = tmp("hdr");
    let seed = std::fs::read(crate_dir().join("tests/fixtures/probes/city.hdr")).expect("the committed CC0 probe");
    let path = dir.join("case.hdr");
    fuzz("Radiance HDR (read_hdr)", CASES, input(seed, 10), |bytes| {
        std::fs::write(&path, &bytes).expect("test setup");
        check("HDR", &["case.hdr"], || read_hdr(&path));
    });
}

#[test]
fn exr_files() {
    let dir = tmp("exr");
    let (rgb, depth) = (dir.join("seed_rgb.exr"), dir.join("seed_z.exr"));
    write_exr(&rgb, &ramp(4, 3, 3)).expect("test setup");
    write_exr_channels(&depth, &ramp(3, 2, 1), &["Z"]).expect("test setup");
    let seeds = [std::fs::read(&rgb).expect("test setup"), std::fs::read(&depth).expect("test setup")];
    let path = dir.join("case.exr");
    let strategy = prop_oneof![input(seeds[0].clone(), 4), input(seeds[1].clone(), 4)];
    fuzz("OpenEXR (read_exr)", CASES, strategy, |bytes| {
        std::fs::write(&path, &bytes).expect("test setup");
        check("EXR", &["case.exr"], || read_exr(&path));
    });
}

/// Two parts, one textured: what the exporters write.
fn small_mesh() -> Mesh {
    let mut b = MeshBuilder::new();
    let tex = Image::filled(2, 2, &[0.5, 0.25, 0.125]);
    let a = b.part(PartMaterial { name: "A".into(), base_color: BaseColor::Texture(std::sync::Arc::new(tex)), roughness: Scalar::Constant(0.4), metallic: Scalar::Constant(0.0) });
    let c = b.part(PartMaterial { name: "B".into(), base_color: BaseColor::Constant(Vec3::splat(0.7)), roughness: Scalar::Constant(0.8), metallic: Scalar::Constant(1.0) });
    b.ellipsoid(a, Vec3::ZERO, Vec3::ONE, Quat::IDENTITY, 5, 3);
    b.cylinder(c, Vec2::ZERO, 0.5, 1.0, 1.5, 5);
    b.build()
}

#[test]
fn obj_and_mtl_files() {
    let dir = tmp("obj");
    let names = vec![MaterialTextureNames { base_color: Some("kd.png".into()), ..Default::default() }];
    write_obj(dir.join("seed.obj"), &small_mesh(), &names).expect("test setup");
    write_png(&dir.join("kd.png"), &ramp(2, 2, 3)).expect("test setup");
    let obj = std::fs::read(dir.join("seed.obj")).expect("test setup");
    let mtl = std::fs::read(dir.join("seed.mtl")).expect("test setup");
    let png = std::fs::read(dir.join("kd.png")).expect("test setup");
    // The OBJ mutated (its MTL intact), the MTL mutated, or the texture the MTL names mutated.
    let strategy = prop_oneof![
        input(obj.clone(), 0).prop_map(|b| (0, b)),
        input(mtl.clone(), 0).prop_map(|b| (1, b)),
        input(png.clone(), 8).prop_map(|b| (2, b)),
    ];
    fuzz("OBJ + MTL + texture (load_obj)", CASES, strategy, |(which, bytes)| {
        let case = dir.join("case");
        std::fs::create_dir_all(&case).expect("test setup");
        let files = [obj.clone(), mtl.clone(), png.clone()];
        for (k, name) in ["seed.obj", "seed.mtl", "kd.png"].iter().enumerate() {
            std::fs::write(case.join(name), if k == which { &bytes } else { &files[k] }).expect("test setup");
        }
        let named: &[&str] = match which {
            0 => &["seed.obj"],
            1 => &["seed.mtl", "seed.obj"],
            _ => &["kd.png"],
        };
        check("OBJ", named, || load_obj(case.join("seed.obj")));
    });
}

#[test]
fn gltf_and_glb_files() {
    let dir = tmp("gltf");
    let mesh = small_mesh();
    write_gltf(dir.join("seed.glb"), &mesh, &[]).expect("test setup");
    write_gltf(dir.join("seed.gltf"), &mesh, &[]).expect("test setup");
    let glb = std::fs::read(dir.join("seed.glb")).expect("test setup");
    let json = std::fs::read(dir.join("seed.gltf")).expect("test setup");
    let bin_name = std::fs::read_dir(&dir).expect("test setup").filter_map(|e| e.ok()).map(|e| e.file_name().to_string_lossy().into_owned()).find(|n| n.ends_with(".bin")).expect("a .bin beside the .gltf");
    let bin = std::fs::read(dir.join(&bin_name)).expect("test setup");
    let strategy = prop_oneof![input(glb, 12).prop_map(|b| (0, b)), input(json.clone(), 0).prop_map(|b| (1, b)), input(bin.clone(), 0).prop_map(|b| (2, b))];
    fuzz("glTF / GLB (load_gltf)", CASES, strategy, |(which, bytes)| {
        if which == 0 {
            let path = dir.join("case.glb");
            std::fs::write(&path, &bytes).expect("test setup");
            check("GLB", &["case.glb"], || load_gltf(&path));
        } else {
            let (j, b) = if which == 1 { (bytes.as_slice(), bin.as_slice()) } else { (json.as_slice(), bytes.as_slice()) };
            std::fs::write(dir.join("seed.gltf"), j).expect("test setup");
            std::fs::write(dir.join(&bin_name), b).expect("test setup");
            check("glTF", &["seed.gltf", bin_name.as_str()], || load_gltf(dir.join("seed.gltf")));
        }
    });
}

#[test]
fn materials_json_files() {
    let dir = tmp("materials");
    std::fs::write(dir.join("m.obj"), "o tri\nv 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nf 1/1 2/2 3/3\n").expect("test setup");
    write_png(&dir.join("r.png"), &ramp(2, 2, 1)).expect("test setup");
    let seed = br#"{"mesh": "m.obj", "parts": [{"name": "tri", "material": "M"}],
        "materials": {"M": {"base_color": [0.1, 0.2, 0.3], "roughness": {"texture": "r.png", "channel": 0}, "metallic": 0.5}}}"#
        .to_vec();
    let path = dir.join("materials.json");
    fuzz("materials.json (load_ground_truth)", CASES, input(seed, 0), |bytes| {
        std::fs::write(&path, &bytes).expect("test setup");
        check("materials.json", &["materials.json"], || load_ground_truth(&dir));
    });
}

/// A one-view NeRF-synthetic dataset (4×4 RGBA) and a NeRFactor-layout view with its metadata.json.
fn tiny_datasets(dir: &Path) -> (Vec<u8>, Vec<u8>) {
    std::fs::create_dir_all(dir.join("synthetic/train")).expect("test setup");
    write_png(&dir.join("synthetic/train/r_0.png"), &ramp(4, 4, 4)).expect("test setup");
    let transforms = br#"{"camera_angle_x": 0.69, "frames": [{"file_path": "./train/r_0", "rotation": 0.1,
        "transform_matrix": [[1, 0, 0, 0], [0, 0.6, -0.8, -3.2], [0, 0.8, 0.6, 2.4], [0, 0, 0, 1]]}]}"#
        .to_vec();
    std::fs::create_dir_all(dir.join("nerfactor/train_000")).expect("test setup");
    write_png(&dir.join("nerfactor/train_000/rgba.png"), &ramp(4, 4, 4)).expect("test setup");
    std::fs::write(
        dir.join("nerfactor/transforms_train.json"),
        r#"{"camera_angle_x": 0.69, "frames": [{"file_path": "./train_000/rgba", "transform_matrix": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]]}]}"#,
    )
    .expect("test setup");
    let metadata = br#"{"scene": "tiny", "cam_transform_mat": "1,0,0,0,0,1,0,0,0,0,1,4,0,0,0,1", "cam_angle_x": 0.69, "envmap": "2163", "envmap_inten": 3, "imh": 4, "imw": 4, "spp": 64}"#.to_vec();
    (transforms, metadata)
}

#[test]
fn transforms_and_metadata_json_files() {
    let dir = tmp("dataset");
    let (transforms, metadata) = tiny_datasets(&dir);
    let strategy = prop_oneof![input(transforms, 0).prop_map(|b| (0, b)), input(metadata, 0).prop_map(|b| (1, b))];
    fuzz("transforms_*.json and metadata.json (Dataset::load)", CASES, strategy, |(which, bytes)| {
        if which == 0 {
            std::fs::write(dir.join("synthetic/transforms_train.json"), &bytes).expect("test setup");
            check("transforms", &["transforms_train.json"], || Dataset::load(&dir.join("synthetic")));
        } else {
            std::fs::write(dir.join("nerfactor/train_000/metadata.json"), &bytes).expect("test setup");
            check("metadata", &["metadata.json"], || Dataset::load(&dir.join("nerfactor")));
        }
    });
}

#[test]
fn scene_spec_toml_files() {
    let dir = tmp("spec");
    let seed = std::fs::read(crate_dir().join("scenes/default.toml")).expect("the default scene spec");
    let path = dir.join("case.toml");
    fuzz("scene spec TOML (SceneSpec::load)", CASES, input(seed, 0), |bytes| {
        std::fs::write(&path, &bytes).expect("test setup");
        check("scene spec", &["case.toml"], || SceneSpec::load(&path));
    });
}

#[test]
fn label_files() {
    let dir = tmp("labels");
    let (transforms, _) = tiny_datasets(&dir);
    std::fs::write(dir.join("synthetic/transforms_train.json"), transforms).expect("test setup");
    let dataset = Dataset::load(&dir.join("synthetic")).expect("test setup");
    // The strip layout: [albedo | normal | metallic | roughness], each 4×4.
    let labels = dir.join("labels");
    std::fs::create_dir_all(&labels).expect("test setup");
    write_png(&labels.join("seed.png"), &ramp(16, 4, 3)).expect("test setup");
    let seed = std::fs::read(labels.join("seed.png")).expect("test setup");
    std::fs::remove_file(labels.join("seed.png")).expect("test setup");
    let prior = LabelsDir::open(&labels).expect("test setup");
    let path = labels.join("r_0.png");
    fuzz("label files (--prior labels:DIR)", CASES, input(seed, 8), |bytes| {
        std::fs::write(&path, &bytes).expect("test setup");
        check("labels", &["r_0.png"], || prior.labels(&dataset, &[0]));
    });
}

#[test]
fn checkpoint_files() {
    let dir = tmp("checkpoint");
    let dev = Device::Cpu;
    let t = |n: usize, v: f32| Tensor::full(v, (n, 1, 3), &dev).expect("test setup");
    let adam = AdamState { step: 3, slots: vec![("kd".into(), t(4, 0.1), t(4, 0.01), 3)] };
    let mut progress = Progress {
        iteration: 0,
        state_file: String::new(),
        identity: serde_json::json!("fuzz"),
        history: Vec::new(),
        adam_step: 3,
        adam_slots: vec![("kd".into(), 3)],
    };
    let seed_dir = dir.join("seed");
    checkpoint::save(&seed_dir, &t(4, 0.5), &t(4, 0.25), &t(6, 1.0), &adam, Vec::new(), &mut progress).expect("test setup");
    let files: Vec<(String, Vec<u8>)> = std::fs::read_dir(&seed_dir)
        .expect("test setup")
        .filter_map(|e| e.ok())
        .map(|e| (e.file_name().to_string_lossy().into_owned(), std::fs::read(e.path()).expect("test setup")))
        .collect();
    assert!(files.len() >= 2, "a checkpoint is at least tensors and progress: {:?}", files.iter().map(|f| &f.0).collect::<Vec<_>>());
    let strategy = (0..files.len()).prop_flat_map({
        let files = files.clone();
        move |k| input(files[k].1.clone(), 0).prop_map(move |b| (k, b))
    });
    let case = dir.join("case");
    fuzz("checkpoint (checkpoint::load)", CASES, strategy, |(which, bytes)| {
        std::fs::create_dir_all(&case).expect("test setup");
        for (k, (name, seed)) in files.iter().enumerate() {
            std::fs::write(case.join(name), if k == which { &bytes } else { seed }).expect("test setup");
        }
        let names: Vec<&str> = files.iter().map(|f| f.0.as_str()).collect();
        check("checkpoint", &names, || checkpoint::load(&case));
    });
}

fn idarb_fixtures() -> PathBuf {
    crate_dir().join("tests/fixtures/idarb")
}

#[test]
fn idarb_prompt_embeddings_files() {
    let dir = tmp("embeddings");
    let dev = Device::Cpu;
    let seed_path = dir.join("seed.safetensors");
    let tensor = Tensor::arange(0f32, 3.0 * 4.0 * 8.0, &dev).and_then(|t| t.reshape((3, 4, 8))).expect("test setup");
    candle_core::safetensors::save(&std::collections::HashMap::from([(TEXT_EMBEDDINGS_KEY.to_string(), tensor)]), &seed_path).expect("test setup");
    let seed = std::fs::read(&seed_path).expect("test setup");
    let path = dir.join("case.safetensors");
    fuzz("IDArb prompt embeddings (load_text_embeddings)", CASES, input(seed, 0), |bytes| {
        std::fs::write(&path, &bytes).expect("test setup");
        check("embeddings", &["case.safetensors"], || load_text_embeddings(&path, &Device::Cpu));
    });
}

#[test]
fn idarb_weight_files() {
    let dir = tmp("weights");
    let fx = idarb_fixtures();
    let unet_config = UNetDR2DConfig::from_json_file(&fx.join("tiny_unet_config.json")).expect("fixture");
    let vae_config = AutoencoderKLConfig::from_json_file(&fx.join("tiny_vae_config.json")).expect("fixture");
    let unet = fx.join("tiny_unet.safetensors");
    let seed = std::fs::read(fx.join("tiny_vae.safetensors")).expect("fixture");
    // Mutations where a safetensors file is fragile: the 8-byte length and the JSON header after it
    // (the tensor data, megabytes of floats, only changes values).
    let header_len = 8 + u64::from_le_bytes(seed[..8].try_into().expect("8 bytes")) as usize;
    let head = seed[..header_len].to_vec();
    let tail = seed[header_len..].to_vec();
    let text = Tensor::zeros((3, 77, unet_config.cross_attention_dim), DType::F32, &Device::Cpu).expect("test setup");
    let intact = dir.join("vae_intact.safetensors");
    std::fs::write(&intact, &seed).expect("test setup");
    build_pipeline(&unet_config, std::slice::from_ref(&unet), &vae_config, std::slice::from_ref(&intact), text.clone(), &Device::Cpu).expect("the unmutated weights load");
    let mut k = 0;
    // Mostly the header; a quarter of the cases edit anywhere in the file (values, truncation).
    let strategy = prop_oneof![3 => input(head, 0).prop_map(move |h| [h, tail.clone()].concat()), 1 => input(seed.clone(), 0)];
    fuzz("IDArb weights (build_pipeline, VAE safetensors)", CASES_WEIGHTS, strategy, |bytes| {
        // A new file per case: the previous one may still be memory-mapped by the last pipeline.
        k += 1;
        let path = dir.join(format!("vae_{k}.safetensors"));
        std::fs::write(&path, bytes).expect("test setup");
        check("weights", &[&format!("vae_{k}.safetensors")], || build_pipeline(&unet_config, std::slice::from_ref(&unet), &vae_config, std::slice::from_ref(&path), text.clone(), &Device::Cpu));
        std::fs::remove_file(&path).ok();
    });
}

// Headers that claim 2³¹ × 2³¹ pixels: refused, naming the file, before any pixel is allocated
// (an attempt to allocate 2⁶² pixels would abort the test process, not fail it).

/// CRC-32 (PNG's chunk checksum, ISO-HDLC polynomial), so the forged header passes the decoder's check.
fn crc32(bytes: &[u8]) -> u32 {
    let mut c = !0u32;
    for &b in bytes {
        c ^= b as u32;
        for _ in 0..8 {
            c = if c & 1 != 0 { 0xEDB8_8320 ^ (c >> 1) } else { c >> 1 };
        }
    }
    !c
}

/// A PNG whose IHDR claims `width` × `height` (CRC fixed so the decoder believes it).
fn forged_png(path: &Path, width: u32, height: u32) {
    write_png(path, &ramp(2, 2, 3)).expect("test setup");
    let mut b = std::fs::read(path).expect("test setup");
    // IHDR data starts at byte 16: width, height, then the CRC over chunk type + data.
    b[16..20].copy_from_slice(&width.to_be_bytes());
    b[20..24].copy_from_slice(&height.to_be_bytes());
    let crc = crc32(&b[12..29]);
    b[29..33].copy_from_slice(&crc.to_be_bytes());
    std::fs::write(path, &b).expect("test setup");
}

#[test]
fn a_png_header_claiming_2_to_the_31_squared_pixels_is_refused_naming_the_file() {
    let dir = tmp("huge-png");
    // PNG's largest, 2³¹ − 1 a side: the png crate's own memory limit refuses it first.
    let path = dir.join("huge.png");
    forged_png(&path, 0x7fff_ffff, 0x7fff_ffff);
    let msg = format!("{:#}", read_png(&path).unwrap_err());
    assert!(msg.contains("huge.png"), "{msg}");
    // One row, wider than our side limit: small enough for the crate, refused by ours, before decoding.
    let path = dir.join("wide.png");
    forged_png(&path, 1 << 16, 1);
    let msg = format!("{:#}", read_png(&path).unwrap_err());
    assert!(msg.contains("wide.png") && msg.contains("claims 65536×1"), "{msg}");
}

#[test]
fn an_hdr_header_claiming_2_to_the_31_squared_pixels_is_refused_naming_the_file() {
    let dir = tmp("huge-hdr");
    let path = dir.join("huge.hdr");
    std::fs::write(&path, b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 2147483648 +X 2147483648\n\x02\x02\x00\x10").expect("test setup");
    let msg = format!("{:#}", read_hdr(&path).unwrap_err());
    assert!(msg.contains("huge.hdr") && msg.contains("2147483648"), "{msg}");
}

#[test]
fn an_exr_header_claiming_2_to_the_31_squared_pixels_is_refused_naming_the_file() {
    let dir = tmp("huge-exr");
    // (the exr crate's own validation refuses 2³¹ a side; 40000² passes it and meets ours)
    for (name, side) in [("huge.exr", i32::MAX - 1), ("large.exr", 39_999)] {
        let path = dir.join(name);
        write_exr(&path, &ramp(2, 2, 3)).expect("test setup");
        let mut b = std::fs::read(&path).expect("test setup");
        // Both windows are box2i attributes: xMin, yMin, xMax, yMax (i32 each) after name, type and size 16.
        for attribute in [&b"dataWindow\0box2i\0"[..], &b"displayWindow\0box2i\0"[..]] {
            let at = b.windows(attribute.len()).position(|w| w == attribute).expect("the writer stores the window") + attribute.len() + 4;
            b[at..at + 16].copy_from_slice(&[0i32, 0, side, side].map(i32::to_le_bytes).concat());
        }
        std::fs::write(&path, &b).expect("test setup");
        let msg = format!("{:#}", read_exr(&path).unwrap_err());
        assert!(msg.contains(name), "{msg}");
        if side < i32::MAX - 1 {
            assert!(msg.contains("claims 40000×40000"), "{msg}");
        }
    }
}

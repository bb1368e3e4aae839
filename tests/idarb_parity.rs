//! Parity with the official IDArb implementation on the fixture cases (tiny random weights,
//! float32): VAE encode, every UNet forward and DDIM step, decode, labels, to ≤ 1e-4 max abs.
//! Fixture folder: `IDARB_FIXTURE_DIR`, else `tests/fixtures/idarb`; every `case_*.safetensors`
//! there is run, with sizes, views, poses and steps read from the case itself. Every check is
//! printed as it is made (worst difference per tensor) and a case fails after all its checks, so
//! a failing case shows its whole report.
use candle_core::{DType, Device, Tensor};
use reconstruct::image::Image;
use reconstruct::prior::idarb::autoencoder_kl::AutoencoderKLConfig;
use reconstruct::prior::idarb::labels::split_labels;
use reconstruct::prior::idarb::preprocess::{prepare_view, Framing};
use reconstruct::prior::idarb::scheduling_ddim::{DdimScheduler, ALPHA_AGREEMENT};
use reconstruct::prior::idarb::unet_dr2d_condition::UNetDR2DConfig;
use reconstruct::prior::idarb::weights::load_pipeline;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

const TOL: f32 = 1e-4;

fn fixture_dir() -> PathBuf {
    std::env::var_os("IDARB_FIXTURE_DIR").map(PathBuf::from).unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/idarb"))
}

fn max_abs(a: &Tensor, b: &Tensor) -> f32 {
    assert_eq!(a.dims(), b.dims(), "shape mismatch");
    (a - b).unwrap().abs().unwrap().flatten_all().unwrap().max(0).unwrap().to_scalar::<f32>().unwrap()
}

/// One check's line, printed at once; a failure is recorded and reported with the case.
fn check(name: &str, got: &Tensor, want: &Tensor, tol: f32, failures: &mut Vec<String>) {
    let d = max_abs(got, want);
    println!("  {name}: max |Δ| = {d:.2e}");
    if d > tol {
        failures.push(format!("{name}: max |Δ| = {d:e} > {tol:e}"));
    }
}

/// Schedule scalars against the reference's float32 values, compared in float64.
fn check_scalars(name: &str, got: &[f64], want: &Tensor, tol: f64, failures: &mut Vec<String>) {
    let want: Vec<f64> = want.to_dtype(DType::F64).unwrap().to_vec1().unwrap();
    if got.len() != want.len() {
        failures.push(format!("{name}: {} values, the case has {}", got.len(), want.len()));
        return;
    }
    let d = got.iter().zip(&want).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
    match tol > 0.0 {
        true => println!("  {name}: max |Δ| = {d:.2e} ({:.1} ulp of 1)", d / f32::EPSILON as f64),
        false => println!("  {name}: max |Δ| = {d:.2e}"),
    }
    if d > tol {
        failures.push(format!("{name}: max |Δ| = {d:e} > {tol:e}"));
    }
}

/// The safetensors header's `__metadata__` (string map).
fn metadata(path: &Path) -> HashMap<String, String> {
    let bytes = std::fs::read(path).expect("read case");
    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let header: serde_json::Value = serde_json::from_slice(&bytes[8..8 + n]).expect("header json");
    header.get("__metadata__").and_then(|m| serde_json::from_value(m.clone()).ok()).unwrap_or_default()
}

fn to_images(t: &Tensor) -> Vec<Image> {
    let (n, c, h, w) = t.dims4().unwrap();
    (0..n)
        .map(|i| {
            let planar = t.get(i).unwrap().flatten_all().unwrap().to_vec1::<f32>().unwrap();
            let mut img = Image::new(w, h, c);
            for p in 0..h * w {
                for ch in 0..c {
                    img.data[p * c + ch] = planar[ch * h * w + p];
                }
            }
            img
        })
        .collect()
}

fn image_to_tensor(img: &Image) -> Tensor {
    let (w, h, c) = (img.width, img.height, img.channels);
    let mut planar = vec![0f32; w * h * c];
    for p in 0..w * h {
        for ch in 0..c {
            planar[ch * w * h + p] = img.data[p * c + ch];
        }
    }
    Tensor::from_vec(planar, (1, c, h, w), &Device::Cpu).unwrap()
}

#[test]
fn official_fixture_cases_match() {
    let dir = fixture_dir();
    let mut cases: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("fixture folder {}: {e}", dir.display()))
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.file_name().and_then(|n| n.to_str()).is_some_and(|n| n.starts_with("case_") && n.ends_with(".safetensors")))
        .collect();
    cases.sort();
    assert!(!cases.is_empty(), "no case_*.safetensors in {}", dir.display());
    let dev = Device::Cpu;
    let unet_cfg = UNetDR2DConfig::from_json_file(&dir.join("tiny_unet_config.json")).unwrap();
    let vae_cfg = AutoencoderKLConfig::from_json_file(&dir.join("tiny_vae_config.json")).unwrap();
    for case in cases {
        println!("case {}", case.display());
        let mut failures = Vec::new();
        let t: HashMap<String, Tensor> = candle_core::safetensors::load(&case, &dev).unwrap();
        let g = |k: &str| t.get(k).unwrap_or_else(|| panic!("{}: no tensor {k}", case.display())).to_dtype(DType::F32).unwrap();
        let meta = metadata(&case);
        // text_embeddings [3, 77, C] live in the case file itself
        let pipe = load_pipeline(&unet_cfg, &[dir.join("tiny_unet.safetensors")], &vae_cfg, &[dir.join("tiny_vae.safetensors")], &case, &dev).unwrap();

        let images = g("images");
        let (n, _, h, w) = images.dims4().unwrap();
        let target: usize = meta.get("target_size").and_then(|s| s.parse().ok()).unwrap_or(h);
        assert_eq!((h, w), (target, target));

        // If the case carries the raw input, its framing must give the resized size.
        if let Some(raw) = t.get("raw_images") {
            let resized = g("resized_images");
            let (_, _, rh, rw) = raw.dims4().unwrap();
            let f = Framing::new(rw, rh, target);
            assert_eq!((f.resized_height, f.resized_width), (resized.dim(2).unwrap(), resized.dim(3).unwrap()));
        }

        // 1-2: mask and white background, exact.
        let prepared: Vec<_> = to_images(&images).iter().map(|im| prepare_view(im, target).unwrap()).collect();
        let rgb = Tensor::from_vec(prepared.iter().flat_map(|p| p.rgb_planar.clone()).collect::<Vec<_>>(), (n, 3, h, w), &dev).unwrap();
        let mask = Tensor::from_vec(prepared.iter().flat_map(|p| p.mask.clone()).collect::<Vec<_>>(), (n, 1, h, w), &dev).unwrap();
        check("image_masks", &mask, &g("image_masks"), 0.0, &mut failures);
        check("images_rgb", &rgb, &g("images_rgb"), 0.0, &mut failures);

        // 3-4: pose and prompts come straight from the case.
        let pose = g("pose");
        assert_eq!(pose.dims(), &[1, n, 4]);
        check("encoder_hidden_states", &pipe.context(n).unwrap(), &g("encoder_hidden_states"), 0.0, &mut failures);

        // 5: image latents.
        let image_latents = pipe.encode_images(&rgb).unwrap();
        check("image_latents", &image_latents, &g("image_latents"), TOL, &mut failures);

        // schedule
        let steps = g("timesteps").dim(0).unwrap();
        let sched = DdimScheduler::idarb(steps);
        let ts: Vec<f64> = sched.timesteps.iter().map(|&x| x as f64).collect();
        let prev: Vec<f64> = sched.prev_timesteps.iter().map(|&x| x as f64).collect();
        let (at, ap): (Vec<f64>, Vec<f64>) = (0..steps).map(|k| sched.alphas(k)).map(|(a, p)| (a as f64, p as f64)).unzip();
        // integer steps exactly; ᾱ within float32 resolution
        for (name, v, tol) in [("timesteps", ts, 0.0), ("prev_timesteps", prev, 0.0), ("alpha_prod_t", at, ALPHA_AGREEMENT), ("alpha_prod_t_prev", ap, ALPHA_AGREEMENT)] {
            check_scalars(name, &v, &g(name), tol, &mut failures);
        }

        // 6: every step, from the stored init noise (η = 0), fed our own latents.
        let mut step_reports = Vec::new();
        let latents = pipe
            .denoise(&image_latents, &pose, &g("init_noise"), &sched, 0.0, &mut |_| unreachable!("η = 0 draws no noise"), &mut |r| {
                step_reports.push((r.step, r.v_pred.clone(), r.latents.clone()));
                Ok(())
            })
            .unwrap();
        assert_eq!(step_reports.len(), steps);
        for (k, v, l) in &step_reports {
            check(&format!("v_pred_step_{k}"), v, &g(&format!("v_pred_step_{k}")), TOL, &mut failures);
            check(&format!("latents_after_step_{k}"), l, &g(&format!("latents_after_step_{k}")), TOL, &mut failures);
        }

        // 7: decode.
        let decoded = pipe.decode(&latents).unwrap();
        check("decoded", &decoded, &g("decoded"), TOL, &mut failures);

        // 8: labels through the same split and unframing as the library.
        let mut maps: HashMap<&str, Vec<Tensor>> = HashMap::new();
        for (v, p) in prepared.iter().enumerate() {
            let l = split_labels(&decoded, v, &p.mask, &p.framing).unwrap();
            for (name, img) in [("labels_albedo", &l.albedo), ("labels_normal", &l.normal), ("labels_metallic", &l.metallic), ("labels_roughness", &l.roughness)] {
                maps.entry(name).or_default().push(image_to_tensor(img));
            }
        }
        let mut names: Vec<&&str> = maps.keys().collect();
        names.sort();
        for name in names {
            check(name, &Tensor::cat(&maps[*name], 0).unwrap(), &g(name), TOL, &mut failures);
        }

        // 9: single UNet forwards at stored inputs and timesteps.
        let ins = g("unet_single_in");
        let tvals = g("unet_single_t").to_vec1::<f32>().unwrap();
        let outs = g("unet_single_out");
        let ctx = pipe.context(n).unwrap();
        for (i, tv) in tvals.iter().enumerate() {
            let out = pipe.unet.forward(&ins.get(i).unwrap(), *tv, &ctx, &pose, n).unwrap();
            check(&format!("unet_single_out[{i}] (t = {tv})"), &out, &outs.get(i).unwrap(), TOL, &mut failures);
        }
        assert!(failures.is_empty(), "{}: {} check(s) failed:\n  {}", case.display(), failures.len(), failures.join("\n  "));
    }
}

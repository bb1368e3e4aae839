//! `--prior idarb` from a weights folder in the official layout alone (`unet/`, `vae/`,
//! `text_encoder/`, `tokenizer/`; no prompt-embedding file): a tiny folder assembled from the parity
//! fixtures labels two views end to end, caches the prompt embeddings, writes the labels as
//! `<view>_<map>.png` (the `--prior labels:DIR` layout) and reuses them without the weights; a
//! text encoder of another width than the UNet's is refused naming both configs.
use candle_core::{Device, Tensor};
use reconstruct::image::Image;
use reconstruct::prior::idarb::labels::{labels_for_named_views, IdarbOptions};
use reconstruct::prior::idarb::text_embeddings::CACHE_SUBDIR;
use reconstruct::prior::idarb::weights::WeightFiles;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

fn fixtures() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/idarb")
}

/// A random CLIP text tower with the official key names, `hidden` wide, one layer, saved as
/// `text_encoder/model.safetensors` (f32) with its config.
fn write_text_encoder(root: &Path, hidden: usize) {
    let dev = Device::Cpu;
    let dir = root.join("text_encoder");
    std::fs::create_dir_all(&dir).unwrap();
    let mut t: HashMap<String, Tensor> = HashMap::new();
    let mut put = |k: &str, shape: &[usize], scale: f64, offset: f64| {
        let v = (Tensor::randn(0f32, 1.0, shape, &dev).unwrap() * scale).unwrap() + offset;
        t.insert(format!("text_model.{k}"), v.unwrap());
    };
    put("embeddings.token_embedding.weight", &[49408, hidden], 1.0, 0.0);
    put("embeddings.position_embedding.weight", &[77, hidden], 1.0, 0.0);
    let l = "encoder.layers.0";
    for p in ["q_proj", "k_proj", "v_proj", "out_proj"] {
        put(&format!("{l}.self_attn.{p}.weight"), &[hidden, hidden], (hidden as f64).powf(-0.5), 0.0);
        put(&format!("{l}.self_attn.{p}.bias"), &[hidden], 0.1, 0.0);
    }
    put(&format!("{l}.mlp.fc1.weight"), &[2 * hidden, hidden], (hidden as f64).powf(-0.5), 0.0);
    put(&format!("{l}.mlp.fc1.bias"), &[2 * hidden], 0.1, 0.0);
    put(&format!("{l}.mlp.fc2.weight"), &[hidden, 2 * hidden], (2.0 * hidden as f64).powf(-0.5), 0.0);
    put(&format!("{l}.mlp.fc2.bias"), &[hidden], 0.1, 0.0);
    for n in [format!("{l}.layer_norm1"), format!("{l}.layer_norm2"), "final_layer_norm".to_string()] {
        put(&format!("{n}.weight"), &[hidden], 0.1, 1.0);
        put(&format!("{n}.bias"), &[hidden], 0.1, 0.0);
    }
    candle_core::safetensors::save(&t, dir.join("model.safetensors")).unwrap();
    let config = serde_json::json!({
        "architectures": ["CLIPTextModel"], "model_type": "clip_text_model", "vocab_size": 49408,
        "hidden_size": hidden, "intermediate_size": 2 * hidden, "num_hidden_layers": 1,
        "num_attention_heads": 2, "max_position_embeddings": 77, "hidden_act": "gelu", "layer_norm_eps": 1e-5
    });
    std::fs::write(dir.join("config.json"), config.to_string()).unwrap();
}

/// The official layout from the fixtures: UNet and VAE as diffusers saves them, the fixture's
/// tokenizer, a text tower `hidden` wide.
fn weights_folder(tag: &str, hidden: usize) -> PathBuf {
    let root = std::env::temp_dir().join(format!("idarb_folder_{tag}_{}", std::process::id()));
    std::fs::remove_dir_all(&root).ok();
    for (sub, model) in [("unet", "tiny_unet"), ("vae", "tiny_vae")] {
        std::fs::create_dir_all(root.join(sub)).unwrap();
        std::fs::copy(fixtures().join(format!("{model}.safetensors")), root.join(sub).join("diffusion_pytorch_model.safetensors")).unwrap();
        std::fs::copy(fixtures().join(format!("{model}_config.json")), root.join(sub).join("config.json")).unwrap();
    }
    std::fs::create_dir_all(root.join("tokenizer")).unwrap();
    for e in std::fs::read_dir(fixtures().join("text/tokenizer")).unwrap() {
        let p = e.unwrap().path();
        std::fs::copy(&p, root.join("tokenizer").join(p.file_name().unwrap())).unwrap();
    }
    write_text_encoder(&root, hidden);
    root
}

/// A 40×24 RGBA view: an opaque disc of `colour` on transparent background.
fn view(colour: [f32; 3]) -> Image {
    let mut img = Image::new(40, 24, 4);
    for y in 0..24 {
        for x in 0..40 {
            let inside = ((x as f32 - 20.0).powi(2) + (y as f32 - 12.0).powi(2)) < 100.0;
            let px = img.pixel_mut(x, y);
            px[..3].copy_from_slice(&colour);
            px[3] = if inside { 1.0 } else { 0.0 };
        }
    }
    img
}

#[test]
fn official_layout_labels_views_and_writes_label_files() {
    // the tiny UNet cross-attends to 32-wide prompts
    let root = weights_folder("ok", 32);
    let cache_root = root.with_extension("cache");
    std::fs::remove_dir_all(&cache_root).ok();
    // the prompt cache lives under the project's cache folder; point it at a fresh one
    std::env::set_var("RECONSTRUCT_CACHE", &cache_root);
    let labels_dir = cache_root.join("idarb");
    let views = vec![view([0.8, 0.3, 0.2]), view([0.2, 0.5, 0.9])];
    let names = vec!["r_0".to_string(), "r_5".to_string()];
    let opts = IdarbOptions { target_size: 64, steps: 2, progress: false, ..IdarbOptions::default() };

    let labels = labels_for_named_views(&views, &names, None, &opts, Some(&root), &labels_dir).unwrap();
    assert_eq!(labels.len(), 2);
    for l in &labels {
        assert_eq!((l.albedo.width, l.albedo.height, l.albedo.channels), (40, 24, 3));
        assert_eq!((l.roughness.width, l.roughness.height, l.roughness.channels), (40, 24, 1));
        assert!(l.albedo.data.iter().chain(&l.roughness.data).all(|v| (0.0..=1.0).contains(v)));
    }
    // the prompt embeddings were computed once and cached
    let cached: Vec<_> = std::fs::read_dir(cache_root.join(CACHE_SUBDIR)).unwrap().collect();
    assert_eq!(cached.len(), 1);
    // labels as files in the `labels:DIR` per-map layout
    for n in &names {
        for m in ["albedo", "normal", "metallic", "roughness"] {
            let p = labels_dir.join(format!("{n}_{m}.png"));
            let img = reconstruct::image::io::read_png(&p).unwrap();
            assert_eq!((img.width, img.height), (40, 24), "{}", p.display());
        }
    }
    // reused without the weights: same labels, and under new names the files follow
    let renamed = vec!["train_000".to_string(), "train_001".to_string()];
    let again = labels_for_named_views(&views, &renamed, None, &opts, Some(Path::new("/nonexistent/weights")), &labels_dir).unwrap();
    let d = again[1].albedo.data.iter().zip(&labels[1].albedo.data).map(|(a, b)| (a - b).abs()).fold(0f32, f32::max);
    assert!(d <= 0.5 / 65535.0 + 1e-6, "cached labels differ by {d}");
    assert!(labels_dir.join("train_001_metallic.png").is_file());

    // a text tower of another width than the UNet's cross-attention: both configs named
    let wrong = weights_folder("wrong", 16);
    let err = WeightFiles::locate(&wrong).and_then(|f| f.load_with_cache(&Device::Cpu, &cache_root).map(|_| ())).unwrap_err();
    let msg = format!("{err:#}");
    assert!(msg.contains("text_encoder/config.json") && msg.contains("unet/config.json") && msg.contains("16"), "{msg}");
    // and a folder without its text encoder says which file is missing
    std::fs::remove_dir_all(wrong.join("text_encoder")).unwrap();
    let msg = format!("{:#}", WeightFiles::locate(&wrong).unwrap_err());
    assert!(msg.contains("text_encoder/config.json"), "{msg}");

    for d in [root, wrong, cache_root] {
        std::fs::remove_dir_all(d).ok();
    }
}

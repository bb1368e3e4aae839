//! Parity of the prompt path with the official stack (tests/fixtures/idarb/text, made by
//! tools/idarb/make_text_fixture.py with transformers): the tokenizer reproduces the ids of the real
//! SD-2.1 tokenizer exactly, the CLIP text tower reproduces `last_hidden_state` to ≤ 1e-5, the
//! embeddings are cached per weights folder, and a broken folder names the key and file at fault.
//! With `IDARB_WEIGHTS` set to the official folder, its full tokenizer must give the same ids, and
//! `text_embeddings.safetensors` (tools/idarb/make_text_embeddings.py), when present there, must
//! match the Rust embeddings.
use candle_core::{DType, Device, Tensor};
use reconstruct::prior::idarb::text_embeddings::{task_prompt_ids, TextEncoderFiles, CACHE_SUBDIR, TASK_PROMPTS};
use reconstruct::prior::idarb::tokenization_clip::ClipTokenizer;
use reconstruct::prior::idarb::weights::{load_text_embeddings, TEXT_EMBEDDINGS_FILE, WEIGHTS_ENV};
use serde_json::Value;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// The text tower's tolerance against the official output (float32 throughout).
const TOL: f32 = 1e-5;

fn fixture() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/idarb/text")
}

fn max_abs(a: &Tensor, b: &Tensor) -> f32 {
    assert_eq!(a.dims(), b.dims(), "shape mismatch");
    (a - b).unwrap().abs().unwrap().flatten_all().unwrap().max(0).unwrap().to_scalar::<f32>().unwrap()
}

fn cases() -> Vec<(String, Vec<u32>)> {
    let json: Value = serde_json::from_str(&std::fs::read_to_string(fixture().join("tokenizer_cases.json")).unwrap()).unwrap();
    json["cases"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| (c["text"].as_str().unwrap().to_string(), c["input_ids"].as_array().unwrap().iter().map(|v| v.as_u64().unwrap() as u32).collect()))
        .collect()
}

fn check_ids(tok: &ClipTokenizer, what: &str) {
    for (text, want) in cases() {
        let got = tok.encode_padded(&text).unwrap();
        assert_eq!(got, want, "{what}: ids of {text:?}");
    }
}

#[test]
fn tokenizer_reproduces_the_official_ids() {
    let tok = ClipTokenizer::from_dir(&fixture().join("tokenizer")).unwrap();
    assert_eq!((tok.pad_token_id, tok.model_max_length), (0, 77), "SD-2.x pads with '!' (id 0) to 77 tokens");
    check_ids(&tok, "fixture vocabulary");
    // the official folder's full vocabulary, when available
    if let Some(dir) = std::env::var_os(WEIGHTS_ENV).map(|d| PathBuf::from(d).join("tokenizer")).filter(|d| d.is_dir()) {
        check_ids(&ClipTokenizer::from_dir(&dir).unwrap(), &dir.display().to_string());
        println!("full tokenizer {} checked", dir.display());
    }
}

#[test]
fn text_tower_matches_the_official_hidden_states() {
    let dev = Device::Cpu;
    let want: HashMap<String, Tensor> = candle_core::safetensors::load(fixture().join("text_case.safetensors"), &dev).unwrap();
    let files = TextEncoderFiles::locate(&fixture()).unwrap();
    let (tok, model) = files.load(&dev).unwrap();
    let ids = task_prompt_ids(&tok, &dev).unwrap();
    let want_ids = want["input_ids"].to_dtype(DType::U32).unwrap();
    assert_eq!(ids.to_vec2::<u32>().unwrap(), want_ids.to_vec2::<u32>().unwrap(), "prompt ids");
    let got = model.forward(&ids).unwrap();
    let d = max_abs(&got, &want["last_hidden_state"]);
    println!("last_hidden_state [{}, 77, {}]: max |Δ| = {d:.2e}", TASK_PROMPTS.len(), model.config.hidden_size);
    assert!(d <= TOL, "last_hidden_state differs by {d:e} > {TOL:e}");
}

fn temp_dir(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("idarb_text_{tag}_{}", std::process::id()));
    std::fs::remove_dir_all(&d).ok();
    std::fs::create_dir_all(&d).unwrap();
    d
}

#[test]
fn embeddings_are_cached_per_folder_content() {
    let dev = Device::Cpu;
    let cache = temp_dir("cache");
    let files = TextEncoderFiles::locate(&fixture()).unwrap();
    let hashes = files.hashes().unwrap();
    let first = files.cached(&cache, &hashes, &dev).unwrap();
    let stored: Vec<PathBuf> = std::fs::read_dir(cache.join(CACHE_SUBDIR)).unwrap().map(|e| e.unwrap().path()).collect();
    assert_eq!(stored.len(), 1, "{stored:?}");
    // the cached copy is what is returned the second time: overwrite it and see the change
    let marked = (first.clone() + 1.0).unwrap();
    candle_core::safetensors::save(&HashMap::from([("text_embeddings".to_string(), marked.clone())]), &stored[0]).unwrap();
    assert_eq!(max_abs(&files.cached(&cache, &hashes, &dev).unwrap(), &marked), 0.0);
    // other file contents → another key, computed afresh
    let mut other = hashes.clone();
    other[0].1 = "0000000000000000".into();
    assert_eq!(max_abs(&files.cached(&cache, &other, &dev).unwrap(), &first), 0.0);
    assert_eq!(std::fs::read_dir(cache.join(CACHE_SUBDIR)).unwrap().count(), 2);
    std::fs::remove_dir_all(&cache).ok();
}

/// Copy the fixture's text folders to a temp folder, then let `edit` break it.
fn broken_copy(tag: &str, edit: impl FnOnce(&Path)) -> PathBuf {
    let root = temp_dir(tag);
    for sub in ["text_encoder", "tokenizer"] {
        std::fs::create_dir_all(root.join(sub)).unwrap();
        for e in std::fs::read_dir(fixture().join(sub)).unwrap() {
            let p = e.unwrap().path();
            std::fs::copy(&p, root.join(sub).join(p.file_name().unwrap())).unwrap();
        }
    }
    edit(&root);
    root
}

fn load_error(root: &Path) -> String {
    let err = TextEncoderFiles::locate(root).and_then(|f| f.load(&Device::Cpu).map(|_| ()));
    format!("{:#}", err.expect_err("a broken folder must not load"))
}

#[test]
fn broken_folders_name_the_key_and_file() {
    let dev = Device::Cpu;
    let weights = |root: &Path| root.join("text_encoder/model.fp16.safetensors");

    // a missing tensor: the key and the weight file are named
    let key = "text_model.encoder.layers.1.mlp.fc2.weight";
    let root = broken_copy("missing", |r| {
        let mut t = candle_core::safetensors::load(weights(r), &dev).unwrap();
        t.remove(key).unwrap();
        candle_core::safetensors::save(&t, weights(r)).unwrap();
    });
    let msg = load_error(&root);
    assert!(msg.contains(key) && msg.contains("model.fp16.safetensors"), "{msg}");

    // a config of another size than the weights: the mismatched key is named
    let root2 = broken_copy("mismatch", |r| {
        let p = r.join("text_encoder/config.json");
        let mut cfg: Value = serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap();
        cfg["intermediate_size"] = 48.into();
        std::fs::write(&p, cfg.to_string()).unwrap();
    });
    let msg = load_error(&root2);
    assert!(msg.contains("fc1.weight") && msg.contains("config.json"), "{msg}");

    // another model's config (a vision tower)
    let root3 = broken_copy("arch", |r| {
        let p = r.join("text_encoder/config.json");
        let mut cfg: Value = serde_json::from_str(&std::fs::read_to_string(&p).unwrap()).unwrap();
        cfg["architectures"] = serde_json::json!(["CLIPVisionModel"]);
        std::fs::write(&p, cfg.to_string()).unwrap();
    });
    let msg = load_error(&root3);
    assert!(msg.contains("CLIPVisionModel") && msg.contains("text_encoder/config.json"), "{msg}");

    // missing files: named
    let root4 = broken_copy("nomerges", |r| std::fs::remove_file(r.join("tokenizer/merges.txt")).unwrap());
    let msg = load_error(&root4);
    assert!(msg.contains("tokenizer/merges.txt"), "{msg}");
    let root5 = broken_copy("noweights", |r| std::fs::remove_file(weights(r)).unwrap());
    let msg = load_error(&root5);
    assert!(msg.contains("text_encoder") && msg.contains("model*.safetensors"), "{msg}");
    for r in [root, root2, root3, root4, root5] {
        std::fs::remove_dir_all(r).ok();
    }
}

/// The cross-check against the Python script's file in the official folder (skipped without it).
#[test]
fn official_folder_matches_the_python_embeddings() {
    let Some(root) = std::env::var_os(WEIGHTS_ENV).map(PathBuf::from).filter(|r| r.join(TEXT_EMBEDDINGS_FILE).is_file()) else {
        println!("skipped: no {WEIGHTS_ENV} folder with {TEXT_EMBEDDINGS_FILE}");
        return;
    };
    let dev = Device::Cpu;
    let want = load_text_embeddings(&root.join(TEXT_EMBEDDINGS_FILE), &dev).unwrap();
    let got = TextEncoderFiles::locate(&root).unwrap().compute(&dev).unwrap().narrow(0, 0, want.dim(0).unwrap()).unwrap();
    let d = max_abs(&got, &want);
    let scale = want.abs().unwrap().flatten_all().unwrap().max(0).unwrap().to_scalar::<f32>().unwrap().max(1.0);
    println!("official text tower vs {TEXT_EMBEDDINGS_FILE}: max |Δ| = {d:.2e} (largest value {scale:.1})");
    // relative to the largest activation: the real tower is 23 layers deep, the fixture's 2
    assert!(d <= 1e-4 * scale, "{d:e}");
}

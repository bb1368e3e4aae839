//! The port asks for exactly the official weight names and shapes: the full-size UNet and VAE are
//! constructed against a VarBuilder that records every requested key and shape (no weights
//! needed), and the record is compared with `../shared/idarb/unet_keys_full.txt` (all 798 official
//! `state_dict` keys) and the VAE facts. Skips when the shared folder is absent.

mod common;
use candle_core::{DType, Device, Shape, Tensor};
use candle_nn::var_builder::SimpleBackend;
use candle_nn::{Init, VarBuilder};
use reconstruct::prior::idarb::autoencoder_kl::{AutoencoderKL, AutoencoderKLConfig};
use reconstruct::prior::idarb::unet_dr2d_condition::{UNetDR2DConditionModel, UNetDR2DConfig};
use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};

/// Hands out broadcast zeros (no allocation) and remembers every request.
struct Recorder(Arc<Mutex<BTreeMap<String, Vec<usize>>>>);

impl SimpleBackend for Recorder {
    fn get(&self, s: Shape, name: &str, _: Init, dtype: DType, dev: &Device) -> candle_core::Result<Tensor> {
        let prev = self.0.lock().unwrap().insert(name.to_string(), s.dims().to_vec());
        assert!(prev.is_none(), "{name} requested twice");
        Tensor::zeros((), dtype, dev)?.broadcast_as(s)
    }
    fn get_unchecked(&self, name: &str, _: DType, _: &Device) -> candle_core::Result<Tensor> {
        candle_core::bail!("unexpected unchecked request for {name}")
    }
    fn contains_tensor(&self, _: &str) -> bool {
        true
    }
}

use common::shared_data::shared_dir;

fn record<T>(build: impl FnOnce(VarBuilder) -> candle_core::Result<T>) -> BTreeMap<String, Vec<usize>> {
    let log = Arc::new(Mutex::new(BTreeMap::new()));
    let vb = VarBuilder::from_backend(Box::new(Recorder(log.clone())), DType::F32, Device::Cpu);
    build(vb).expect("model construction");
    let out = log.lock().unwrap().clone();
    out
}

#[test]
fn full_unet_requests_exactly_the_official_keys_and_shapes() {
    if common::shared_data::require("idarb_keys::full_unet_requests_exactly_the_official_keys_and_shapes").is_none() {
        return;
    }
    let dir = shared_dir().join("idarb");
    let keys_path = dir.join("unet_keys_full.txt");
    let text = std::fs::read_to_string(&keys_path).expect("registered as present");
    let official: BTreeMap<String, Vec<usize>> = text
        .lines()
        .filter(|l| !l.trim().is_empty())
        .map(|l| {
            let (k, s) = l.split_once('\t').expect("key<TAB>[shape]");
            (k.to_string(), serde_json::from_str(s).expect("shape list"))
        })
        .collect();
    // the config file, when present, must parse to the built-in full config
    let config = match UNetDR2DConfig::from_json_file(&dir.join("unet_config_full.json")) {
        Ok(c) => {
            assert_eq!(c, UNetDR2DConfig::full());
            c
        }
        Err(_) => UNetDR2DConfig::full(),
    };
    let requested = record(|vb| UNetDR2DConditionModel::new(vb, config));
    let missing: Vec<_> = official.keys().filter(|k| !requested.contains_key(*k)).collect();
    let extra: Vec<_> = requested.keys().filter(|k| !official.contains_key(*k)).collect();
    assert!(missing.is_empty() && extra.is_empty(), "missing {missing:?}\nextra {extra:?}");
    for (k, s) in &official {
        assert_eq!(&requested[k], s, "shape of {k}");
    }
    let params: usize = requested.values().map(|s| s.iter().product::<usize>()).sum();
    println!("UNet: {} keys, {params} parameters", requested.len());
}

#[test]
fn full_vae_has_the_sd_layout() {
    if common::shared_data::require("idarb_keys::full_vae_has_the_sd_layout").is_none() {
        return;
    }
    let path = shared_dir().join("idarb/vae_config_full.json");
    let config = AutoencoderKLConfig::from_json_file(&path).expect("registered as present");
    assert_eq!(config, AutoencoderKLConfig::sd21());
    let requested = record(|vb| AutoencoderKL::new(vb, config));
    let params: usize = requested.values().map(|s| s.iter().product::<usize>()).sum();
    // counts stated in ../shared/idarb/README.md for diffusers' AutoencoderKL with this config
    assert_eq!((requested.len(), params), (248, 83_653_863));
    assert_eq!(requested["encoder.mid_block.attentions.0.to_q.weight"], vec![512, 512]);
    assert_eq!(requested["quant_conv.weight"], vec![8, 8, 1, 1]);
    assert_eq!(requested["decoder.up_blocks.3.resnets.0.conv_shortcut.weight"], vec![128, 256, 1, 1]);
}

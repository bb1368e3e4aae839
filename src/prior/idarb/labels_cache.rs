//! On-disk label cache: one 16-bit PNG per map and view plus `settings.json` (options, input
//! hashes, weight hashes). A cache is reused only when its key (options + inputs) matches.
//! The maps are named `<view>_<map>.png` (albedo, normal, metallic, roughness, plus the mask), the
//! per-map layout `--prior labels:DIR` reads, so a cache folder is also a labels folder.
use crate::prior::view_labels::ViewLabels;
use crate::image::Image;
use anyhow::{bail, Context, Result};
use serde_json::Value;
use std::path::Path;

pub const SETTINGS_FILE: &str = "settings.json";
const MAPS: [(&str, usize); 5] = [("albedo", 3), ("normal", 3), ("metallic", 1), ("roughness", 1), ("mask", 1)];

fn map_of<'a>(l: &'a ViewLabels, name: &str) -> &'a Image {
    match name {
        "albedo" => &l.albedo,
        "normal" => &l.normal,
        "metallic" => &l.metallic,
        "roughness" => &l.roughness,
        _ => &l.mask,
    }
}

fn save_png16(img: &Image, path: &Path) -> Result<()> {
    let q = |v: f32| (v.clamp(0.0, 1.0) * 65535.0).round() as u16;
    let (w, h) = (img.width as u32, img.height as u32);
    let res = match img.channels {
        1 => image::ImageBuffer::<image::Luma<u16>, _>::from_raw(w, h, img.data.iter().map(|&v| q(v)).collect::<Vec<_>>()).map(|b| b.save(path)),
        3 => image::ImageBuffer::<image::Rgb<u16>, _>::from_raw(w, h, img.data.iter().map(|&v| q(v)).collect::<Vec<_>>()).map(|b| b.save(path)),
        c => bail!("cannot cache a {c}-channel map"),
    };
    res.context("image buffer size mismatch")?.with_context(|| format!("writing {}", path.display()))
}

fn load_png(path: &Path, channels: usize) -> Result<Image> {
    let img = crate::image::safe_decode::decode_with_image_crate(path, "cached label")?;
    let (w, h) = (img.width() as usize, img.height() as usize);
    let data: Vec<f32> = match channels {
        1 => img.to_luma16().into_raw().into_iter().map(|v| v as f32 / 65535.0).collect(),
        _ => img.to_rgb16().into_raw().into_iter().map(|v| v as f32 / 65535.0).collect(),
    };
    Ok(Image { width: w, height: h, channels, data })
}

/// The view names a cache's files use: its `views` list, else (caches written before names were
/// stored) `view_0000`, `view_0001`, ….
fn stored_names(settings: &Value, n: usize) -> Vec<String> {
    match settings.get("views").and_then(Value::as_array) {
        Some(v) if v.len() == n && v.iter().all(Value::is_string) => v.iter().filter_map(|s| s.as_str().map(str::to_string)).collect(),
        _ => default_names(n),
    }
}

/// Names of views that have none: `view_0000`, `view_0001`, ….
pub fn default_names(n: usize) -> Vec<String> {
    (0..n).map(|v| format!("view_{v:04}")).collect()
}

/// (file, content hash) of each weight file a cache was made with.
pub type WeightHashes = Vec<(String, String)>;

/// The view names and weight hashes of the cache in `dir`, when there is one.
pub fn names_and_weights(dir: &Path) -> Result<Option<(Vec<String>, WeightHashes)>> {
    let settings_path = dir.join(SETTINGS_FILE);
    if !settings_path.is_file() {
        return Ok(None);
    }
    let text = std::fs::read_to_string(&settings_path).with_context(|| format!("reading {}", settings_path.display()))?;
    let settings: Value = serde_json::from_str(&text).with_context(|| format!("parsing {}", settings_path.display()))?;
    let n = settings.get("num_views").and_then(Value::as_u64).unwrap_or(0) as usize;
    let weights = match settings.get("weights_fnv1a64").and_then(Value::as_object) {
        Some(m) => m.iter().filter_map(|(f, h)| h.as_str().map(|h| (f.clone(), h.to_string()))).collect(),
        None => Vec::new(),
    };
    Ok(Some((stored_names(&settings, n), weights)))
}

/// Cached labels for `key`, or None when absent or made with other settings.
pub fn load(dir: &Path, key: &Value) -> Result<Option<Vec<ViewLabels>>> {
    let settings_path = dir.join(SETTINGS_FILE);
    if !settings_path.is_file() {
        return Ok(None);
    }
    let text = std::fs::read_to_string(&settings_path).with_context(|| format!("reading {}", settings_path.display()))?;
    let settings: Value = serde_json::from_str(&text).with_context(|| format!("parsing {}", settings_path.display()))?;
    // compare as stored: an f32 in the key (a pose angle) is written in its shortest form and
    // reads back as another f64 than the in-memory one
    let key: Value = serde_json::from_str(&key.to_string())?;
    if settings.get("key") != Some(&key) {
        return Ok(None);
    }
    let n = settings.get("num_views").and_then(Value::as_u64).with_context(|| format!("{}: no num_views", settings_path.display()))? as usize;
    let mut out = Vec::with_capacity(n);
    for view in stored_names(&settings, n) {
        let get = |name: &str, c: usize| load_png(&dir.join(format!("{view}_{name}.png")), c);
        out.push(ViewLabels { albedo: get("albedo", 3)?, normal: get("normal", 3)?, metallic: get("metallic", 1)?, roughness: get("roughness", 1)?, mask: get("mask", 1)? });
    }
    Ok(Some(out))
}

/// Write labels and their settings (`weights` = file hashes for provenance) as `<view>_<map>.png`
/// for the view names `names` (one per label; unique, usable as file names).
pub fn store(dir: &Path, key: &Value, weights: &[(String, String)], names: &[String], labels: &[ViewLabels]) -> Result<()> {
    if names.len() != labels.len() {
        bail!("label cache: {} names for {} views", names.len(), labels.len());
    }
    let mut unique = names.to_vec();
    unique.sort();
    unique.dedup();
    if let Some(bad) = names.iter().find(|n| n.is_empty() || n.contains(['/', '\\']) || n.as_str() == "." || n.as_str() == "..") {
        bail!("label cache: view name `{bad}` cannot name a file");
    }
    if unique.len() != names.len() {
        bail!("label cache: view names repeat ({names:?})");
    }
    std::fs::create_dir_all(dir).with_context(|| format!("creating label cache {}", dir.display()))?;
    for (view, l) in names.iter().zip(labels) {
        for (name, _) in MAPS {
            save_png16(map_of(l, name), &dir.join(format!("{view}_{name}.png")))?;
        }
    }
    let settings = serde_json::json!({
        "what": "IDArb pseudo-labels: albedo (sRGB-encoded), normal (camera space, (n+1)/2), metallic, roughness, mask; 16-bit PNG, <view>_<map>.png",
        "num_views": labels.len(),
        "views": names,
        "key": key,
        "weights_fnv1a64": weights.iter().map(|(f, h)| (f.clone(), Value::String(h.clone()))).collect::<serde_json::Map<_, _>>(),
    });
    let path = dir.join(SETTINGS_FILE);
    std::fs::write(&path, serde_json::to_string_pretty(&settings)?).with_context(|| format!("writing {}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn store_then_load_round_trips_and_key_mismatch_misses() -> Result<()> {
        let dir = std::env::temp_dir().join(format!("idarb_cache_test_{}", std::process::id()));
        let ramp = |c: usize| Image { width: 5, height: 3, channels: c, data: (0..15 * c).map(|i| i as f32 / (15 * c) as f32).collect() };
        let labels = vec![ViewLabels { albedo: ramp(3), normal: ramp(3), metallic: ramp(1), roughness: ramp(1), mask: ramp(1) }];
        let key = serde_json::json!({"steps": 4, "pose": [1.1565497f32]});
        store(&dir, &key, &[("unet/x".into(), "00".into())], &["r_7".to_string()], &labels)?;
        assert!(dir.join("r_7_albedo.png").is_file() && dir.join("r_7_roughness.png").is_file());
        assert_eq!(names_and_weights(&dir)?, Some((vec!["r_7".to_string()], vec![("unet/x".to_string(), "00".to_string())])));
        let back = load(&dir, &key)?.expect("cache hit");
        for (a, b) in back[0].albedo.data.iter().zip(&labels[0].albedo.data) {
            assert!((a - b).abs() <= 0.5 / 65535.0 + 1e-7);
        }
        assert_eq!(back[0].roughness.channels, 1);
        assert!(load(&dir, &serde_json::json!({"steps": 5, "pose": [1.1565497f32]}))?.is_none());
        assert!(store(&dir, &key, &[], &["a/b".to_string()], &labels).is_err());
        std::fs::remove_dir_all(&dir).ok();
        Ok(())
    }
}

//! Label files (`--prior labels:DIR`) in both layouts round-trip; a wrong-size or missing label
//! file is a clear error naming it; and the assembled prior term (sRGB-encoded base colour,
//! roughness, metallic) matches finite differences.

use anyhow::Result;
use candle_core::{Device, Tensor, D};
use reconstruct::image::io::write_png;
use reconstruct::image::Image;
use reconstruct::optim::gradcheck::check_gradient;
use reconstruct::optim::prior_loss::prior_loss;
use reconstruct::optim::srgb::srgb_encode;
use reconstruct::prior::view_labels::ViewLabels;
use reconstruct::prior::oracle::view_labels;
use reconstruct::prior::source::{make_prior, PriorContext, PriorSource};
use reconstruct::scene::dataset::Dataset;
use reconstruct::scene::SceneSpec;

fn dataset() -> Result<Dataset> {
    SceneSpec::find("default")?.load_dataset()
}

fn ctx() -> PriorContext {
    PriorContext { idarb_weights: None, cache_dir: std::env::temp_dir(), idarb: Default::default(), seed: 1 }
}

fn temp(name: &str) -> std::path::PathBuf {
    let d = std::env::temp_dir().join(format!("reconstruct-labels-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).expect("temp dir");
    d
}

fn grey_to_rgb(img: &Image) -> Image {
    Image { width: img.width, height: img.height, channels: 3, data: img.data.iter().flat_map(|v| [*v; 3]).collect() }
}

fn close(a: &Image, b: &Image, what: &str) {
    assert_eq!((a.width, a.height), (b.width, b.height), "{what} size");
    let n = a.channels.min(b.channels);
    for i in 0..a.pixel_count() {
        for c in 0..n {
            let d = (a.data[i * a.channels + c] - b.data[i * b.channels + c]).abs();
            assert!(d <= 1.0 / 255.0 + 1e-6, "{what}: pixel {i} channel {c} differs by {d}");
        }
    }
}

fn load(dir: &std::path::Path, ds: &Dataset) -> Result<ViewLabels> {
    let prior = make_prior(&PriorSource::LabelsDir(dir.to_path_buf()), &ctx())?;
    let mut labels = prior.labels(ds, &[0, 1])?;
    assert!(labels[1].is_none(), "view 1 has no files, so no labels");
    Ok(labels.swap_remove(0).expect("view 0 labelled"))
}

#[test]
fn per_map_and_strip_layouts_round_trip() -> Result<()> {
    let ds = dataset()?;
    let view = &ds.train[0];
    let truth = view_labels(view)?;
    // One file per map.
    let dir = temp("maps");
    write_png(&dir.join(format!("{}_albedo.png", view.name)), &truth.albedo)?;
    write_png(&dir.join(format!("{}_normal.png", view.name)), &truth.normal)?;
    write_png(&dir.join(format!("{}_metallic.png", view.name)), &truth.metallic)?;
    write_png(&dir.join(format!("{}_roughness.png", view.name)), &truth.roughness)?;
    let got = load(&dir, &ds)?;
    close(&got.albedo, &truth.albedo, "albedo");
    close(&got.normal, &truth.normal, "normal");
    close(&got.metallic, &truth.metallic, "metallic");
    close(&got.roughness, &truth.roughness, "roughness");
    // The official strip: [albedo | normal | metallic | roughness].
    let dir2 = temp("strip");
    let (w, h) = (truth.albedo.width, truth.albedo.height);
    let mut strip = Image::new(4 * w, h, 3);
    for (k, tile) in [truth.albedo.clone(), truth.normal.clone(), grey_to_rgb(&truth.metallic), grey_to_rgb(&truth.roughness)].iter().enumerate() {
        for y in 0..h {
            for x in 0..w {
                strip.pixel_mut(k * w + x, y).copy_from_slice(tile.pixel(x, y));
            }
        }
    }
    write_png(&dir2.join(format!("{}.png", view.name)), &strip)?;
    let got = load(&dir2, &ds)?;
    close(&got.albedo, &truth.albedo, "strip albedo");
    close(&got.normal, &truth.normal, "strip normal");
    close(&got.roughness, &truth.roughness, "strip roughness");
    std::fs::remove_dir_all(dir)?;
    std::fs::remove_dir_all(dir2)?;
    Ok(())
}

#[test]
fn wrong_size_and_missing_files_are_named_in_the_error() -> Result<()> {
    let ds = dataset()?;
    let name = ds.train[0].name.clone();
    let dir = temp("bad");
    let odd = Image::new(7, 3, 3); // not the view's aspect ratio
    for m in ["albedo", "normal", "metallic", "roughness"] {
        write_png(&dir.join(format!("{name}_{m}.png")), &odd)?;
    }
    let err = format!("{:#}", load(&dir, &ds).expect_err("wrong size"));
    assert!(err.contains(&format!("{name}_albedo.png")) && err.contains("7×3"), "{err}");
    std::fs::remove_file(dir.join(format!("{name}_roughness.png")))?;
    let err = format!("{:#}", load(&dir, &ds).expect_err("missing file"));
    assert!(err.contains(&format!("{name}_roughness.png")) && err.contains("missing"), "{err}");
    std::fs::remove_dir_all(dir)?;
    Ok(())
}

#[test]
fn prior_term_gradient_matches_finite_differences() -> anyhow::Result<()> {
    let dev = Device::Cpu;
    let labels_albedo = Tensor::rand(0f64, 1.0, (30, 1, 3), &dev)?;
    let labels_rough = Tensor::rand(0f64, 1.0, (30, 1, 1), &dev)?;
    let mask = Tensor::rand(0f64, 1.0, (30, 1, 1), &dev)?.ge(0.3)?.to_dtype(candle_core::DType::F64)?;
    let kd = Tensor::rand(0.05f64, 0.95, (30, 1, 3), &dev)?;
    let ks = Tensor::rand(0.1f64, 0.9, (30, 1, 3), &dev)?;
    let term = |x: &[Tensor]| -> candle_core::Result<Tensor> {
        let a = prior_loss(&srgb_encode(&x[0])?, &labels_albedo, &mask, 0.7)?;
        let r = prior_loss(&x[1].narrow(D::Minus1, 1, 1)?, &labels_rough, &mask, 0.3)?;
        a + r
    };
    check_gradient(term, &[kd, ks], 1e-6, 1e-2)?;
    Ok(())
}

/// The IDArb label cache (`--prior idarb`) is itself a `labels:DIR` folder: labels stored under a
/// view's name read back through `LabelsDir` (16-bit files, so within 8-bit resolution here).
#[test]
fn idarb_label_cache_reads_back_as_a_labels_folder() -> Result<()> {
    let ds = dataset()?;
    let view = &ds.train[0];
    let truth = view_labels(view)?;
    let dir = temp("idarb-cache");
    let key = serde_json::json!({"test": 1});
    reconstruct::prior::idarb::labels_cache::store(&dir, &key, &[], std::slice::from_ref(&view.name), std::slice::from_ref(&truth))?;
    let got = load(&dir, &ds)?;
    close(&got.albedo, &truth.albedo, "albedo");
    close(&got.normal, &truth.normal, "normal");
    close(&got.roughness, &truth.roughness, "roughness");
    close(&got.metallic, &truth.metallic, "metallic");
    std::fs::remove_dir_all(&dir).ok();
    Ok(())
}

//! Picture files: sRGB through 8-bit PNG, EXR round trips, and the Radiance probes.

mod common;

use std::path::PathBuf;

use rand::{Rng, SeedableRng};
use reconstruct::image::io::{read_exr, read_hdr, read_png, read_probe, write_exr, write_png};
use reconstruct::image::Image;
use reconstruct::scene::crate_dir;

fn temp_file(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("reconstruct-scene-io-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

fn random_image(w: usize, h: usize, c: usize, seed: u64) -> Image {
    let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
    let mut img = Image::new(w, h, c);
    img.data.iter_mut().for_each(|v| *v = rng.random::<f32>());
    img
}

#[test]
fn linear_colour_survives_srgb_encoding_through_an_8bit_png() {
    for channels in [3, 4] {
        let linear = random_image(37, 23, channels, 7 + channels as u64);
        let path = temp_file(&format!("srgb{channels}.png"));
        write_png(&path, &linear.linear_to_srgb()).unwrap();
        let back = read_png(&path).unwrap();
        assert_eq!((back.width, back.height, back.channels), (37, 23, channels));
        let decoded = back.srgb_to_linear();
        for (i, (a, b)) in linear.data.iter().zip(&decoded.data).enumerate() {
            let is_alpha = channels == 4 && i % 4 == 3;
            // Within half a code in the encoded space; alpha is stored without a curve.
            let (ea, eb) = if is_alpha { (*a, *b) } else { (reconstruct::color::linear_to_srgb(*a), reconstruct::color::linear_to_srgb(*b)) };
            assert!((ea - eb).abs() <= 0.5 / 255.0 + 1e-6, "value {i}: {a} → {b}");
        }
    }
}

#[test]
fn exr_keeps_hdr_values_exactly() {
    let mut img = random_image(19, 11, 3, 3);
    img.data.iter_mut().for_each(|v| *v = (*v * 12.0 - 2.0).exp());
    let path = temp_file("hdr.exr");
    write_exr(&path, &img).unwrap();
    assert_eq!(read_exr(&path).unwrap(), img);
    assert_eq!(read_probe(&path).unwrap(), img);
}

#[test]
fn the_cc0_fixture_probes_are_16x32_positive_radiance() {
    let dir = crate_dir().join("tests/fixtures/probes");
    let shared_copies = common::shared_data::require("scene_io::the_cc0_fixture_probes_are_16x32_positive_radiance (byte copies of the shared probes)");
    for name in ["city", "courtyard", "forest", "interior", "night", "studio", "sunrise", "sunset"] {
        let path = dir.join(format!("{name}.hdr"));
        let img = read_hdr(&path).unwrap();
        assert_eq!((img.width, img.height, img.channels), (32, 16, 3), "{name}");
        assert!(img.data.iter().all(|v| v.is_finite() && *v > 0.0), "{name}: non-positive texel");
        assert_eq!(read_probe(&path).unwrap(), img);
        // The fixtures are byte copies of the shared probes.
        if let Some(shared) = shared_copies.as_ref() {
            let shared = shared.join(format!("data/probes/{name}.hdr"));
            assert_eq!(std::fs::read(&shared).unwrap(), std::fs::read(&path).unwrap(), "{name}");
        }
    }
    assert!(!dir.join("2163.hdr").exists(), "2163.hdr (licence unknown) must not be committed");
}

#[test]
fn training_probe_2163_matches_the_readme_values() {
    let Some(shared) = common::shared_data::require("scene_io::training_probe_2163_matches_the_readme_values") else { return };
    let path = shared.join("data/probes/2163.hdr");
    let img = read_probe(&path).unwrap();
    assert_eq!((img.width, img.height), (32, 16));
    // README, "Checks": the probe values Blender's convention gives. Texels away from bright
    // neighbours are exact: RGBE decodes as m·2^(e−136) (no +0.5, like OpenCV, NeRFactor's reader).
    for ((x, y), want) in [((27, 13), [0.02222, 0.01770, 0.01343]), ((5, 10), [0.00684, 0.00806, 0.00367])] {
        let v = img.pixel(x, y);
        for (got, want) in v.iter().zip(want) {
            assert!((got - want).abs() < 1.2e-5, "texel ({x},{y}): {v:?}");
        }
    }
    // The brightest texel is row 5, column 0 (the README's value there is a 0.2° footprint
    // average around the peak, (1.59120, 1.56001, 1.57553): 0.2 % below the texel value).
    let brightest = (0..img.pixel_count()).max_by(|&a, &b| img.rgb(a).x.total_cmp(&img.rgb(b).x)).unwrap();
    assert_eq!((brightest / 32, brightest % 32), (5, 0));
    let v = img.pixel(0, 5);
    for (got, want) in v.iter().zip([1.59120, 1.56001, 1.57553]) {
        assert!(*got >= want && (got - want) < 0.003 * want, "{v:?}");
    }
}

#[test]
fn a_shared_depth_map_reads_as_one_channel() {
    let Some(shared) = common::shared_data::require("scene_io::a_shared_depth_map_reads_as_one_channel") else { return };
    let path = shared.join("data/nerfactor/hotdog_2163/train_000/depth.exr");
    let d = read_exr(&path).unwrap();
    assert_eq!((d.width, d.height, d.channels), (256, 256, 1));
    // Cameras are 4.03 from the origin and the scene fits in a ~1.3 radius: depths lie in between.
    assert!(d.data.iter().all(|&z| z == 0.0 || (2.5..5.5).contains(&z)));
}

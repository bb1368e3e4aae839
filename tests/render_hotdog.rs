//! The hotdog's ground truth rendered by the project against the dataset's Mitsuba path-traced
//! `rgba.png` (max depth 6: up to 4 indirect bounces), with direct light only and with the
//! interreflection effect, and the probe orientation against where the bright side and the
//! shadows fall.

mod common;

use glam::Vec3;
use reconstruct::eval::metrics::protocol_psnr;
use reconstruct::geometry::bvh::Bvh;
use reconstruct::geometry::ground_truth::load_ground_truth;
use reconstruct::image::Image;
use reconstruct::light::CubeMap;
use reconstruct::render::effects::Effects;
use reconstruct::render::view::{render_view, PreparedLight, RenderSettings, ShadingMode};
use reconstruct::scene::dataset::Dataset;
use reconstruct::scene::probe::Probe;
use reconstruct::scene::spec::shared_dir;

struct Hotdog {
    dataset: Dataset,
    mesh: reconstruct::geometry::Mesh,
    bvh: Bvh,
    probe: Image,
}

fn hotdog(test: &str) -> Option<Hotdog> {
    let shared = common::shared_data::require(test)?;
    let dir = shared.join("data/nerfactor/hotdog_2163");
    let probe = shared.join("data/probes/2163.hdr");
    let dataset = Dataset::load(&dir).expect("hotdog dataset loads");
    let mesh = load_ground_truth(dir.join("gt")).expect("hotdog gt loads");
    let bvh = Bvh::build(&mesh);
    let probe = Probe::load(&probe, 3.0).expect("probe 2163 loads").radiance_image();
    Some(Hotdog { dataset, mesh, bvh, probe })
}

/// The probe mirrored left to right (u → 1 − u): the wrong handedness.
fn mirrored(img: &Image) -> Image {
    let mut out = img.clone();
    for y in 0..img.height {
        for x in 0..img.width {
            out.pixel_mut(x, y).copy_from_slice(img.pixel(img.width - 1 - x, y));
        }
    }
    out
}

/// The probe turned half a turn about z (u → u + ½): the main light moves from −x to +x.
fn half_turn(img: &Image) -> Image {
    let mut out = img.clone();
    for y in 0..img.height {
        for x in 0..img.width {
            out.pixel_mut(x, y).copy_from_slice(img.pixel((x + img.width / 2) % img.width, y));
        }
    }
    out
}

/// PSNR of the ground truth rendered with `effects` against each checked view's `rgba.png`.
fn ground_truth_scores(h: &Hotdog, effects: Effects) -> Vec<f64> {
    let light = PreparedLight::new(CubeMap::from_latlong(&h.probe, 64));
    let settings = RenderSettings { mode: ShadingMode::MonteCarlo, spp: 32, supersample: 2, seed: 1, effects };
    let views: Vec<_> = h.dataset.train.iter().step_by(25).chain(h.dataset.val.iter().take(2)).collect();
    views
        .into_iter()
        .map(|view| {
            let score = protocol_psnr(&render_view(&h.mesh, &h.bvh, &light, &view.camera, &settings), &view.load_rgba().expect("rgba.png"));
            println!("{}: PSNR {score:.2} dB (MC 32 spp, {} indirect bounces, vs Mitsuba path tracing)", view.name, effects.indirect_bounces);
            score
        })
        .collect()
}

#[test]
fn ground_truth_render_matches_dataset_per_view() {
    let Some(h) = hotdog("render_hotdog::ground_truth_render_matches_dataset_per_view") else { return };
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    let direct = ground_truth_scores(&h, Effects::DIRECT);
    let bounced = ground_truth_scores(&h, Effects::with_bounces(3));
    println!("mean PSNR over {} views: direct light {:.2} dB, 3 bounces {:.2} dB", direct.len(), mean(&direct), mean(&bounced));
    // Measured 2026-11-22, direct light: 23.6–26.6 dB per view, mean 25.1 dB: our red channel was
    // 15–19% darker on covered pixels. With 3 bounces the missing interreflection is back; what
    // remains is Disney diffuse vs Lambert, the last bounce, and noise on both sides (the targets
    // are 64-spp path traces). Measured 2026-12-01 with 3 bounces: 32.1–34.0 dB per view, mean
    // 33.3 dB. Floors leave ~1.5 dB for seed and platform changes.
    assert!(direct.iter().all(|&s| s > 22.0), "direct light: per-view PSNR fell below the floor: {direct:?}");
    assert!(mean(&direct) > 24.0, "direct light: mean PSNR {:.2}", mean(&direct));
    assert!(bounced.iter().all(|&s| s > 30.5), "3 bounces: per-view PSNR fell below the floor: {bounced:?}");
    assert!(mean(&bounced) > 31.8, "3 bounces: mean PSNR {:.2}", mean(&bounced));
    assert!(mean(&bounced) > mean(&direct) + 6.0, "interreflection should close most of the gap");
}

#[test]
fn probe_orientation_agrees_with_relit_ground_truth() {
    let Some(h) = hotdog("render_hotdog::probe_orientation_agrees_with_relit_ground_truth") else { return };
    let settings = RenderSettings { mode: ShadingMode::MonteCarlo, spp: 16, supersample: 1, seed: 1, effects: Effects::DIRECT };
    let right = PreparedLight::new(CubeMap::from_latlong(&h.probe, 32));
    let wrong = PreparedLight::new(CubeMap::from_latlong(&half_turn(&h.probe), 32));
    for view in [&h.dataset.train[0], &h.dataset.train[50]] {
        let target = view.load_rgba().expect("rgba.png");
        let good = protocol_psnr(&render_view(&h.mesh, &h.bvh, &right, &view.camera, &settings), &target);
        let bad = protocol_psnr(&render_view(&h.mesh, &h.bvh, &wrong, &view.camera, &settings), &target);
        println!("{}: Blender orientation {good:.2} dB, probe turned by 180° {bad:.2} dB", view.name);
        assert!(good > bad + 1.0, "the probe's orientation does not explain the lit sides and shadows");
    }
    // Handedness: 2163's main light sits on the −x axis, which a mirror (u → 1 − u, i.e. y → −y)
    // leaves in place, so check it with the relit test views under `city`, whose sun is at
    // (0.49, −0.40, 0.77): mirroring moves it to +y.
    let city = Probe::load(&shared_dir().join("data/probes/city.hdr"), 1.0).expect("city probe").radiance_image();
    let right = PreparedLight::new(CubeMap::from_latlong(&city, 32));
    let wrong = PreparedLight::new(CubeMap::from_latlong(&mirrored(&city), 32));
    for view in h.dataset.test.iter().take(2) {
        let target = view.load_relit("city").expect("rgba_city.png");
        let good = protocol_psnr(&render_view(&h.mesh, &h.bvh, &right, &view.camera, &settings), &target);
        let bad = protocol_psnr(&render_view(&h.mesh, &h.bvh, &wrong, &view.camera, &settings), &target);
        println!("{} under city: Blender orientation {good:.2} dB, mirrored probe {bad:.2} dB", view.name);
        assert!(good > bad + 1.0, "the probe's handedness does not explain the relit image");
    }
    let right = PreparedLight::new(CubeMap::from_latlong(&h.probe, 32));
    // train_000 looks down on the plate with −x to the image's right (dataset README): the main
    // light is toward −x, so the right half of the render is the brighter one.
    let render = render_view(&h.mesh, &h.bvh, &right, &h.dataset.train[0].camera, &settings);
    let half_mean = |x0: usize, x1: usize| {
        let mut sum = Vec3::ZERO;
        let mut n = 0.0;
        for y in 0..render.height {
            for x in x0..x1 {
                let p = render.pixel(x, y);
                if p[3] > 0.99 {
                    sum += Vec3::new(p[0], p[1], p[2]);
                    n += 1.0;
                }
            }
        }
        sum / n
    };
    let w = render.width;
    assert!(half_mean(w / 2, w).element_sum() > half_mean(0, w / 2).element_sum());
}

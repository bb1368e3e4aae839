//! The NeRFactor evaluation protocol's building blocks on real ground truth: the albedo scale
//! recovers a known per-channel gain, and relit images composite over white.

mod common;

use reconstruct::eval::metrics::{albedo_scale, mask_from_alpha, over_white, psnr, scale_colour};
use reconstruct::scene::Dataset;

fn hotdog(test: &str) -> Option<Dataset> {
    let dir = common::shared_data::require(test)?.join("data/nerfactor/hotdog_2163");
    Some(Dataset::load(&dir).unwrap())
}

#[test]
fn albedo_scale_undoes_a_known_gain_on_the_first_val_view() {
    let Some(ds) = hotdog("metrics_protocol::albedo_scale_undoes_a_known_gain_on_the_first_val_view") else { return };
    let gt = ds.val[0].load_albedo().unwrap();
    let gain = [0.5, 0.8, 1.25];
    let pred = scale_colour(&gt, gain);
    let mask = mask_from_alpha(&gt, 0.9);
    assert!(mask.iter().filter(|&&m| m).count() > 5000);
    let s = albedo_scale(&pred, &gt, Some(&mask));
    for c in 0..3 {
        assert!((s[c] * gain[c] - 1.0).abs() < 1e-5, "{s:?}");
    }
    let raw = psnr(&pred, &gt, Some(&mask));
    let scaled = psnr(&scale_colour(&pred, s), &gt, Some(&mask));
    assert!(raw < 20.0 && scaled > 80.0, "raw {raw} scaled {scaled}");
}

#[test]
fn relit_ground_truth_over_white_has_a_white_background() {
    let Some(ds) = hotdog("metrics_protocol::relit_ground_truth_over_white_has_a_white_background") else { return };
    let relit = ds.test[1].load_relit("sunset").unwrap();
    let composed = over_white(&relit, &relit);
    let alpha = relit.channel(3);
    for i in 0..composed.pixel_count() {
        if alpha.data[i] == 0.0 {
            assert!(composed.rgb(i).min_element() > 0.99999);
        }
    }
    let mask = mask_from_alpha(&alpha, 0.8);
    assert!(psnr(&composed, &composed, Some(&mask)).is_infinite());
    // Covered pixels keep their sRGB value (the PNG's codes) to within float precision.
    let i = (0..alpha.pixel_count()).find(|&i| alpha.data[i] == 1.0).unwrap();
    let srgb = relit.rgb(i).to_array().map(reconstruct::color::linear_to_srgb);
    assert!((composed.rgb(i) - glam::Vec3::from(srgb)).abs().max_element() < 1e-6);
}

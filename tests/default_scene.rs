//! The embedded default scene round trip: the project renders it into the NeRFactor layout, the
//! loader reads it back, and the render job re-renders the ground truth to the stored images.
//! Every convention the writer and the loader share (sRGB encoding, straight alpha, camera
//! matrices, probe orientation, AOV encodings) must agree for the PSNR to be high.

use reconstruct::jobs::render::{run, RenderOptions};
use reconstruct::render::view::ShadingMode;
use reconstruct::scene::{Dataset, SceneSpec};

#[test]
fn default_scene_is_generated_loaded_and_reproduced() {
    let cache = std::env::temp_dir().join(format!("reconstruct-default-scene-{}", std::process::id()));
    // This binary holds one test, so changing the environment is safe.
    std::env::set_var("RECONSTRUCT_CACHE", &cache);
    let spec = SceneSpec::find("default").expect("scenes/default.toml");
    let dataset: Dataset = spec.load_dataset().expect("generated and loaded");
    assert_eq!((dataset.train.len(), dataset.val.len(), dataset.test.len()), (40, 4, 4));
    let view = &dataset.test[0];
    assert_eq!((view.camera.width, view.camera.height), (128, 128));
    assert_eq!(view.relit_probes().expect("relit list").len(), 8);
    // The spoon is the one metallic part: some covered pixels must say so in metallic.png.
    let metal_pixels = dataset.train.iter().take(10).map(|v| v.load_metallic().expect("metallic.png").data.iter().filter(|&&m| m > 0.9).count()).sum::<usize>();
    assert!(metal_pixels > 0, "no metallic pixels in 10 training views");

    let out = cache.join("render");
    let opts = RenderOptions {
        scene: "default".into(),
        data: None,
        views: vec![view.name.clone()],
        probes: vec!["train".into(), "city".into()],
        modes: vec![ShadingMode::MonteCarlo],
        spp: 32,
        supersample: 2,
        seed: 99,
        out: out.clone(),
    };
    let report = run(&opts).expect("render job");
    for r in &report.renders {
        let psnr = r.psnr_db.expect("the dataset has this image");
        println!("{} under {}: {psnr:.2} dB", r.view, r.probe);
        // Same renderer, other seed and spp: only Monte Carlo noise separates the two.
        assert!(psnr > 30.0, "{} under {}: {psnr:.2} dB", r.view, r.probe);
        assert!(r.png.exists() && r.exr.exists());
    }
    assert!(out.join("report.json").exists());
    std::fs::remove_dir_all(&cache).ok();
}

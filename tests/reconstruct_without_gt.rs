//! A run on data that has no ground-truth mesh (a copy of the default scene's images without its
//! mesh, as the original NeRFactor data ships) reconstructs the shape from the images and goes
//! through materials, evaluation and export; the report says which geometry it used and which
//! scores it could not compute. A view set whose masks carry no shape is refused by name.

mod common;

use reconstruct::fit::config::FitConfig;
use reconstruct::fit::geometry_pass::GeometryPassConfig;
use reconstruct::jobs::reconstruct::{run, GeometrySource, ReconstructOptions};
use reconstruct::prior::source::PriorSource;
use reconstruct::render::view::ShadingMode;
use reconstruct::scene::SceneSpec;


#[test]
fn a_scene_without_a_mesh_is_reconstructed_end_to_end() -> anyhow::Result<()> {
    let default = SceneSpec::find("default")?;
    default.load_dataset()?; // renders the default scene into the cache on first use
    let tmp = std::env::temp_dir().join(format!("reconstruct-no-gt-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&tmp);
    common::copy_dir(&default.data_dir, &tmp.join("data"))?;
    assert!(!tmp.join("data/gt").exists());
    let spec_path = tmp.join("nomesh.toml");
    std::fs::write(
        &spec_path,
        format!(
            "name = \"nomesh\"\ndata = \"{}\"\n[test_probes]\nnames = [\"city\"]\nfolders = [\"{{crate}}/tests/fixtures/probes\"]\n",
            tmp.join("data").display()
        ),
    )?;
    let fit = FitConfig { mode: ShadingMode::SplitSum, iterations: 6, batch: 1, texture_res: 64, light_res: 8, checkpoint_every: 0, ..FitConfig::default() };
    let mut opts = ReconstructOptions::new(spec_path.to_str().expect("utf-8 path"), fit, 1, tmp.join("run"));
    opts.geometry = GeometrySource::Auto;
    opts.geometry_pass = GeometryPassConfig { iterations: 10, batch: 2, ..GeometryPassConfig::default() };
    opts.progress = false;
    opts.eval_test_views = Some(1);
    let report = run(&opts, &PriorSource::None)?;
    assert_eq!(report.geometry.used, GeometrySource::Reconstruct, "auto must reconstruct: {}", report.geometry.why);
    let scores = report.geometry.scores.as_ref().expect("scores");
    assert!(scores.mesh.is_none() && scores.not_computed.iter().any(|l| l.contains("no ground-truth mesh")), "{:?}", scores.not_computed);
    let iou = scores.test_views.as_ref().expect("test-view scores").silhouette_iou;
    assert!(iou > 0.8, "silhouette IoU {iou}");
    for f in ["report.json", "report.md", "model/model.obj", "model/model.gltf", "model/kd.png"] {
        assert!(tmp.join("run").join(f).exists(), "{f} missing");
    }
    // Masks that carry no shape: every alpha opaque. The hull refuses and names the views.
    let views = reconstruct::scene::dataset::Dataset::load(&tmp.join("data"))?;
    let masks: Vec<_> = views
        .train
        .iter()
        .take(3)
        .map(|v| reconstruct::geometry::hull::MaskView {
            name: v.name.clone(),
            camera: v.camera.clone(),
            alpha: reconstruct::image::Image::filled(v.camera.width, v.camera.height, &[1.0]),
        })
        .collect();
    let err = reconstruct::geometry::hull::visual_hull(&masks, &Default::default()).expect_err("opaque masks").to_string();
    assert!(err.contains(&views.train[0].name), "{err}");
    let _ = std::fs::remove_dir_all(&tmp);
    Ok(())
}

//! `--downscale N`: the material pass trains on views N times smaller, the evaluation keeps the
//! data's resolution, the labels are reduced with the views, the run's identity records the
//! divisor, and a divisor that does not divide the views is refused by view name.

use reconstruct::fit::config::FitConfig;
use reconstruct::fit::geometry_pass::GeometryPassConfig;
use reconstruct::jobs::reconstruct::{prepare, prior_context, run, views_with_prior, GeometrySource, ReconstructOptions};
use reconstruct::prior::source::PriorSource;
use reconstruct::render::view::ShadingMode;

fn fit() -> FitConfig {
    FitConfig { mode: ShadingMode::SplitSum, iterations: 4, batch: 1, texture_res: 256, light_res: 8, checkpoint_every: 0, ..FitConfig::default() }
}

#[test]
fn training_views_are_reduced_and_the_evaluation_is_not() -> anyhow::Result<()> {
    let pass = GeometryPassConfig::default();
    let full = prepare("default", None, GeometrySource::GroundTruth, &pass, &fit(), 1, false)?;
    let half = prepare("default", None, GeometrySource::GroundTruth, &pass, &fit(), 2, false)?;
    let (w, h) = (full.views[0].camera.width, full.views[0].camera.height);
    assert_eq!((half.views[0].camera.width, half.views[0].camera.height), (w / 2, h / 2));
    // A quarter of the pixels, give or take the outline's pixels (which round either way).
    let covered = |p: &reconstruct::jobs::reconstruct::Prepared| p.views.iter().map(|v| v.pixels.len()).sum::<usize>() as f64;
    let ratio = covered(&half) / covered(&full);
    assert!((0.22..0.28).contains(&ratio), "covered pixels at 1/2: {ratio:.3} of the full resolution's");
    // Labels come at the data's resolution and are reduced with the views.
    let (labelled, description) = views_with_prior(&half, &PriorSource::Oracle, &prior_context(0, None), usize::MAX)?;
    assert!(labelled.iter().all(|v| v.labels.is_some()), "{description}");

    let tmp = std::env::temp_dir().join(format!("reconstruct-downscale-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&tmp);
    let mut opts = ReconstructOptions::new("default", fit(), 1, tmp.join("run"));
    opts.progress = false;
    opts.eval_test_views = Some(1);
    opts.downscale = 2;
    let report = run(&opts, &PriorSource::None)?;
    // The relighting was scored against the data's own images: at the training resolution the
    // protocol's image comparison would have refused the size.
    assert!(report.evaluation.relight_psnr_raw.is_some_and(f64::is_finite), "relighting not scored");
    let json: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(tmp.join("run/report.json"))?)?;
    assert_eq!(json["identity"]["training"]["downscale"], 2, "report.json identity: {}", json["identity"]);
    std::fs::remove_dir_all(&tmp).ok();
    Ok(())
}

#[test]
fn a_divisor_that_does_not_divide_the_views_is_refused_by_name() {
    let err = prepare("default", None, GeometrySource::GroundTruth, &GeometryPassConfig::default(), &fit(), 3, false).err().expect("128 does not divide by 3");
    let text = format!("{err:#}");
    assert!(text.contains("do not divide by the training downscale 3") && text.contains("training view"), "{text}");
}

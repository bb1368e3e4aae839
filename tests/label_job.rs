//! `reconstruct label` writes label files that `--prior labels:DIR` reads back as the labels the
//! source gives a run (within 16-bit rounding); sources that make no labels are refused clearly.
//! Checked with idarb-sim, which needs no network weights and depends on the run's geometry and
//! seed, so the round trip also checks that the label job labels what a run would.

use anyhow::Result;
use reconstruct::fit::config::FitConfig;
use reconstruct::image::Image;
use reconstruct::jobs::label::{self, LabelOptions, ViewSelection};
use reconstruct::jobs::reconstruct::{labelled_views, prepare, prior_context, GeometrySource};
use reconstruct::prior::labels_dir::LabelsDir;
use reconstruct::prior::source::{make_prior, Prior, PriorSource};

fn assert_close(a: &Image, b: &Image, what: &str) {
    assert_eq!((a.width, a.height, a.channels), (b.width, b.height, b.channels), "{what}");
    let worst = a.data.iter().zip(&b.data).map(|(x, y)| (x - y).abs()).fold(0.0f32, f32::max);
    // 16-bit PNG codes: at most half a step apart.
    assert!(worst <= 0.5 / 65535.0 + 1e-6, "{what}: off by {worst}");
}

#[test]
fn label_files_read_back_as_the_runs_labels() -> Result<()> {
    let out = std::env::temp_dir().join(format!("reconstruct-label-job-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let opts = LabelOptions { scene: "default".into(), data: None, source: "idarb-sim".into(), views: ViewSelection::Count(3), out: out.clone(), idarb_weights: None, seed: 0 };
    let report = label::run(&opts)?;

    let prepared = prepare("default", None, GeometrySource::GroundTruth, &Default::default(), &FitConfig::default(), 1, false)?;
    let which = labelled_views(prepared.dataset.train.len(), 3);
    let names: Vec<String> = which.iter().map(|&i| prepared.dataset.train[i].name.clone()).collect();
    assert_eq!(report.views, names);
    let run_labels = make_prior(&PriorSource::IdarbSim(1.0), &prior_context(0, None))?.labels(&prepared.dataset, &which)?;
    let read = LabelsDir::open(&out)?.labels(&prepared.dataset, &which)?;
    for ((r, l), name) in run_labels.iter().zip(&read).zip(&names) {
        let (r, l) = (r.as_ref().expect("simulated label"), l.as_ref().expect("label file"));
        assert_close(&l.albedo, &r.albedo, &format!("{name} albedo"));
        assert_close(&l.normal, &r.normal, &format!("{name} normal"));
        assert_close(&l.metallic, &r.metallic, &format!("{name} metallic"));
        assert_close(&l.roughness, &r.roughness, &format!("{name} roughness"));
    }
    // Views the job did not label have no file.
    let mixed = LabelsDir::open(&out)?.labels(&prepared.dataset, &[which[0], which[0] + 1])?;
    assert!(mixed[0].is_some() && mixed[1].is_none());

    let err = format!("{:#}", label::run(&LabelOptions { source: "none".into(), ..opts.clone() }).unwrap_err());
    assert!(err.contains("--source none") && err.contains("idarb"), "{err}");
    std::fs::remove_dir_all(&out).ok();
    Ok(())
}

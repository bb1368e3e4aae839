//! A run's identity covers every setting that changes its result: changing any one of them, in
//! turn, changes the default run folder (so the new run starts afresh instead of resuming another
//! run's checkpoint) and shows up by name among the identity's differences (what a resume into
//! the same folder refuses with: `Fit::resume` prints exactly these, old → new). The iteration
//! count and the checkpoint interval change neither (a rerun extends the run).

mod common;

use std::path::{Path, PathBuf};

use anyhow::Result;
use reconstruct::fit::config::FitConfig;
use reconstruct::fit::geometry_pass::GeometryPassConfig;
use reconstruct::fit::settings_diff::differences;
use reconstruct::jobs::reconstruct::{load_scene, GeometrySource, ReconstructOptions};
use reconstruct::jobs::run_folder::default_run_folder;
use reconstruct::jobs::run_identity::RunIdentity;
use reconstruct::jobs::tradeoff::{default_points, point_folder};
use reconstruct::prior::source::PriorSource;
use reconstruct::render::effects::Effects;
use reconstruct::render::view::ShadingMode;
use reconstruct::scene::{crate_dir, SceneSpec};


struct Case {
    opts: ReconstructOptions,
    prior: PriorSource,
}

fn identity(c: &Case) -> Result<RunIdentity> {
    let (spec, dataset) = load_scene(&c.opts.scene, c.opts.data.as_ref())?;
    RunIdentity::new(&spec, &dataset, &c.opts, &c.prior)
}

fn base() -> Case {
    let mut opts = ReconstructOptions::new("default", FitConfig::default(), 16, PathBuf::new());
    opts.auto_mode = true;
    opts.labelled_views = 100;
    Case { opts, prior: PriorSource::None }
}

/// `change` applied to `from` must name `path` among the differences and move the default run folder.
fn separates(from: &Case, path: &str, change: impl FnOnce(&mut Case)) -> Result<()> {
    let (a, folder) = (identity(from)?, default_run_folder(&from.opts, &from.prior)?);
    let mut to = Case { opts: from.opts.clone(), prior: from.prior.clone() };
    change(&mut to);
    let b = identity(&to)?;
    let d = differences(&a.to_value()?, &b.to_value()?);
    assert!(d.iter().any(|d| d.path == path), "changing {path} must be named; differences: {d:?}");
    assert_ne!(a.digest(), b.digest(), "{path}");
    assert_ne!(folder, default_run_folder(&to.opts, &to.prior)?, "changing {path} must change the default run folder");
    Ok(())
}

#[test]
fn each_setting_separates_runs_and_is_named() -> Result<()> {
    let b = base();
    let spec = SceneSpec::find("default")?;
    spec.load_dataset()?; // renders the default scene into the cache on first use
    let tmp = std::env::temp_dir().join(format!("reconstruct-identity-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&tmp);

    // Data: another folder with the same content, then the same folder with other content.
    common::copy_dir(&spec.data_dir, &tmp.join("data"))?;
    separates(&b, "data.folder", |c| c.opts.data = Some(tmp.join("data")))?;
    let copy = Case { opts: ReconstructOptions { data: Some(tmp.join("data")), ..b.opts.clone() }, prior: PriorSource::None };
    separates(&copy, "data.content", |_| {
        let f = tmp.join("data/transforms_test.json");
        let text = std::fs::read_to_string(&f).expect("transforms_test.json");
        std::fs::write(&f, text.replacen("0.", "0.0", 1)).expect("rewrite");
    })?;

    // The scene spec: the same file but another test-probe strength.
    let text = std::fs::read_to_string(crate_dir().join("scenes/default.toml"))?;
    let stronger = tmp.join("default.toml");
    std::fs::write(&stronger, text.replace("[test_probes]\n", "[test_probes]\nstrength = 2.0\n").replacen("strength = 1.0\n\n[ground", "\n[ground", 1))?;
    separates(&b, "scene.test_probe_strength", |c| c.opts.scene = stronger.display().to_string())?;

    // Geometry source and the geometry pass.
    separates(&b, "geometry.source", |c| c.opts.geometry = GeometrySource::Reconstruct)?;
    let rec = Case { opts: ReconstructOptions { geometry: GeometrySource::Reconstruct, ..b.opts.clone() }, prior: PriorSource::None };
    separates(&rec, "geometry.pass.iterations", |c| c.opts.geometry_pass = GeometryPassConfig { iterations: 5, ..GeometryPassConfig::default() })?;
    separates(&rec, "geometry.pass.seed", |c| c.opts.geometry_pass.seed = 1)?;
    // A reconstruction with a prior holds its normals to the labels: the prior is part of the
    // geometry, and so is the prior's weight there.
    let rec_sim = Case { opts: rec.opts.clone(), prior: PriorSource::IdarbSim(1.0) };
    separates(&rec_sim, "geometry.labels.source", |c| c.prior = PriorSource::Oracle)?;
    separates(&rec_sim, "geometry.pass.normal_prior", |c| c.opts.geometry_pass.normal_prior *= 2.0)?;
    assert_eq!(identity(&rec_sim)?.geometry.labels, Some(identity(&rec_sim)?.prior));
    // Without a prior, or with the scene's mesh, the pass's normal prior does not enter: the
    // identity is the one written before the prior existed (no `normal_prior`, no `labels`).
    let weightless = |c: &Case| Case { opts: ReconstructOptions { geometry_pass: GeometryPassConfig { normal_prior: 0.0, ..c.opts.geometry_pass.clone() }, ..c.opts.clone() }, prior: c.prior.clone() };
    assert_eq!(identity(&rec)?, identity(&weightless(&rec))?);
    let text = serde_json::to_string(&identity(&rec)?.geometry)?;
    assert!(!text.contains("normal_prior") && !text.contains("labels"), "{text}");
    let gt_sim = Case { opts: b.opts.clone(), prior: PriorSource::IdarbSim(1.0) };
    assert_eq!(identity(&gt_sim)?.geometry, identity(&weightless(&gt_sim))?.geometry);
    assert_eq!(identity(&gt_sim)?.geometry.labels, None);

    // Prior: source, level, labelled views.
    separates(&b, "prior.source", |c| c.prior = PriorSource::Oracle)?;
    let sim = Case { opts: b.opts.clone(), prior: PriorSource::IdarbSim(1.0) };
    separates(&sim, "prior.source", |c| c.prior = PriorSource::IdarbSim(0.5))?;
    separates(&sim, "prior.labelled_views", |c| c.opts.labelled_views = 10)?;

    // Effects, mode, resolution.
    separates(&b, "training.effects", |c| c.opts.effects_override = Some(Effects { shadows: false, specular: true, indirect_bounces: 0 }))?;
    separates(&b, "training.mode", |c| {
        c.opts.auto_mode = false;
        c.opts.fit.mode = ShadingMode::MonteCarlo;
    })?;
    separates(&b, "training.downscale", |c| c.opts.downscale = 2)?;

    // Every optimiser setting and the seed.
    separates(&b, "training.fit.seed", |c| c.opts.fit.seed = 1)?;
    separates(&b, "training.fit.spp", |c| c.opts.fit.spp += 4)?;
    separates(&b, "training.fit.denoise", |c| c.opts.fit.denoise = !c.opts.fit.denoise)?;
    separates(&b, "training.fit.batch", |c| c.opts.fit.batch = 3)?;
    separates(&b, "training.fit.texture_res", |c| c.opts.fit.texture_res = 256)?;
    separates(&b, "training.fit.light_res", |c| c.opts.fit.light_res = 32)?;
    separates(&b, "training.fit.lr_material", |c| c.opts.fit.lr_material = 0.02)?;
    separates(&b, "training.fit.lr_light", |c| c.opts.fit.lr_light = 0.01)?;
    separates(&b, "training.fit.warmup_steps", |c| c.opts.fit.warmup_steps = 10)?;
    separates(&b, "training.fit.decay_steps", |c| c.opts.fit.decay_steps = 100)?;
    separates(&b, "training.fit.init_kd", |c| c.opts.fit.init_kd = 0.3)?;
    separates(&b, "training.fit.init_light", |c| c.opts.fit.init_light = 1.0)?;
    separates(&b, "training.fit.regularizers.light_white_balance", |c| c.opts.fit.regularizers.light_white_balance = 0.0)?;
    separates(&b, "training.fit.prior.albedo", |c| c.opts.fit.prior.albedo = 2.0)?;
    separates(&b, "training.fit.prior.anneal", |c| c.opts.fit.prior.anneal = 1.0)?;

    // Evaluation settings.
    separates(&b, "evaluation.spp", |c| c.opts.eval_spp = 4)?;
    separates(&b, "evaluation.test_views", |c| c.opts.eval_test_views = Some(1))?;

    // Not part of it: the length (a rerun extends the run) and the checkpoint interval…
    let mut longer = b.opts.clone();
    longer.fit.iterations *= 3;
    longer.fit.checkpoint_every = 7;
    assert_eq!(default_run_folder(&b.opts, &b.prior)?, default_run_folder(&longer, &b.prior)?);
    assert_eq!(identity(&b)?, identity(&Case { opts: longer, prior: PriorSource::None })?);
    // …unless the prior anneals over the run's length.
    let anneal = Case { opts: ReconstructOptions { fit: FitConfig { prior: reconstruct::fit::config::PriorWeights { anneal: 1.0, ..Default::default() }, ..FitConfig::default() }, ..b.opts.clone() }, prior: PriorSource::IdarbSim(1.0) };
    separates(&anneal, "training.fit.iterations", |c| c.opts.fit.iterations = 10)?;

    // Trade-off points: forced effects and resolution get folders of their own.
    let pts = default_points(30);
    let out = Path::new("t");
    let no_shadows = pts.iter().position(|p| p.name.contains("no shadows")).expect("a no-shadow point");
    let mut same_slot = pts[no_shadows].clone();
    same_slot.effects = None;
    assert_ne!(point_folder(out, no_shadows, &pts[no_shadows]), point_folder(out, no_shadows, &same_slot));
    same_slot = pts[no_shadows].clone();
    same_slot.downscale = 2;
    assert_ne!(point_folder(out, no_shadows, &pts[no_shadows]), point_folder(out, no_shadows, &same_slot));
    std::fs::remove_dir_all(&tmp).ok();
    Ok(())
}

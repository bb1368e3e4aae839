//! The reconstruct job: a scene's training views → materials and light optimised on fixed geometry
//! (the ground-truth mesh) → evaluation (NeRFactor protocol) → a run folder with the model, the
//! light, validation renders and a report.
//!
//! Run folder: `model/` (OBJ + MTL, glTF, kd/ks PNG), `light/` (lat-long EXR, cube faces),
//! `renders/` (validation views under the learned light), `checkpoint/` (resume state),
//! `geometry.json` (reconstructed geometry, reused by a rerun), `report.md`, `plots/`, and
//! `report.json`, written last. What makes two runs the same run, and how a killed run resumes:
//! docs/runs.md.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use serde::Serialize;

use crate::fit::batch_render::ShadingContext;
use crate::fit::config::FitConfig;
use crate::eval::protocol::{evaluate, EvalSettings, Evaluation};
use crate::fit::export::{write_light, write_material_maps, write_model, write_render};
use crate::fit::fitter::Fit;
use crate::fit::history::IterationRecord;
use crate::fit::labels::PixelLabels;
use crate::prior::idarb::labels::IdarbOptions;
use crate::prior::source::{make_prior, PriorContext, PriorSource};
use crate::fit::parameters::Parameters;
use crate::fit::training_view::TrainingView;
use crate::fit::view_screening::screen_views;
use crate::geometry::atlas::{self, Atlas, AtlasSource};
use crate::geometry::bvh::Bvh;
pub use crate::jobs::geometry::GeometrySource;
use crate::jobs::geometry::{obtain_geometry, score_geometry, scores_summary, GeometryOutcome, GeometryReport, PassLabels};
use crate::jobs::geometry_cache::obtain_or_reuse;
use crate::jobs::run_identity::{PriorIdentity, RunIdentity};
use crate::atomic_write;
use crate::fit::geometry_pass::{interpolate, transfer_vertex_values, GeometryPassConfig};
use crate::material::texture_maps::MaterialTextures;
use crate::material::SurfaceParams;
use crate::light::CubeMap;
use crate::jobs::report_markdown::{markdown, write_plots, PLOTS_DIR};
use crate::light::brdf_lut::BrdfLut;
use crate::light::prefilter::PrefilterOptions;
use crate::render::effects::{self, EffectChoice, Effects};
use crate::render::splitsum_op::LightMaps;
use crate::render::view::{ray_epsilon, ShadingMode};
use crate::scene::dataset::Dataset;
use crate::scene::SceneSpec;

#[derive(Clone, Debug)]
pub struct ReconstructOptions {
    pub scene: String,
    pub data: Option<PathBuf>,
    pub geometry: GeometrySource,
    /// Settings of the geometry pass (used when the geometry is reconstructed).
    pub geometry_pass: GeometryPassConfig,
    pub fit: FitConfig,
    /// Monte Carlo samples of the evaluation renders.
    pub eval_spp: u32,
    pub out: PathBuf,
    pub progress: bool,
    /// Training views the prior labels (evenly spread).
    pub labelled_views: usize,
    /// IDArb weights folder for `--prior idarb` (else `$IDARB_WEIGHTS`).
    pub idarb_weights: Option<PathBuf>,
    /// Effects forced on or off instead of the scene's choice (trade-off studies).
    pub effects_override: Option<Effects>,
    /// Relight at most this many test views (None = all).
    pub eval_test_views: Option<usize>,
    /// Choose `fit.mode` from the scene's effects ([`auto_training_mode`]) instead of using it.
    pub auto_mode: bool,
    /// Train the materials on views this many times smaller (box-filtered targets; 1 = the data's
    /// resolution). The geometry pass and the evaluation are not affected: the pass has its own
    /// cap (`jobs::geometry::GEOMETRY_MAX_SIDE`), and the evaluation renders at the data's
    /// resolution, as the protocol asks.
    pub downscale: usize,
}

/// The training shading mode the effects call for: Monte Carlo when they need visibility
/// (shadows or interreflection, which split-sum's unoccluded prefiltered light cannot give),
/// split-sum otherwise (the fastest). Returns the mode and the reason.
pub fn auto_training_mode(effects: &Effects) -> (ShadingMode, String) {
    let needs: Vec<&str> = [(effects.shadows, "shadows"), (effects.interreflection(), "interreflection")].into_iter().filter(|e| e.0).map(|e| e.1).collect();
    if needs.is_empty() {
        (ShadingMode::SplitSum, "split-sum (auto): the scene needs no visibility, so the fastest mode is exact enough".into())
    } else {
        (ShadingMode::MonteCarlo, format!("Monte Carlo (auto): the scene needs {}, which split-sum cannot simulate", needs.join(" and ")))
    }
}

impl ReconstructOptions {
    /// A run of `scene` on its ground-truth mesh with `fit`, into `out`: the scene's own data,
    /// every training view labelled, all test views relit, the scene's effects, a progress bar.
    pub fn new(scene: &str, fit: FitConfig, eval_spp: u32, out: PathBuf) -> Self {
        ReconstructOptions {
            scene: scene.to_string(),
            data: None,
            geometry: GeometrySource::GroundTruth,
            geometry_pass: GeometryPassConfig::default(),
            fit,
            eval_spp,
            out,
            progress: true,
            labelled_views: usize::MAX,
            idarb_weights: None,
            effects_override: None,
            eval_test_views: None,
            auto_mode: false,
            downscale: 1,
        }
    }
}

/// Everything a run needs that does not depend on the fit settings (reused across ablation runs).
pub struct Prepared {
    pub spec: SceneSpec,
    pub dataset: Dataset,
    pub atlas: Atlas,
    pub bvh: Arc<Bvh>,
    /// Where the mesh came from, and the reconstruction's records.
    pub geometry: GeometryReport,
    /// The visual hull, when the geometry was reconstructed (for the geometry metrics).
    pub hull: Option<crate::geometry::Mesh>,
    /// Starting textures baked from the geometry pass's per-vertex colour (reconstruction only).
    pub initial_textures: Option<MaterialTextures>,
    pub effects: EffectChoice,
    pub views: Vec<TrainingView>,
    /// Training resolution divisor of `views`.
    pub downscale: usize,
    pub stage_seconds: Vec<(String, f64)>,
}

/// A scene's spec (its data folder replaced by `data` when given) and its dataset (view list and
/// cameras; no image is read).
pub fn load_scene(scene: &str, data: Option<&PathBuf>) -> Result<(SceneSpec, Dataset)> {
    let mut spec = SceneSpec::find(scene)?;
    if let Some(dir) = data {
        spec = spec.with_data_dir(dir);
    }
    let dataset = spec.load_dataset()?;
    Ok((spec, dataset))
}

/// Load the scene, obtain the geometry (the scene's mesh or reconstructed), build the atlas and
/// BVH, choose the effects, trace the training views. `downscale` > 1 trains on views
/// `downscale`× smaller (box-filtered targets). A reconstruction's pass runs without labels.
pub fn prepare(scene: &str, data: Option<&PathBuf>, geometry: GeometrySource, pass: &GeometryPassConfig, fit: &FitConfig, downscale: usize, progress: bool) -> Result<Prepared> {
    prepare_in(scene, data, fit, downscale, progress, |spec, dataset| obtain_geometry(spec, dataset, geometry, pass, None, progress))
}

/// [`prepare`] for a run of `opts` with `prior`: a reconstruction's pass holds its normals to the
/// prior's labels (of the views the run labels), and is kept in `opts.out` and reused from there
/// by a rerun of the same identity (`jobs::geometry_cache`).
pub fn prepare_run(opts: &ReconstructOptions, prior: &PriorSource) -> Result<Prepared> {
    prepare_in(&opts.scene, opts.data.as_ref(), &opts.fit, opts.downscale, opts.progress, |spec, dataset| {
        let identity = PriorIdentity::of(prior, opts.labelled_views, dataset);
        let source = make_prior(prior, &prior_context(opts.fit.seed, opts.idarb_weights.clone()))?;
        let labels = PassLabels { prior: source.as_ref(), views: labelled_views(dataset.train.len(), opts.labelled_views) };
        let given = identity.labels_any().then_some((&identity, &labels));
        obtain_or_reuse(&opts.out, spec, dataset, opts.geometry, &opts.geometry_pass, given, opts.progress)
    })
}

fn prepare_in(
    scene: &str,
    data: Option<&PathBuf>,
    fit: &FitConfig,
    downscale: usize,
    progress: bool,
    obtain: impl FnOnce(&SceneSpec, &Dataset) -> Result<GeometryOutcome>,
) -> Result<Prepared> {
    let texture_res = fit.texture_res;
    let mut stages = Vec::new();
    let t = Instant::now();
    let (spec, dataset) = load_scene(scene, data)?;
    stages.push(("load scene".to_string(), t.elapsed().as_secs_f64()));

    let t = Instant::now();
    let outcome = obtain(&spec, &dataset)?;
    stages.push(("geometry".to_string(), t.elapsed().as_secs_f64()));
    let t = Instant::now();
    let mesh = outcome.mesh;
    let atlas = atlas::build(&mesh, texture_res).with_context(|| format!("building the UV atlas of scene {:?}", spec.name))?;
    let bvh = Arc::new(Bvh::build(&atlas.mesh));
    // The geometry pass's colour, baked into the atlas: the material pass starts from it.
    let initial_textures = outcome.vertex_kd.as_ref().map(|kd| {
        let kd = transfer_vertex_values(&mesh, kd, &atlas.mesh);
        MaterialTextures::bake_with(&atlas, texture_res, |t, b| SurfaceParams {
            kd: interpolate(&atlas.mesh, &kd, t, glam::Vec2::new(b.y, b.z)),
            roughness: fit.init_roughness,
            metallic: fit.init_metallic,
        })
    });
    stages.push(("atlas, BVH".to_string(), t.elapsed().as_secs_f64()));
    let mut geometry_report = outcome.report;
    if geometry_report.used == GeometrySource::Reconstruct {
        let scores = score_geometry(&spec, &dataset, &atlas.mesh, &bvh, outcome.hull.as_ref());
        if progress {
            eprintln!("{}", scores_summary(&scores));
        }
        stages.push(("score geometry".to_string(), scores.seconds));
        geometry_report.scores = Some(scores);
    }

    let t = Instant::now();
    // Materials are what we solve for, so `auto` may not look at the ground-truth ones.
    let probes = effects::probe_views(&atlas.mesh, &bvh, &dataset.train);
    let effects = effects::choose(spec.effects, &atlas.mesh, &bvh, &probes, false);
    stages.push(("choose effects".to_string(), t.elapsed().as_secs_f64()));

    let t = Instant::now();
    let views: Vec<TrainingView> =
        dataset.train.iter().enumerate().map(|(i, v)| TrainingView::new(v, i, &atlas.mesh, &bvh, downscale)).collect::<Result<_>>()?;
    let views = screen_views(views, geometry_report.used == GeometrySource::GroundTruth, &spec.name)?;
    if views.iter().all(|v| v.is_empty()) {
        bail!("no training view of scene {:?} sees the mesh: check the cameras and the geometry", spec.name);
    }
    stages.push(("trace training views".to_string(), t.elapsed().as_secs_f64()));
    Ok(Prepared { spec, dataset, atlas, bvh, geometry: geometry_report, hull: outcome.hull, initial_textures, effects, views, downscale, stage_seconds: stages })
}

/// The shading context of a run on `prepared` with `config`.
pub fn shading_context(prepared: &Prepared, config: &FitConfig) -> ShadingContext {
    ShadingContext {
        mode: config.mode,
        effects: prepared.effects.effects,
        spp: config.spp,
        denoise: config.denoise,
        seed: config.seed,
        ray_epsilon: ray_epsilon(&prepared.atlas.mesh),
        mesh: Arc::new(prepared.atlas.mesh.clone()),
        bvh: prepared.bvh.clone(),
        light_maps: Arc::new(LightMaps::matrix_free(config.light_res, PrefilterOptions::default())),
        lut: Arc::new(BrdfLut::standard()),
    }
}

#[derive(Serialize)]
pub struct ReconstructReport {
    pub scene: String,
    pub data_dir: PathBuf,
    pub geometry: GeometryReport,
    pub atlas: String,
    pub effects: EffectChoice,
    /// The training shading mode and why (chosen by the user or from the effects).
    pub training_mode: String,
    pub prior: String,
    /// What the run's checkpoint and folder name stand for (docs/runs.md).
    pub identity: RunIdentity,
    pub config: FitConfig,
    pub evaluation: Evaluation,
    pub stage_seconds: Vec<(String, f64)>,
    pub history: Vec<IterationRecord>,
}

fn atlas_description(a: &Atlas) -> String {
    match &a.source {
        AtlasSource::OwnUvs => format!("the mesh's own UVs ({}², {:.0}% used)", a.resolution, 100.0 * a.stats.utilisation),
        AtlasSource::Generated { reason, charts } => {
            format!("generated: {charts} charts, {:.0}% of {}² used ({reason})", 100.0 * a.stats.utilisation, a.resolution)
        }
    }
}

/// The effects a run used, for its report: the scene's choice, or the run's override (trade-off
/// studies) with the scene's choice named beside it.
fn reported_effects(scene: &EffectChoice, run_override: Option<Effects>) -> EffectChoice {
    match run_override {
        Some(e) if e != scene.effects => {
            let chosen = EffectChoice { effects: scene.effects, reasons: Vec::new() };
            EffectChoice { effects: e, reasons: vec![format!("set by the run instead of the scene's choice ({chosen})")] }
        }
        _ => scene.clone(),
    }
}

/// Fit on prepared data, evaluate, and write the run folder. `prior` is the label source and
/// `description` its description for the report.
///
/// Rerunning after a kill at any point gives the same report: the fit resumes from its last
/// checkpoint (refused when the run identity differs), and the exports and the evaluation, which
/// are deterministic, are redone and each folder and file replaced whole (`atomic_write`);
/// `report.json` is written last, so its presence means the run finished.
pub fn run_prepared(prepared: &Prepared, views: Vec<TrainingView>, opts: &ReconstructOptions, prior: &PriorSource, description: &str) -> Result<ReconstructReport> {
    anyhow::ensure!(
        prepared.downscale == opts.downscale,
        "run {}: the views were prepared at 1/{} of their resolution for a run at 1/{}",
        opts.out.display(),
        prepared.downscale,
        opts.downscale
    );
    let mut stages = prepared.stage_seconds.clone();
    std::fs::create_dir_all(&opts.out).with_context(|| format!("cannot create the run folder {}", opts.out.display()))?;
    let effects = opts.effects_override.unwrap_or(prepared.effects.effects);
    let mut config = opts.fit.clone();
    config.prior_source = prior.tag();
    let training_mode = if opts.auto_mode {
        let (mode, why) = auto_training_mode(&effects);
        config.mode = mode;
        why
    } else {
        format!("{:?} (set by the run)", config.mode)
    };
    if opts.progress {
        eprintln!("training mode: {training_mode}");
    }
    let identity = RunIdentity::new(&prepared.spec, &prepared.dataset, opts, prior)?.with_decided(effects, config.mode);
    let mut ctx = shading_context(prepared, &config);
    ctx.effects = effects;
    let start = match &prepared.initial_textures {
        Some(t) => Parameters::from_values(t, &CubeMap::constant(config.light_res, glam::Vec3::splat(config.init_light)))?,
        None => Parameters::initial(&config)?,
    };
    let mut fit = Fit::new(config.clone(), start, views, ctx)?;
    fit.set_identity(identity.to_value()?);
    let checkpoint_dir = opts.out.join("checkpoint");
    if fit.resume(&checkpoint_dir)? && opts.progress {
        eprintln!("resuming from {} at iteration {}", checkpoint_dir.display(), fit.iteration());
    }
    let t = Instant::now();
    fit.run(Some(&checkpoint_dir), opts.progress)?;
    stages.push(("optimise".to_string(), t.elapsed().as_secs_f64()));

    let t = Instant::now();
    let textures = fit.params.textures()?;
    let light = fit.params.light_cube()?;
    // With vertex refinement the model and the evaluation are the moved mesh.
    let refined = fit.refined_mesh().map(|m| {
        let bvh = Arc::new(Bvh::build(&m));
        (m, bvh)
    });
    let (mesh, bvh) = match &refined {
        Some((m, b)) => (m, b),
        None => (&prepared.atlas.mesh, &prepared.bvh),
    };
    atomic_write::replace_dir(&opts.out.join("model"), |d| write_model(d, mesh, &textures))?;
    atomic_write::replace_dir(&opts.out.join("light"), |d| write_light(d, &light))?;
    stages.push(("export".to_string(), t.elapsed().as_secs_f64()));

    let t = Instant::now();
    if opts.progress {
        eprintln!("evaluating");
    }
    let test_probes = prepared.spec.load_test_probes().unwrap_or_else(|e| {
        eprintln!("relighting skipped: {e:#}");
        Vec::new()
    });
    let settings = EvalSettings {
        relight_mode: ShadingMode::MonteCarlo,
        spp: opts.eval_spp,
        supersample: 2,
        seed: config.seed,
        effects,
        train_mode: config.mode,
        train_view_stride: 10,
        max_test_views: opts.eval_test_views,
    };
    let evaluated = evaluate(&prepared.dataset, mesh, bvh, &textures, &light, &test_probes, &settings)?;
    atomic_write::replace_dir(&opts.out.join("renders"), |d| {
        for (name, img) in &evaluated.val_renders {
            write_render(d, name, img)?;
        }
        for maps in &evaluated.val_materials {
            write_material_maps(d, maps)?;
        }
        Ok(())
    })?;
    stages.push(("evaluate".to_string(), t.elapsed().as_secs_f64()));

    let report = ReconstructReport {
        scene: prepared.spec.name.clone(),
        data_dir: prepared.spec.data_dir.clone(),
        geometry: prepared.geometry.clone(),
        atlas: atlas_description(&prepared.atlas),
        effects: reported_effects(&prepared.effects, opts.effects_override),
        training_mode,
        prior: description.to_string(),
        identity,
        config,
        evaluation: evaluated.metrics,
        stage_seconds: stages,
        history: fit.history.clone(),
    };
    let mut plots = Vec::new();
    atomic_write::replace_dir(&opts.out.join(PLOTS_DIR), |d| {
        plots = write_plots(d, &report.history)?;
        Ok(())
    })?;
    atomic_write::write(&opts.out.join("report.md"), markdown(&report, &plots))?;
    atomic_write::write(&opts.out.join("report.json"), serde_json::to_string_pretty(&report)?)?;
    Ok(report)
}

/// Which training views get labels: every `stride`-th, `count` of them (labelling is expensive).
pub fn labelled_views(total: usize, count: usize) -> Vec<usize> {
    let count = count.min(total);
    if count == 0 {
        return Vec::new();
    }
    (0..count).map(|k| k * total / count).collect()
}

/// The training views with the prior's labels attached (a copy of `prepared.views`), and the
/// prior's description for the report.
pub fn views_with_prior(prepared: &Prepared, source: &PriorSource, ctx: &PriorContext, labelled: usize) -> Result<(Vec<TrainingView>, String)> {
    let prior = make_prior(source, ctx)?;
    let mut views = prepared.views.clone();
    if *source == PriorSource::None {
        return Ok((views, prior.describe()));
    }
    // Positions in `views` (views with an empty mask are not there) and the same views' dataset indices.
    let which = labelled_views(views.len(), labelled);
    let dataset_indices: Vec<usize> = which.iter().map(|&k| views[k].index).collect();
    let labels = prior.labels(&prepared.dataset, &dataset_indices).with_context(|| format!("getting labels from --prior {}", source.tag()))?;
    let mut count = 0;
    for (&i, l) in which.iter().zip(labels) {
        if let Some(l) = l {
            let v = &mut views[i];
            // Labels come at the data's resolution; a run at a reduced one takes them reduced alike.
            let l = if prepared.downscale > 1 && l.mask.width == v.camera.width * prepared.downscale {
                l.downsampled(prepared.downscale).with_context(|| format!("labels of view {}", v.name))?
            } else {
                l
            };
            v.labels = Some(PixelLabels::gather(&l, &v.pixels, v.camera.width, v.camera.height, v.camera.c2w, &v.name)?);
            count += 1;
        }
    }
    Ok((views, format!("{} — {count} of {} training views labelled", prior.describe(), prepared.views.len())))
}

/// The prior context of a run (seed for simulated labels, cache for IDArb's; no label source reads the geometry).
pub fn prior_context(seed: u64, idarb_weights: Option<PathBuf>) -> PriorContext {
    PriorContext {
        idarb_weights,
        cache_dir: crate::scene::spec::cache_dir(),
        idarb: IdarbOptions::default(),
        seed,
    }
}

/// Prepare the scene and run (the `reconstruct` command).
pub fn run(opts: &ReconstructOptions, prior: &PriorSource) -> Result<ReconstructReport> {
    let prepared = prepare_run(opts, prior)?;
    if opts.progress {
        eprintln!("scene {}: {} training views; atlas: {}", prepared.spec.name, prepared.views.len(), atlas_description(&prepared.atlas));
        eprintln!("effects: {}", prepared.effects);
    }
    let ctx = prior_context(opts.fit.seed, opts.idarb_weights.clone());
    let (views, description) = views_with_prior(&prepared, prior, &ctx, opts.labelled_views)?;
    if opts.progress {
        eprintln!("prior: {description}");
    }
    run_prepared(&prepared, views, opts, prior, &description)
}

impl ReconstructReport {
    /// A few lines for the terminal.
    pub fn summary(&self) -> String {
        let f = |v: Option<f64>| v.map_or("-".to_string(), |v| format!("{v:.2}"));
        let e = &self.evaluation;
        let mut s = format!(
            "scene {} | prior {} | {:?}\n\
             re-rendered training views: {} dB, validation views: {} dB\n\
             albedo PSNR raw / scaled: {} / {} dB\n\
             relighting PSNR raw / scaled: {} / {} dB ({} renders)\n\
             roughness MSE {}, metallic MSE {}, normal error {}°",
            self.scene,
            self.prior,
            self.config.mode,
            f(e.train_psnr),
            f(e.val_psnr),
            f(e.albedo_psnr_raw),
            f(e.albedo_psnr_scaled),
            f(e.relight_psnr_raw),
            f(e.relight_psnr_scaled),
            e.relight.len(),
            e.roughness_mse.map_or("-".into(), |v| format!("{v:.4}")),
            e.metallic_mse.map_or("-".into(), |v| format!("{v:.4}")),
            f(e.normal_error_deg),
        );
        for line in &e.not_computed {
            s.push_str(&format!("\nnot computed: {line}"));
        }
        for (stage, secs) in &self.stage_seconds {
            s.push_str(&format!("\n{stage}: {secs:.1} s"));
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_report_names_the_effects_the_run_used() {
        let scene = EffectChoice { effects: Effects::with_bounces(3), reasons: vec!["interreflection on (auto)".into()] };
        assert_eq!(reported_effects(&scene, None).effects, scene.effects);
        assert_eq!(reported_effects(&scene, Some(scene.effects)).reasons, scene.reasons);
        let off = Effects { shadows: false, specular: true, indirect_bounces: 0 };
        let r = reported_effects(&scene, Some(off));
        assert_eq!(r.effects, off);
        assert!(r.reasons[0].contains("instead of the scene's choice (shadows on"), "{:?}", r.reasons);
    }
}

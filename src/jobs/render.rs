//! The render job: a scene's ground-truth mesh and materials rendered under chosen probes for
//! chosen views, in either shading mode, written as PNG (sRGB) and EXR (linear, straight alpha),
//! each compared with the dataset's own image when it has one (NeRFactor protocol: sRGB over
//! white, alpha > 0.8). A `report.json` records every score, the effects chosen and why, and the
//! time each stage took.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use serde::Serialize;

use crate::eval::metrics::protocol_psnr;
use crate::geometry::bvh::Bvh;
use crate::geometry::Mesh;
use crate::image::{io, Image};
use crate::render::effects::{self, EffectChoice};
use crate::render::view::{render_view, PreparedLight, RenderSettings, ShadingMode};
use crate::scene::dataset::{Dataset, View};
use crate::scene::probe::Probe;
use crate::scene::SceneSpec;
use crate::scene_data::ground_truth_mesh;

#[derive(Clone, Debug)]
pub struct RenderOptions {
    pub scene: String,
    /// Overrides the spec's data folder.
    pub data: Option<PathBuf>,
    /// View names (e.g. `test_049`); empty means every test view.
    pub views: Vec<String>,
    /// `train` (the training probe), a test-probe name, or a .hdr/.exr path; empty means the
    /// training probe (when the scene names one) and every test probe.
    pub probes: Vec<String>,
    pub modes: Vec<ShadingMode>,
    pub spp: u32,
    pub supersample: usize,
    pub seed: u64,
    pub out: PathBuf,
}

#[derive(Serialize)]
pub struct RenderRecord {
    pub view: String,
    pub probe: String,
    pub mode: ShadingMode,
    pub seconds: f64,
    /// PSNR (dB) against the dataset's image for this view and probe, when there is one.
    pub psnr_db: Option<f64>,
    pub png: PathBuf,
    pub exr: PathBuf,
}

#[derive(Serialize)]
pub struct RenderReport {
    pub scene: String,
    pub data_dir: PathBuf,
    pub triangles: usize,
    pub effects: EffectChoice,
    pub spp: u32,
    pub supersample: usize,
    pub stage_seconds: Vec<(String, f64)>,
    pub renders: Vec<RenderRecord>,
}

impl RenderReport {
    /// Mean PSNR per shading mode over the renders that have a reference.
    pub fn mean_psnr(&self, mode: ShadingMode) -> Option<f64> {
        let scores: Vec<f64> = self.renders.iter().filter(|r| r.mode == mode).filter_map(|r| r.psnr_db).collect();
        (!scores.is_empty()).then(|| scores.iter().sum::<f64>() / scores.len() as f64)
    }
}

/// Which probe a `--probe` value means, and the dataset image lit by it (if any).
fn resolve_probe(spec: &SceneSpec, key: &str) -> Result<(String, Probe)> {
    if key == "train" {
        let p = spec.load_train_probe()?;
        return Ok(("train".into(), p));
    }
    let as_path = Path::new(key);
    if as_path.extension().is_some_and(|e| e == "hdr" || e == "exr") {
        let name = as_path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| key.into());
        return Ok((name, Probe::load(as_path, 1.0)?));
    }
    if spec.test_probes.names.iter().any(|n| n == key) {
        return Ok((key.into(), Probe::load(&spec.test_probe_path(key)?, spec.test_probes.strength)?));
    }
    bail!("unknown probe {key:?}: use `train`, one of {} or a path to a .hdr/.exr file", spec.test_probes.names.join(", "))
}

fn reference_image(view: &View, probe: &str) -> Result<Option<Image>> {
    if probe == "train" {
        return view.load_rgba().map(Some);
    }
    if view.has_relit(probe) {
        return view.load_relit(probe).map(Some);
    }
    Ok(None)
}

/// Effects for the scene: `auto` decided from G-buffers of a few training views.
pub fn choose_effects(spec: &SceneSpec, dataset: &Dataset, mesh: &Mesh, bvh: &Bvh) -> EffectChoice {
    effects::choose(spec.effects, mesh, bvh, &effects::probe_views(mesh, bvh, &dataset.train), true)
}

pub fn run(opts: &RenderOptions) -> Result<RenderReport> {
    let mut stages = Vec::new();
    let mut stage = |name: &str, t: Instant| stages.push((name.to_string(), t.elapsed().as_secs_f64()));

    let t = Instant::now();
    let mut spec = SceneSpec::find(&opts.scene)?;
    if let Some(dir) = &opts.data {
        spec = spec.with_data_dir(dir);
    }
    let dataset = spec.load_dataset()?;
    stage("load scene", t);

    let t = Instant::now();
    let mesh = ground_truth_mesh(&spec)?;
    let bvh = Bvh::build(&mesh);
    stage("load mesh + build BVH", t);

    let t = Instant::now();
    let effects = choose_effects(&spec, &dataset, &mesh, &bvh);
    eprintln!("effects: {effects}");
    stage("choose effects", t);

    let views: Vec<&View> = if opts.views.is_empty() { dataset.test.iter().collect() } else { opts.views.iter().map(|n| dataset.view(n)).collect::<Result<_>>()? };
    let probe_keys: Vec<String> = if opts.probes.is_empty() {
        // The training probe is optional (a reconstruction learns the light).
        spec.train_probe.iter().map(|_| "train".to_string()).chain(spec.test_probes.names.iter().cloned()).collect()
    } else {
        opts.probes.clone()
    };
    let t = Instant::now();
    let probes: Vec<(String, PreparedLight)> = probe_keys
        .iter()
        .map(|k| {
            let (name, probe) = resolve_probe(&spec, k)?;
            Ok((name, PreparedLight::from_probe(&probe)))
        })
        .collect::<Result<_>>()?;
    stage("load probes", t);

    std::fs::create_dir_all(&opts.out).with_context(|| format!("cannot create {}", opts.out.display()))?;
    let t = Instant::now();
    let mut renders = Vec::new();
    for view in &views {
        let dir = opts.out.join(&view.name);
        std::fs::create_dir_all(&dir).with_context(|| format!("cannot create {}", dir.display()))?;
        for (probe, light) in &probes {
            let reference = reference_image(view, probe)?;
            for &mode in &opts.modes {
                let settings = RenderSettings { mode, spp: opts.spp, supersample: opts.supersample, seed: opts.seed, effects: effects.effects };
                let started = Instant::now();
                let img = render_view(&mesh, &bvh, light, &view.camera, &settings);
                let seconds = started.elapsed().as_secs_f64();
                let tag = mode.tag();
                let png = dir.join(format!("{probe}_{tag}.png"));
                let exr = dir.join(format!("{probe}_{tag}.exr"));
                io::write_png(&png, &img.map_channels(3, crate::color::linear_to_srgb))?;
                io::write_exr(&exr, &img)?;
                let psnr_db = reference.as_ref().map(|r| protocol_psnr(&img, r));
                renders.push(RenderRecord { view: view.name.clone(), probe: probe.clone(), mode, seconds, psnr_db, png, exr });
            }
        }
    }
    stage("render", t);

    let report = RenderReport {
        scene: spec.name.clone(),
        data_dir: spec.data_dir.clone(),
        triangles: mesh.triangles.len(),
        effects,
        spp: opts.spp,
        supersample: opts.supersample,
        stage_seconds: stages,
        renders,
    };
    let path = opts.out.join("report.json");
    std::fs::write(&path, serde_json::to_string_pretty(&report)?).with_context(|| format!("cannot write {}", path.display()))?;
    Ok(report)
}

//! Evaluation of a fitted model by the NeRFactor protocol (docs/model.md, *Evaluation*):
//! - albedo PSNR on the validation views, raw and after a per-channel least-squares scale
//!   (linear values, alpha > 0.9, scale fitted on the first validation view), PSNR taken on
//!   sRGB-encoded values;
//! - relighting PSNR on the test views under each test probe (sRGB over white, alpha > 0.8), with
//!   the raw and the scaled albedo;
//! - roughness and metallic MSE and the shading normal's mean angular error on the validation views;
//! - re-rendered training views under the learned light, in the training shading mode.
//!
//! Maps the dataset lacks (e.g. no albedo in a NeRF-synthetic scene) give `None`, not a failure,
//! and `not_computed` says which metrics are missing and why.

use anyhow::{Context, Result};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::eval::metrics::{albedo_scale, mask_from_alpha, mean_angular_error_deg, mse, protocol_psnr, psnr, scale_colour};
use crate::geometry::bvh::Bvh;
use crate::geometry::Mesh;
use crate::image::Image;
use crate::light::CubeMap;
use crate::material::texture_maps::MaterialTextures;
use crate::render::effects::Effects;
use crate::render::gbuffer::GBuffer;
use crate::render::view::{render_view_with, PreparedLight, RenderSettings, ShadingMode};
use crate::scene::dataset::{Dataset, View};
use crate::scene::probe::Probe;

#[derive(Clone, Debug)]
pub struct EvalSettings {
    /// Mode and samples of the relighting renders (Monte Carlo with the scene's effects by default).
    pub relight_mode: ShadingMode,
    pub spp: u32,
    pub supersample: usize,
    pub seed: u64,
    pub effects: Effects,
    /// Mode of the re-rendered training views (the training mode).
    pub train_mode: ShadingMode,
    /// Every k-th training view is re-rendered.
    pub train_view_stride: usize,
    /// At most this many test views are relit (None = all).
    pub max_test_views: Option<usize>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RelightRecord {
    pub view: String,
    pub probe: String,
    pub psnr_raw: f64,
    pub psnr_scaled: f64,
}

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Evaluation {
    pub albedo_psnr_raw: Option<f64>,
    pub albedo_psnr_scaled: Option<f64>,
    /// The per-channel scale (linear) fitted on the first validation view.
    pub albedo_scale: Option<[f64; 3]>,
    pub relight_psnr_raw: Option<f64>,
    pub relight_psnr_scaled: Option<f64>,
    pub relight: Vec<RelightRecord>,
    pub roughness_mse: Option<f64>,
    pub metallic_mse: Option<f64>,
    pub normal_error_deg: Option<f64>,
    /// Mean PSNR of re-rendered training views and of the validation views (learned light).
    pub train_psnr: Option<f64>,
    pub val_psnr: Option<f64>,
    /// The metrics the dataset cannot support, each with the reason ("albedo PSNR: no validation
    /// view has albedo.png").
    pub not_computed: Vec<String>,
}

/// What the dataset lacks for the metrics (empty when every metric can be computed).
fn missing_metrics(dataset: &Dataset, test_probes: &[Probe], max_test_views: Option<usize>) -> Vec<String> {
    let mut out = Vec::new();
    let val = &dataset.val;
    if val.is_empty() {
        out.push("validation PSNR, albedo, roughness, metallic and normal metrics: the dataset has no validation views".to_string());
    } else if !val.iter().any(View::has_albedo) {
        out.push("albedo PSNR (raw and scaled), roughness and metallic MSE, normal error, scaled relighting: no validation view has albedo.png".to_string());
    } else {
        let maps = [
            ("roughness MSE", "roughness.png", View::has_roughness as fn(&View) -> bool),
            ("metallic MSE", "metallic.png", View::has_metallic),
            ("normal error", "normal.png", View::has_normal),
        ];
        for (metric, file, has) in maps {
            if !val.iter().any(has) {
                out.push(format!("{metric}: no validation view has {file}"));
            }
        }
    }
    let tests: Vec<&View> = dataset.test.iter().take(max_test_views.unwrap_or(usize::MAX)).collect();
    let unreferenced: Vec<&str> = test_probes.iter().filter(|p| !tests.iter().any(|v| v.has_relit(&p.name))).map(|p| p.name.as_str()).collect();
    if test_probes.is_empty() {
        out.push("relighting PSNR: the scene names no test probes".to_string());
    } else if unreferenced.len() == test_probes.len() {
        out.push(format!("relighting PSNR: no test view has a relit image rgba_<probe>.png for the test probes ({})", unreferenced.join(", ")));
    } else if !unreferenced.is_empty() {
        out.push(format!("relighting under {}: no test view has its rgba_<probe>.png", unreferenced.join(", ")));
    }
    out
}

fn mean(v: &[f64]) -> Option<f64> {
    let v: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
    (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
}

/// A G-buffer quantity as an image: `f` per covered pixel, zero elsewhere.
fn gbuffer_image(g: &GBuffer, channels: usize, f: impl Fn(&crate::render::gbuffer::Surfel) -> Vec<f32> + Sync) -> Image {
    let mut img = Image::new(g.width, g.height, channels);
    img.data.par_chunks_mut(channels).zip(g.surfels.par_iter()).for_each(|(px, s)| {
        if let Some(s) = s {
            px.copy_from_slice(&f(s));
        }
    });
    img
}

fn encode(img: &Image) -> Image {
    img.map_channels(img.colour_channels(), |v| crate::color::linear_to_srgb(v.clamp(0.0, 1.0)))
}

/// The learned materials seen from one validation view: kd (linear RGB), roughness, metallic.
pub struct MaterialMaps {
    pub view: String,
    pub kd: Image,
    pub roughness: Image,
    pub metallic: Image,
}

/// The material metrics on the validation views (kd, roughness, metallic, normals); returns the
/// learned maps of each view.
fn material_metrics(val: &[View], mesh: &Mesh, bvh: &Bvh, textures: &MaterialTextures, out: &mut Evaluation) -> Result<Vec<MaterialMaps>> {
    let mut maps = Vec::new();
    let (mut raw, mut scaled, mut rough, mut metal, mut normal) = (vec![], vec![], vec![], vec![], vec![]);
    let mut scale = None;
    for view in val {
        // The normals scored are the ones the renders shade with: the normal map's, if any.
        let mut g = GBuffer::trace(mesh, bvh, &view.camera);
        g.apply_material_normals(textures);
        let kd = gbuffer_image(&g, 3, |s| textures.eval(s.uv).kd.to_array().to_vec());
        let r = gbuffer_image(&g, 1, |s| vec![textures.eval(s.uv).roughness]);
        let m = gbuffer_image(&g, 1, |s| vec![textures.eval(s.uv).metallic]);
        if view.has_albedo() {
            let gt = view.load_albedo()?;
            let covered: Vec<bool> = g.surfels.iter().map(|s| s.is_some()).collect();
            let mask: Vec<bool> = mask_from_alpha(&gt, 0.9).iter().zip(&covered).map(|(a, b)| *a && *b).collect();
            let gt_rgb = crate::image::io::to_rgb(&gt);
            let s = *scale.get_or_insert_with(|| albedo_scale(&kd, &gt_rgb, Some(&mask)));
            raw.push(psnr(&encode(&kd), &encode(&gt_rgb), Some(&mask)));
            scaled.push(psnr(&encode(&scale_colour(&kd, s)), &encode(&gt_rgb), Some(&mask)));
            if view.has_normal() {
                let gt_n = view.load_normal()?;
                let n = gbuffer_image(&g, 3, |s| s.normal.to_array().to_vec());
                normal.push(mean_angular_error_deg(&n, &gt_n, Some(&mask)));
            }
            if let Some(gt_r) = view.load_roughness_if_present()? {
                rough.push(mse(&r, &gt_r, Some(&mask)));
            }
            if let Some(gt_m) = view.load_metallic_if_present()? {
                metal.push(mse(&m, &gt_m, Some(&mask)));
            }
        }
        maps.push(MaterialMaps { view: view.name.clone(), kd, roughness: r, metallic: m });
    }
    out.albedo_psnr_raw = mean(&raw);
    out.albedo_psnr_scaled = mean(&scaled);
    out.albedo_scale = scale;
    out.roughness_mse = mean(&rough);
    out.metallic_mse = mean(&metal);
    out.normal_error_deg = mean(&normal);
    Ok(maps)
}

/// Renders of the validation views under the learned light (returned for export) and the scores.
pub struct Evaluated {
    pub metrics: Evaluation,
    /// (view name, linear RGBA render) of each validation view.
    pub val_renders: Vec<(String, Image)>,
    /// The learned materials seen from each validation view.
    pub val_materials: Vec<MaterialMaps>,
}

/// Evaluate `textures` + `light` on `mesh` (the atlas mesh the textures belong to).
pub fn evaluate(
    dataset: &Dataset,
    mesh: &Mesh,
    bvh: &Bvh,
    textures: &MaterialTextures,
    light: &CubeMap,
    test_probes: &[Probe],
    settings: &EvalSettings,
) -> Result<Evaluated> {
    let mut out = Evaluation { not_computed: missing_metrics(dataset, test_probes, settings.max_test_views), ..Default::default() };
    let val_materials = material_metrics(&dataset.val, mesh, bvh, textures, &mut out).context("material metrics on the validation views")?;

    let learned = PreparedLight::new(light.clone());
    let train_settings =
        RenderSettings { mode: settings.train_mode, spp: settings.spp, supersample: settings.supersample, seed: settings.seed, effects: settings.effects };
    let materials = textures;
    let mut train = Vec::new();
    for view in dataset.train.iter().step_by(settings.train_view_stride.max(1)) {
        let img = render_view_with(mesh, bvh, &learned, &view.camera, &train_settings, materials);
        train.push(protocol_psnr(&img, &view.load_rgba()?));
    }
    out.train_psnr = mean(&train);
    let mut val_renders = Vec::new();
    let mut val = Vec::new();
    for view in &dataset.val {
        let img = render_view_with(mesh, bvh, &learned, &view.camera, &train_settings, materials);
        val.push(protocol_psnr(&img, &view.load_rgba()?));
        val_renders.push((view.name.clone(), img));
    }
    out.val_psnr = mean(&val);

    // Relighting: raw always; scaled with the albedo scale when the dataset has albedo.
    let scaled_textures = out.albedo_scale.map(|scale| MaterialTextures {
        kd: scale_colour(&textures.kd, scale).map_channels(3, |v| v.clamp(0.0, 1.0)),
        ks: textures.ks.clone(),
        normal: textures.normal.clone(),
    });
    let scaled_materials = scaled_textures.as_ref();
    let relight_settings =
        RenderSettings { mode: settings.relight_mode, spp: settings.spp, supersample: settings.supersample, seed: settings.seed, effects: settings.effects };
    let views: Vec<&View> = dataset.test.iter().take(settings.max_test_views.unwrap_or(usize::MAX)).collect();
    for probe in test_probes {
        let light = PreparedLight::from_probe(probe);
        for view in &views {
            if !view.has_relit(&probe.name) {
                continue;
            }
            let target = view.load_relit(&probe.name)?;
            let raw = render_view_with(mesh, bvh, &light, &view.camera, &relight_settings, materials);
            let psnr_scaled = match scaled_materials {
                Some(m) => protocol_psnr(&render_view_with(mesh, bvh, &light, &view.camera, &relight_settings, m), &target),
                None => f64::NAN,
            };
            out.relight.push(RelightRecord { view: view.name.clone(), probe: probe.name.clone(), psnr_raw: protocol_psnr(&raw, &target), psnr_scaled });
        }
    }
    out.relight_psnr_raw = mean(&out.relight.iter().map(|r| r.psnr_raw).collect::<Vec<_>>());
    out.relight_psnr_scaled = mean(&out.relight.iter().map(|r| r.psnr_scaled).collect::<Vec<_>>());
    Ok(Evaluated { metrics: out, val_renders, val_materials })
}

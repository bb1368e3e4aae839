//! Where the relighting of a learned mesh loses, against known geometry: re-evaluates a finished
//! run (learned geometry, its textures and light) three ways: as it is; with the ground truth's
//! shading normals baked into the run's atlas as a tangent-space normal map
//! (`material::normal_map`); and with the ground truth's materials baked in as well. The second
//! row bounds what a normal map baked from the truth can give. A column scores the raw
//! relighting inside both outlines only, which leaves the outline out.
//!
//! A second table renders the ground truth's materials and normals three ways: on the
//! ground-truth mesh; baked onto the learned mesh; and on the learned mesh as each pixel sees
//! them (the ground truth's own G-buffer supplies the visible surface's material and shading
//! normal, the learned mesh the positions, the outline, and what shadow and bounce rays meet).
//! The third isolates what the learned positions cost; the bake is not a clean stand-in for it,
//! because a closest-point bake gives a point above a thin part the mesh lacks (a sauce blob) the
//! surface under that part. Each with the run's effects and with direct light without shadows,
//! in PSNR and in MSE: errors from different causes add in MSE, not in PSNR.
//!
//! cargo run --release --example normal_ceiling -- RUN_FOLDER [--spp 8] [--test-views N] [--error-map FILE.png]
//!
//! `--error-map` writes where the second table's renders (the run's effects) miss: the root mean
//! squared error over the probes on the first test view, the ground-truth mesh left and the
//! learned positions with the truth as each pixel sees it right, on one scale (white = the 99th
//! percentile of both), and prints how much of each one's squared error its worst pixels hold.
//!
//! The scene must have a ground-truth mesh. Each texel of the atlas takes the interpolated normal
//! and the material of the ground truth's closest point to the surface point it shows, the
//! normal expressed in that point's MikkTSpace frame (clamped to the frame's upper hemisphere,
//! where the map lives). The evaluation is the run's own (`eval::protocol::evaluate`).

use std::path::PathBuf;

use anyhow::{bail, Context, Result};
use clap::Parser;
use glam::{Mat3, Vec3};
use rayon::prelude::*;
use reconstruct::eval::protocol::{evaluate, EvalSettings};
use reconstruct::geometry::atlas::texel_hits;
use reconstruct::geometry::bvh::Bvh;
use reconstruct::geometry::closest_point::SurfaceQuery;
use reconstruct::geometry::obj::load_obj;
use reconstruct::geometry::tangents::{corner_tangents, interpolate};
use reconstruct::geometry::Mesh;
use reconstruct::image::io::{read_exr, write_png};
use reconstruct::image::Image;
use reconstruct::light::CubeMap;
use reconstruct::material::normal_map::NormalMap;
use reconstruct::material::texture_maps::MaterialTextures;
use reconstruct::material::{MaterialField, SurfaceParams};
use reconstruct::render::effects::Effects;
use reconstruct::eval::metrics::{mask_from_alpha, mse, over_white, psnr};
use reconstruct::render::gbuffer::GBuffer;
use reconstruct::render::montecarlo::TraceScene;
use reconstruct::render::view::{ray_epsilon, render_view_with, shade_with_params, straight_rgba, PreparedLight, RenderSettings, ShadingMode};
use reconstruct::scene::camera::Camera;
use reconstruct::scene::probe::Probe;
use reconstruct::scene::dataset::Dataset;
use reconstruct::scene::spec::SceneSpec;
use reconstruct::scene_data::ground_truth::ground_truth_mesh;

#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

#[derive(Parser)]
struct Args {
    /// A run folder written by `reconstruct` with learned geometry (has model/, light/, report.json).
    run: PathBuf,
    #[arg(long, default_value_t = 8)]
    spp: u32,
    /// At most this many test views are relit (default: all).
    #[arg(long)]
    test_views: Option<usize>,
    /// Write the second table's error maps (first test view) side by side to this PNG.
    #[arg(long)]
    error_map: Option<PathBuf>,
}

#[derive(serde::Deserialize)]
struct RunReport {
    scene: String,
    data_dir: PathBuf,
    effects: EffectsField,
}

#[derive(serde::Deserialize)]
struct EffectsField {
    effects: Effects,
}

/// Texels a bilinear lookup inside a chart can touch lie within √2 texels of it.
const REACH: f32 = 1.5;

/// The ground truth's normals and materials on `mesh`'s atlas: a `res`² normal map in `mesh`'s
/// MikkTSpace frame, and `learned` with every texel a lookup can reach replaced by the ground
/// truth's material (the others, outside every chart, keep the learned values).
fn baked_truth(mesh: &Mesh, truth: &Mesh, learned: &MaterialTextures) -> Result<(NormalMap, MaterialTextures)> {
    let res = learned.resolution();
    let query = SurfaceQuery::new(truth)?;
    let hits = texel_hits(mesh, res, REACH);
    let mut map = NormalMap::flat(res, corner_tangents(mesh)?.into());
    let mut materials = learned.clone();
    let texels: Vec<Option<([f32; 3], SurfaceParams)>> = hits
        .par_iter()
        .map(|hit| {
            let h = hit.as_ref()?;
            let tri = mesh.triangles[h.triangle as usize].map(|i| i as usize);
            let p = mesh.positions[tri[0]] * h.bary.x + mesh.positions[tri[1]] * h.bary.y + mesh.positions[tri[2]] * h.bary.z;
            let n = (mesh.normals[tri[0]] * h.bary.x + mesh.normals[tri[1]] * h.bary.y + mesh.normals[tri[2]] * h.bary.z).normalize_or(Vec3::Z);
            let c = query.closest(p)?;
            let w = barycentrics(truth, c.triangle as usize, c.point);
            let idx = truth.triangles[c.triangle as usize].map(|i| i as usize);
            let face = truth.face_normal_scaled(c.triangle as usize).normalize_or(Vec3::Z);
            let mut target = (truth.normals[idx[0]] * w.x + truth.normals[idx[1]] * w.y + truth.normals[idx[2]] * w.z).normalize_or(face);
            // The closest sheet may face the other way (a thin part's far side): take it as seen.
            if target.dot(n) < 0.0 {
                target = -target;
            }
            let uv = truth.uvs[idx[0]] * w.x + truth.uvs[idx[1]] * w.y + truth.uvs[idx[2]] * w.z;
            let material = truth.triangle_material(c.triangle as usize).eval(uv);
            // perturb: n' ∝ m.x·T + m.y·B + m.z·N; solve for m, then keep it in the upper hemisphere.
            let (t, s) = interpolate(&map.tangents[h.triangle as usize], h.bary);
            let frame = Mat3::from_cols(t, s * n.cross(t), n);
            let mut m = if frame.determinant().abs() > 1e-6 { (frame.inverse() * target).normalize_or(Vec3::Z) } else { Vec3::Z };
            m.z = m.z.max(0.0);
            Some((m.normalize_or(Vec3::Z).to_array(), material))
        })
        .collect();
    for (i, texel) in texels.into_iter().enumerate() {
        if let Some((m, p)) = texel {
            map.map.data[3 * i..3 * i + 3].copy_from_slice(&m);
            materials.kd.data[3 * i..3 * i + 3].copy_from_slice(&p.kd.to_array());
            materials.ks.data[3 * i..3 * i + 3].copy_from_slice(&[0.0, p.roughness, p.metallic]);
        }
    }
    Ok((map, materials))
}

/// A way to render a view: a light, a camera and settings in, a linear RGBA image out.
type Render<'a> = dyn Fn(&PreparedLight, &Camera, &RenderSettings) -> Image + 'a;

/// `mesh` rendered with `materials` (the visible surface and what shadow and bounce rays reach).
fn on_mesh<'a>(mesh: &'a Mesh, bvh: &'a Bvh, materials: &'a dyn MaterialField) -> impl Fn(&PreparedLight, &Camera, &RenderSettings) -> Image + 'a {
    move |light, camera, settings| render_view_with(mesh, bvh, light, camera, settings, materials)
}

/// `mesh` rendered with the shading normals (and, with `truth_materials`, the materials) the
/// ground truth shows through each pixel (its own G-buffer, where both cover the pixel;
/// elsewhere, and for what shadow and bounce rays reach, `baked`): the learned positions with
/// the ground truth's surface as the camera sees it, free of the bake's closest-point mistakes
/// (a point above a thin part, such as a sauce blob the mesh lacks, takes the surface under it).
fn seen_truth<'a>(mesh: &'a Mesh, bvh: &'a Bvh, baked: &'a dyn MaterialField, truth: &'a Mesh, truth_bvh: &'a Bvh, truth_materials: bool) -> impl Fn(&PreparedLight, &Camera, &RenderSettings) -> Image + 'a {
    move |light, camera, settings| {
        let s = settings.supersample.max(1);
        let fine = camera.resized(camera.width * s, camera.height * s);
        let mut gbuf = GBuffer::trace(mesh, bvh, &fine);
        gbuf.apply_material_normals(baked);
        let seen = GBuffer::trace(truth, truth_bvh, &fine);
        let mut params = gbuf.material_params(baked);
        for ((surfel, param), t) in gbuf.surfels.iter_mut().zip(params.iter_mut()).zip(&seen.surfels) {
            if let (Some(surfel), Some(t)) = (surfel.as_mut(), t) {
                surfel.normal = t.normal;
                if truth_materials {
                    *param = Some(t.material(truth));
                }
            }
        }
        let scene = TraceScene { mesh, bvh, materials: baked };
        let radiance = shade_with_params(&gbuf, &params, &scene, light, settings, 0, ray_epsilon(mesh));
        straight_rgba(&gbuf, &radiance, s)
    }
}

/// Mean raw relighting PSNR (dB) and mean squared error (the mean of each image's masked MSE) of
/// `render` with `effects`, over the target's pixels (alpha > 0.8, the protocol's mask) or, with
/// `inside_both`, over the pixels the render covers too: the protocol's PSNR without the
/// outline's share. Errors from different causes add in MSE, not in PSNR: a fixed local error
/// costs many dB on top of a small error elsewhere and few on top of a large one.
fn relight_scores(dataset: &Dataset, render: &Render, effects: Effects, probes: &[Probe], settings: &EvalSettings, inside_both: bool) -> Result<(f64, f64)> {
    let render_settings = RenderSettings { mode: settings.relight_mode, spp: settings.spp, supersample: settings.supersample, seed: settings.seed, effects };
    let mut scores = Vec::new();
    for probe in probes {
        let light = PreparedLight::from_probe(probe);
        for view in dataset.test.iter().take(settings.max_test_views.unwrap_or(usize::MAX)) {
            if !view.has_relit(&probe.name) {
                continue;
            }
            let target = view.load_relit(&probe.name)?;
            let img = render(&light, &view.camera, &render_settings);
            let mut mask = mask_from_alpha(&target, 0.8);
            if inside_both {
                mask.iter_mut().zip(mask_from_alpha(&img, 0.8)).for_each(|(a, b)| *a &= b);
            }
            let (a, b) = (over_white(&img, &img), over_white(&target, &target));
            scores.push((psnr(&a, &b, Some(&mask)), mse(&a, &b, Some(&mask))));
        }
    }
    let n = scores.len().max(1) as f64;
    Ok((scores.iter().map(|s| s.0).sum::<f64>() / n, scores.iter().map(|s| s.1).sum::<f64>() / n))
}

/// Mean over the probes of the per-pixel squared error (mean over RGB, over white: the terms of
/// the relighting PSNR's MSE) of `render` on the first test view, as a one-channel image.
fn error_map(dataset: &Dataset, render: &Render, probes: &[Probe], settings: &EvalSettings) -> Result<Image> {
    let view = dataset.test.first().context("the scene has no test views")?;
    let render_settings = RenderSettings { mode: settings.relight_mode, spp: settings.spp, supersample: settings.supersample, seed: settings.seed, effects: settings.effects };
    let mut sum = Image::new(view.camera.width, view.camera.height, 1);
    let relit: Vec<&Probe> = probes.iter().filter(|p| view.has_relit(&p.name)).collect();
    for probe in &relit {
        let target = view.load_relit(&probe.name)?;
        let img = render(&PreparedLight::from_probe(probe), &view.camera, &render_settings);
        let (a, b) = (over_white(&img, &img), over_white(&target, &target));
        for (i, e) in sum.data.iter_mut().enumerate() {
            *e += (0..3).map(|c| (a.data[3 * i + c] - b.data[3 * i + c]).powi(2)).sum::<f32>() / 3.0 / relit.len() as f32;
        }
    }
    Ok(sum)
}

/// Barycentrics (w0, w1, w2) of `point` (on the plane of triangle `t`).
fn barycentrics(truth: &Mesh, t: usize, point: Vec3) -> Vec3 {
    let [a, b, c] = truth.triangle_positions(t);
    let (v0, v1, v2) = (b - a, c - a, point - a);
    let (d00, d01, d11, d20, d21) = (v0.dot(v0), v0.dot(v1), v1.dot(v1), v2.dot(v0), v2.dot(v1));
    let denom = d00 * d11 - d01 * d01;
    if denom.abs() < f32::EPSILON {
        return Vec3::new(1.0, 0.0, 0.0);
    }
    let (w1, w2) = ((d11 * d20 - d01 * d21) / denom, (d00 * d21 - d01 * d20) / denom);
    Vec3::new(1.0 - w1 - w2, w1, w2)
}

fn main() -> Result<()> {
    reconstruct::allocator::keep_freed_pages();
    let args = Args::parse();
    let report_path = args.run.join("report.json");
    let report: RunReport = serde_json::from_str(&std::fs::read_to_string(&report_path).with_context(|| format!("{} is not a finished run folder", args.run.display()))?)
        .with_context(|| format!("{}: not a reconstruct report", report_path.display()))?;
    let spec = SceneSpec::find(&report.scene)?.with_data_dir(&report.data_dir);
    let truth = ground_truth_mesh(&spec).with_context(|| format!("scene {}: no ground-truth mesh to take normals from", report.scene))?;
    let model = args.run.join("model");
    let mesh = load_obj(model.join("model.obj")).with_context(|| format!("loading the learned mesh of {}", args.run.display()))?;
    let textures = MaterialTextures::load_for(&model, &mesh)?;
    if textures.normal.is_some() {
        bail!("{}: the run learned a normal map; compare against a run without one", args.run.display());
    }
    let light_path = args.run.join("light/light_latlong.exr");
    let light_image = read_exr(&light_path).with_context(|| format!("the learned light {}", light_path.display()))?;
    // Only the re-rendered training and validation views (not printed) see the learned light;
    // relighting uses the test probes.
    let light = CubeMap::from_latlong(&light_image, (light_image.height / 4).max(8));
    let dataset = Dataset::load(&report.data_dir).with_context(|| format!("loading the run's scene data {}", report.data_dir.display()))?;
    let probes = spec.load_test_probes()?;
    let bvh = Bvh::build(&mesh);
    let settings = EvalSettings {
        relight_mode: ShadingMode::MonteCarlo,
        spp: args.spp,
        supersample: 2,
        seed: 0,
        effects: report.effects.effects,
        train_mode: ShadingMode::MonteCarlo,
        train_view_stride: 10,
        max_test_views: args.test_views,
    };
    let truth_bvh = Bvh::build(&truth);
    let (map, truth_materials) = baked_truth(&mesh, &truth, &textures)?;
    let with_normals = MaterialTextures { normal: Some(map.clone()), ..textures.clone() };
    let with_both = MaterialTextures { normal: Some(map), ..truth_materials };
    println!("| on the learned mesh | relighting PSNR raw / scaled (dB) | raw, inside both outlines (dB) | normal error (°) |\n|---|---:|---:|---:|");
    for (name, t) in [
        ("the run's materials and the mesh's normals", &textures),
        ("the run's materials, the ground truth's normals as a normal map", &with_normals),
        ("the ground truth's materials and normals, baked", &with_both),
    ] {
        let e = evaluate(&dataset, &mesh, &bvh, t, &light, &probes, &settings)?.metrics;
        let f = |v: Option<f64>| v.map_or("–".to_string(), |v| format!("{v:.2}"));
        let inside = relight_scores(&dataset, &on_mesh(&mesh, &bvh, t), settings.effects, &probes, &settings, true)?.0;
        println!("| {name} | {} / {} | {inside:.2} | {} |", f(e.relight_psnr_raw), f(e.relight_psnr_scaled), f(e.normal_error_deg));
    }
    let seen_normals = seen_truth(&mesh, &bvh, &with_normals, &truth, &truth_bvh, false);
    let (raw, inside) = (
        relight_scores(&dataset, &seen_normals, settings.effects, &probes, &settings, false)?.0,
        relight_scores(&dataset, &seen_normals, settings.effects, &probes, &settings, true)?.0,
    );
    println!("| the run's materials, the ground truth's normals as each pixel sees them | {raw:.2} / – | {inside:.2} | 0 |");
    // Visibility: the same ground-truth materials on either mesh, with the run's effects and with
    // direct light without shadows (which neither mesh's shape can then change but through its
    // normals and outline).
    let unshadowed = Effects { shadows: false, indirect_bounces: 0, ..settings.effects };
    println!("\n| ground-truth materials on | the run's effects: raw relighting PSNR (dB) / mean MSE | direct light, no shadows: PSNR / MSE |\n|---|---:|---:|");
    let mut mse_rows = Vec::new();
    let renders: [(&str, Box<Render>); 3] = [
        ("the ground-truth mesh", Box::new(on_mesh(&truth, &truth_bvh, &truth))),
        ("the learned mesh, ground-truth materials and normals baked", Box::new(on_mesh(&mesh, &bvh, &with_both))),
        ("the learned mesh, ground-truth materials and normals as each pixel sees them", Box::new(seen_truth(&mesh, &bvh, &with_both, &truth, &truth_bvh, true))),
    ];
    for (name, render) in &renders {
        let full = relight_scores(&dataset, render.as_ref(), settings.effects, &probes, &settings, false)?;
        let direct = relight_scores(&dataset, render.as_ref(), unshadowed, &probes, &settings, false)?;
        println!("| {name} | {:.2} / {:.5} | {:.2} / {:.5} |", full.0, full.1, direct.0, direct.1);
        mse_rows.push((full.1, direct.1));
    }
    for (k, (name, _)) in renders.iter().enumerate().skip(1) {
        println!(
            "\n{name}: excess MSE over the ground-truth mesh {:.5} with the run's effects, {:.5} with direct light without shadows",
            mse_rows[k].0 - mse_rows[0].0,
            mse_rows[k].1 - mse_rows[0].1
        );
    }
    if let Some(path) = &args.error_map {
        let maps = [error_map(&dataset, renders[0].1.as_ref(), &probes, &settings)?, error_map(&dataset, renders[2].1.as_ref(), &probes, &settings)?];
        // How concentrated each map's squared error is: the share the worst 1 % and 5 % of the
        // pixels hold (of those either render or the target covers, i.e. nonzero in either map).
        let covered: Vec<usize> = (0..maps[0].data.len()).filter(|&i| maps.iter().any(|m| m.data[i] > 0.0)).collect();
        for (name, m) in ["ground-truth mesh", "learned positions, the truth as each pixel sees it"].iter().zip(&maps) {
            let mut e: Vec<f32> = covered.iter().map(|&i| m.data[i]).collect();
            e.sort_by(|a, b| b.total_cmp(a));
            let total: f64 = e.iter().map(|&v| v as f64).sum();
            let share = |f: usize| e[..covered.len() * f / 100].iter().map(|&v| v as f64).sum::<f64>() / total.max(f64::MIN_POSITIVE);
            println!("{name}, first test view: mean squared error {:.5} over {} pixels; the worst 1 % hold {:.0} % of it, the worst 5 % {:.0} %", total / covered.len().max(1) as f64, covered.len(), 100.0 * share(1), 100.0 * share(5));
        }
        let maps = maps.map(|m| Image { data: m.data.iter().map(|v| v.sqrt()).collect(), ..m });
        // White at the 99th percentile of both maps' covered pixels, so a few outline pixels do
        // not set the scale.
        let mut errors: Vec<f32> = maps.iter().flat_map(|m| m.data.iter().copied()).filter(|&e| e > 0.0).collect();
        errors.sort_by(f32::total_cmp);
        let scale = errors.get(errors.len() * 99 / 100).copied().unwrap_or(1.0).max(f32::MIN_POSITIVE);
        let (w, h) = (maps[0].width, maps[0].height);
        let mut side = Image::new(2 * w, h, 1);
        for (k, m) in maps.iter().enumerate() {
            for y in 0..h {
                for x in 0..w {
                    side.pixel_mut(k * w + x, y)[0] = (m.pixel(x, y)[0] / scale).min(1.0);
                }
            }
        }
        write_png(path, &side).with_context(|| format!("writing {}", path.display()))?;
        println!("\nerror maps (ground-truth mesh | learned positions, white = {scale:.3}): {}", path.display());
    }
    Ok(())
}

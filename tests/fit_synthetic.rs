//! End-to-end checks of the optimisation loop on a small scene made here (known textures and
//! light, targets rendered by the project's own split-sum renderer with the same pixel-centre rays
//! the loop traces, so a perfect fit is reachable):
//! - from a flat start, the loop recovers the albedo texture on the texels the cameras see and
//!   the training images;
//! - a checkpoint taken mid-run and resumed gives exactly the uninterrupted run's parameters;
//! - a 500-iteration run under a light with a 1e4-radiance sun keeps every loss finite;
//! - on a concave scene whose targets have interreflection (Monte Carlo, 3 bounces), training
//!   with the effect simulated recovers the albedo better than direct light only, which must
//!   brighten the albedo where light bounces;
//! - vertex refinement: the pixels' shading normals as functions of the welded positions equal
//!   the G-buffer's and their gradient through Monte Carlo shading matches finite differences; a
//!   refined run resumes exactly from a checkpoint, keeps its seams closed and its triangles
//!   unflipped, and split-sum training refuses it;
//! - normal map: with everything else known, the fit's render, loss and update recover a known
//!   tangent-space tilt from Monte Carlo targets; a run with a map resumes exactly, and split-sum
//!   training refuses it.

use std::sync::Arc;

use anyhow::Result;
use glam::{Quat, Vec3};
use reconstruct::fit::batch_render::ShadingContext;
use reconstruct::fit::config::FitConfig;
use reconstruct::fit::fitter::Fit;
use reconstruct::fit::parameters::Parameters;
use reconstruct::fit::training_view::TrainingView;
use reconstruct::geometry::atlas::{self, Atlas};
use reconstruct::geometry::bvh::Bvh;
use reconstruct::geometry::primitives::MeshBuilder;
use reconstruct::image::Image;
use reconstruct::light::brdf_lut::BrdfLut;
use reconstruct::light::prefilter::PrefilterOptions;
use reconstruct::light::CubeMap;
use reconstruct::material::texture_maps::MaterialTextures;
use reconstruct::material::{BaseColor, PartMaterial, Scalar};
use reconstruct::optim::texture::bilinear_taps;
use reconstruct::render::effects::Effects;
use reconstruct::render::splitsum_op::LightMaps;
use reconstruct::render::view::{ray_epsilon, render_view_with, PreparedLight, RenderSettings, ShadingMode};
use reconstruct::scene::Camera;

const TEX: usize = 32;
/// The concave scene has several parts: more charts than a 32² atlas holds.
const CONCAVE_TEX: usize = 64;
const LIGHT: usize = 16;
const PIXELS: usize = 40;

/// A stripy, two-tone albedo in linear RGB.
fn pattern(size: usize) -> Image {
    let mut img = Image::new(size, size, 3);
    for y in 0..size {
        for x in 0..size {
            let (u, v) = ((x as f32 + 0.5) / size as f32, (y as f32 + 0.5) / size as f32);
            let t = 0.5 + 0.5 * (6.0 * u + 3.0 * (5.0 * v).sin()).sin();
            img.set_rgb(y * size + x, Vec3::new(0.7, 0.35, 0.1).lerp(Vec3::new(0.15, 0.3, 0.6), t));
        }
    }
    img
}

struct Scene {
    atlas: Atlas,
    bvh: Arc<Bvh>,
    truth: MaterialTextures,
    light: CubeMap,
    views: Vec<TrainingView>,
    /// The light transport of the targets (and of the training, in `context`).
    effects: Effects,
}

fn sky(sun: f32) -> CubeMap {
    let sun_dir = Vec3::new(0.5, 0.3, 0.8).normalize();
    CubeMap::from_fn(LIGHT, |d| {
        let base = if d.z > 0.0 { Vec3::new(0.6, 0.7, 0.9) } else { Vec3::new(0.25, 0.22, 0.2) };
        base + if d.dot(sun_dir) > 0.995 { Vec3::splat(sun) } else { Vec3::ZERO }
    })
}

/// A convex textured ellipsoid: split-sum targets (no visibility needed).
fn scene(sun: f32) -> Result<Scene> {
    let mut b = MeshBuilder::new();
    let part = b.part(PartMaterial { name: "body".into(), base_color: BaseColor::Texture(Arc::new(pattern(64))), roughness: Scalar::Constant(0.5), metallic: Scalar::Constant(0.0) });
    b.ellipsoid(part, Vec3::ZERO, Vec3::new(0.8, 0.6, 0.5), Quat::IDENTITY, 32, 16);
    let split_sum = RenderSettings { mode: ShadingMode::SplitSum, spp: 1, supersample: 1, seed: 0, effects: Effects { shadows: false, specular: true, indirect_bounces: 0 } };
    scene_of(b.build(), sky(sun), split_sum, TEX)
}

/// A textured ball sunk into a light disc between two walls: light bounces between them.
fn concave_scene() -> Result<Scene> {
    let mut b = MeshBuilder::new();
    let ball = b.part(PartMaterial { name: "ball".into(), base_color: BaseColor::Texture(Arc::new(pattern(64))), roughness: Scalar::Constant(0.7), metallic: Scalar::Constant(0.0) });
    b.ellipsoid(ball, Vec3::new(0.0, 0.0, 0.3), Vec3::splat(0.4), Quat::IDENTITY, 24, 12);
    let walls = b.part(PartMaterial { name: "walls".into(), base_color: BaseColor::Constant(Vec3::new(0.85, 0.8, 0.7)), roughness: Scalar::Constant(0.9), metallic: Scalar::Constant(0.0) });
    b.cylinder(walls, glam::Vec2::ZERO, 0.9, -0.1, 0.0, 32);
    for y in [-0.55, 0.55] {
        b.ellipsoid(walls, Vec3::new(0.0, y, 0.3), Vec3::new(0.8, 0.08, 0.4), Quat::IDENTITY, 24, 12);
    }
    let bounced = RenderSettings { mode: ShadingMode::MonteCarlo, spp: 256, supersample: 1, seed: 3, effects: Effects::with_bounces(3) };
    scene_of(b.build(), sky(0.0), bounced, CONCAVE_TEX)
}

/// Atlas, baked truth (`tex`² textures) and training views of `mesh` rendered with `settings`
/// under `light`.
fn scene_of(mesh: reconstruct::geometry::Mesh, light: CubeMap, settings: RenderSettings, tex: usize) -> Result<Scene> {
    let atlas = atlas::build(&mesh, tex)?;
    let truth = MaterialTextures::bake_from(&mesh, &atlas, tex)?;
    let bvh = Arc::new(Bvh::build(&atlas.mesh));
    let views = training_views(&atlas, &bvh, &light, &settings, &truth)?;
    Ok(Scene { atlas, bvh, truth, light, views, effects: settings.effects })
}

/// 12 training views around the origin (two elevations) of `atlas.mesh` with materials `truth`,
/// rendered with `settings` under `light`.
fn training_views(atlas: &Atlas, bvh: &Bvh, light: &CubeMap, settings: &RenderSettings, truth: &MaterialTextures) -> Result<Vec<TrainingView>> {
    let prepared = PreparedLight::new(light.clone());
    let mut views = Vec::new();
    for i in 0..12 {
        let az = i as f32 * std::f32::consts::TAU / 12.0;
        let el: f32 = if i % 2 == 0 { 0.5 } else { -0.2 };
        let eye = 3.0 * Vec3::new(el.cos() * az.cos(), el.cos() * az.sin(), el.sin());
        let camera = Camera::look_at(eye, Vec3::ZERO, Vec3::Z, 0.7, PIXELS, PIXELS);
        let target = render_view_with(&atlas.mesh, bvh, &prepared, &camera, settings, truth);
        views.push(TrainingView::from_image(&format!("train_{i:03}"), &camera, i, &target, &atlas.mesh, bvh)?);
    }
    Ok(views)
}

fn context(s: &Scene, config: &FitConfig) -> ShadingContext {
    ShadingContext {
        mode: config.mode,
        effects: s.effects,
        spp: config.spp,
        denoise: false,
        seed: config.seed,
        ray_epsilon: ray_epsilon(&s.atlas.mesh),
        mesh: Arc::new(s.atlas.mesh.clone()),
        bvh: s.bvh.clone(),
        light_maps: Arc::new(LightMaps::matrix_free(config.light_res, PrefilterOptions::default())),
        lut: Arc::new(BrdfLut::compute(32, 256)),
    }
}

fn config(iterations: usize) -> FitConfig {
    FitConfig { iterations, batch: 3, texture_res: TEX, light_res: LIGHT, lr_material: 0.03, warmup_steps: 10, checkpoint_every: 0, ..FitConfig::default() }
}

/// Texels of a `tex`² texture some training pixel's bilinear lookup touches with weight > 5 %.
fn covered_texels(views: &[TrainingView], tex: usize) -> Vec<bool> {
    let mut covered = vec![false; tex * tex];
    for v in views {
        for uv in v.uv.iter() {
            for (k, w) in bilinear_taps(*uv, tex, tex) {
                if w > 0.05 {
                    covered[k] = true;
                }
            }
        }
    }
    covered
}

fn texel_psnr(a: &Image, b: &Image, mask: &[bool]) -> f64 {
    let (mut sum, mut n) = (0.0f64, 0usize);
    for (i, &m) in mask.iter().enumerate() {
        if m {
            for c in 0..3 {
                let d = (a.data[3 * i + c] - b.data[3 * i + c]) as f64;
                sum += d * d;
                n += 1;
            }
        }
    }
    -10.0 * (sum / n as f64).log10()
}

fn mean_view_psnr(fit: &Fit) -> Result<f64> {
    use reconstruct::fit::batch_render::render_batch;
    use reconstruct::fit::objective::batch_psnr;
    let mut total = 0.0;
    for v in &fit.views {
        let r = render_batch(&[v], &fit.params, &fit.ctx, 0, None, None)?;
        total += batch_psnr(&r.rgb, &v.target.rgba)?;
    }
    Ok(total / fit.views.len() as f64)
}

#[test]
fn flat_start_recovers_the_albedo_texture_and_the_images() -> Result<()> {
    let s = scene(0.0)?;
    // The light is known here (learning rate 0): with it free, albedo is only defined up to a
    // per-channel scale, which the hotdog evaluation handles with the protocol's scaled PSNR.
    let cfg = FitConfig { lr_light: 0.0, ..config(400) };
    let flat = MaterialTextures::constant(TEX, Vec3::splat(cfg.init_kd), cfg.init_roughness, cfg.init_metallic);
    let params = Parameters::from_values(&flat, &s.light)?;
    let ctx = context(&s, &cfg);
    let mut fit = Fit::new(cfg, params, s.views.clone(), ctx)?;
    let covered = covered_texels(&fit.views, TEX);
    let before = texel_psnr(&fit.params.textures()?.kd, &s.truth.kd, &covered);
    let images_before = mean_view_psnr(&fit)?;
    fit.run(None, false)?;
    let after = texel_psnr(&fit.params.textures()?.kd, &s.truth.kd, &covered);
    let images_after = mean_view_psnr(&fit)?;
    eprintln!("albedo PSNR on covered texels: {before:.2} → {after:.2} dB; images {images_before:.2} → {images_after:.2} dB");
    // Measured: 13.7 → 30.5 dB albedo, 18.8 → 45.4 dB images. The albedo stays below the images
    // because texels at the edge of the covered set are seen by few pixels at grazing angles and
    // the smoothness regulariser pulls them toward their neighbours. Bounds sit 1.5 dB under the
    // measurement, far above the flat start.
    assert!(before < 15.0 && images_before < 22.0, "flat start already close? {before} / {images_before}");
    assert!(after > 29.0, "albedo PSNR on covered texels {after:.2} dB");
    assert!(images_after > 43.0, "re-rendered training images {images_after:.2} dB");
    Ok(())
}

/// Albedo PSNR on covered texels after fitting `s` from a flat start with the light known.
fn fitted_albedo_psnr(s: &Scene, cfg: FitConfig, effects: Effects) -> Result<f64> {
    let tex = s.truth.resolution();
    let flat = MaterialTextures::constant(tex, Vec3::splat(cfg.init_kd), cfg.init_roughness, cfg.init_metallic);
    let mut ctx = context(s, &cfg);
    ctx.effects = effects;
    let mut fit = Fit::new(cfg, Parameters::from_values(&flat, &s.light)?, s.views.clone(), ctx)?;
    fit.run(None, false)?;
    Ok(texel_psnr(&fit.params.textures()?.kd, &s.truth.kd, &covered_texels(&fit.views, tex)))
}

#[test]
fn simulating_interreflection_recovers_the_albedo_that_direct_light_overestimates() -> Result<()> {
    let s = concave_scene()?;
    let cfg = FitConfig { mode: ShadingMode::MonteCarlo, spp: 4, lr_light: 0.0, texture_res: CONCAVE_TEX, ..config(300) };
    let with = fitted_albedo_psnr(&s, cfg.clone(), s.effects)?;
    let without = fitted_albedo_psnr(&s, cfg, Effects::DIRECT)?;
    eprintln!("albedo PSNR on covered texels: {with:.2} dB with 3 bounces, {without:.2} dB with direct light only");
    // Measured 23.2 dB with bounces, 13.4 dB direct only (that fit brightens the walls and the
    // ball's underside to explain the light they reflect onto each other). The bound keeps a
    // third of the gap.
    assert!(with > without + 3.0, "interreflection {with:.2} dB vs direct only {without:.2} dB");
    Ok(())
}

/// What a finished fit leaves: textures, light and (with refinement) the mesh's positions.
type FitOutcome = (MaterialTextures, Vec<Vec3>, Option<Vec<Vec3>>);

fn outcome(fit: &Fit) -> Result<FitOutcome> {
    Ok((fit.params.textures()?, fit.params.light_cube()?.data, fit.refined_mesh().map(|m| m.positions)))
}

/// `cfg` run straight through, and run to half its length into a checkpoint in `dir` then resumed
/// by a new fit to the end.
fn straight_and_resumed(s: &Scene, cfg: &FitConfig, dir: &std::path::Path) -> Result<(FitOutcome, FitOutcome)> {
    let straight = {
        let mut fit = Fit::new(cfg.clone(), Parameters::initial(cfg)?, s.views.clone(), context(s, cfg))?;
        fit.run(None, false)?;
        outcome(&fit)?
    };
    let _ = std::fs::remove_dir_all(dir);
    {
        let half = FitConfig { iterations: cfg.iterations / 2, ..cfg.clone() };
        let mut fit = Fit::new(half, Parameters::initial(cfg)?, s.views.clone(), context(s, cfg))?;
        fit.run(Some(dir), false)?;
    }
    let mut fit = Fit::new(cfg.clone(), Parameters::initial(cfg)?, s.views.clone(), context(s, cfg))?;
    assert!(fit.resume(dir)?, "checkpoint not found");
    assert_eq!(fit.iteration(), cfg.iterations / 2);
    fit.run(Some(dir), false)?;
    Ok((straight, outcome(&fit)?))
}

#[test]
fn resumed_run_matches_the_uninterrupted_one() -> Result<()> {
    let s = scene(0.0)?;
    let cfg = config(8);
    let dir = std::env::temp_dir().join(format!("reconstruct-resume-{}", std::process::id()));
    let (straight, resumed) = straight_and_resumed(&s, &cfg, &dir)?;
    assert!(straight == resumed, "the resumed run differs");
    // Other settings must not silently reuse the checkpoint.
    let other = FitConfig { lr_material: 0.5, ..cfg.clone() };
    let mut wrong = Fit::new(other.clone(), Parameters::initial(&other)?, s.views.clone(), context(&s, &other))?;
    let err = wrong.resume(&dir).expect_err("settings differ").to_string();
    assert!(err.contains(&format!("fit.lr_material: {} → 0.5", cfg.lr_material)) && err.contains(&dir.display().to_string()), "{err}");
    // A checkpoint past the run's length is refused, not reported under the shorter length.
    let short = FitConfig { iterations: 2, ..cfg.clone() };
    let mut early = Fit::new(short.clone(), Parameters::initial(&short)?, s.views.clone(), context(&s, &short))?;
    let err = early.resume(&dir).expect_err("checkpoint past the end").to_string();
    assert!(err.contains("at iteration 8, past this run's 2 iterations"), "{err}");
    std::fs::remove_dir_all(&dir)?;
    Ok(())
}

#[test]
fn losses_stay_finite_under_a_sun() -> Result<()> {
    let s = scene(1e4)?;
    let cfg = config(500);
    let mut fit = Fit::new(cfg.clone(), Parameters::initial(&cfg)?, s.views.clone(), context(&s, &cfg))?;
    fit.run(None, false)?;
    assert_eq!(fit.history.len(), 500);
    assert!(fit.history.iter().all(|r| r.terms.total.is_finite()), "a loss went non-finite");
    assert!(fit.params.all_finite()?);
    Ok(())
}

#[test]
fn exported_model_reloads_and_renders_the_same() -> Result<()> {
    use reconstruct::fit::export::write_model;
    use reconstruct::geometry::obj::load_obj;
    let s = scene(0.0)?;
    let dir = std::env::temp_dir().join(format!("reconstruct-export-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    write_model(&dir, &s.atlas.mesh, &s.truth)?;
    let mesh = load_obj(dir.join("model.obj"))?;
    let textures = MaterialTextures::load(&dir)?;
    assert!(dir.join("model.gltf").is_file() && dir.join("roughness.png").is_file());
    let light = PreparedLight::new(s.light.clone());
    let settings = RenderSettings { mode: ShadingMode::SplitSum, spp: 1, supersample: 1, seed: 0, effects: Effects { shadows: false, specular: true, indirect_bounces: 0 } };
    let camera = &s.views[0].camera;
    let a = render_view_with(&s.atlas.mesh, &s.bvh, &light, camera, &settings, &s.truth);
    let b = render_view_with(&mesh, &Bvh::build(&mesh), &light, camera, &settings, &textures);
    let psnr = reconstruct::eval::metrics::psnr(&a, &b, None);
    // 8-bit textures and OBJ decimals are the only differences.
    assert!(psnr > 40.0, "reloaded model renders at {psnr:.1} dB");
    std::fs::remove_dir_all(&dir)?;
    Ok(())
}

/// Refinement on the ellipsoid: a Monte Carlo fit whose vertices move too.
fn refine_config(iterations: usize) -> FitConfig {
    FitConfig { mode: ShadingMode::MonteCarlo, spp: 2, refine_geometry: true, ..config(iterations) }
}

#[test]
fn refinement_normals_are_the_gbuffers_and_their_gradient_matches_finite_differences() -> Result<()> {
    use candle_core::{Device, Tensor};
    use reconstruct::fit::vertex_refinement::VertexRefinement;
    use reconstruct::optim::gradcheck::{check_gradient_with, GradCheckOptions};
    use reconstruct::render::montecarlo::{McSettings, TraceScene};
    use reconstruct::render::montecarlo_op::{shade_mc_with_normal, McPixel, McShading};
    let s = scene(0.0)?;
    let r = VertexRefinement::new(&s.atlas.mesh)?;
    // The welded mesh is the atlas mesh with its seams closed: fewer vertices, same surface.
    assert!(r.positions().len() < s.atlas.mesh.positions.len());
    let mesh = r.mesh();
    let bvh = Bvh::build(&mesh);
    // A small view (FD perturbs every vertex) on the moved-to mesh (here: the start).
    let camera = Camera::look_at(Vec3::new(2.0, 1.5, 1.2), Vec3::ZERO, Vec3::Z, 0.7, 12, 12);
    let view = TrainingView::from_image("small", &camera, 0, &Image::new(12, 12, 4), &mesh, &bvh)?.retraced(&mesh, &bvh);
    let dev = &Device::Cpu;
    let x: Vec<f64> = r.positions().iter().flatten().copied().collect();
    let x = Tensor::from_vec(x, (r.positions().len(), 3), dev)?;
    let normals = r.pixel_normals(&[&view], &x)?.to_vec2::<f64>()?;
    assert!(view.len() > 40, "{} pixels", view.len());
    for (n, s) in normals.iter().zip(&view.surfels) {
        // The surfel's normal faces the camera; the operator's is the mesh's own orientation.
        let cos = Vec3::new(n[0] as f32, n[1] as f32, n[2] as f32).dot(s.normal).abs();
        assert!(cos > 1.0 - 1e-5, "pixel normal {n:?} vs G-buffer {}", s.normal);
    }
    // Shading as a function of the positions, samples fixed at the start.
    let pixels: Vec<Option<McPixel>> = view.surfels.iter().zip(&view.pixels).map(|(s, &p)| Some(McPixel::from_surfel(s, view.origin, p as u64))).collect();
    let n = pixels.len();
    let kd: Vec<[f32; 3]> = (0..n).map(|i| [0.3 + 0.05 * (i % 7) as f32, 0.5, 0.4]).collect();
    let ks: Vec<[f32; 3]> = (0..n).map(|i| [0.0, 0.2 + 0.1 * (i % 5) as f32, 0.5 * (i % 2) as f32]).collect();
    let settings = McSettings { spp: 2, seed: 1, effects: Effects { shadows: true, specular: true, indirect_bounces: 0 }, ray_epsilon: ray_epsilon(&mesh) };
    let op = McShading::prepare(&pixels, &kd, &ks, &s.light, &TraceScene { mesh: &mesh, bvh: &bvh, materials: &mesh }, &settings);
    let rows = |v: &[[f32; 3]]| Tensor::from_vec(v.iter().flatten().map(|&c| c as f64).collect::<Vec<_>>(), (v.len(), 3), dev);
    let (kd, ks) = (rows(&kd)?, rows(&ks)?);
    let light: Vec<f64> = s.light.data.iter().flat_map(|c| c.to_array()).map(|c| c as f64).collect();
    let light = Tensor::from_vec(light, (6, s.light.res, s.light.res, 3), dev)?;
    let weights = Tensor::rand(0.5f64, 1.5, (n, 6), dev)?;
    let report = check_gradient_with(
        |p| (shade_mc_with_normal(&op, &kd, &ks, &light, &r.pixel_normals(&[&view], &p[0]).map_err(|e| candle_core::Error::Msg(format!("{e:#}")))?)? * &weights)?.sum_all(),
        &[x],
        &GradCheckOptions { eps: 1e-7, tol: 1e-3, max_elements: 2000, seed: 5 },
    )?;
    eprintln!("{report}");
    assert!(report.inputs[0].max_abs_fd > 0.0);
    Ok(())
}

#[test]
fn refined_run_resumes_exactly_and_keeps_a_healthy_mesh() -> Result<()> {
    use reconstruct::optim::guarded_step::{broken_triangles, degenerate_area2};
    let s = scene(0.0)?;
    let cfg = refine_config(6);
    let dir = std::env::temp_dir().join(format!("reconstruct-resume-refine-{}", std::process::id()));
    let (straight, resumed) = straight_and_resumed(&s, &cfg, &dir)?;
    assert!(straight == resumed, "the resumed refinement differs");
    std::fs::remove_dir_all(&dir)?;
    let moved = straight.2.expect("refined positions");
    let start = &s.atlas.mesh.positions;
    let largest = moved.iter().zip(start).map(|(a, b)| (*a - *b).length()).fold(0.0, f32::max);
    // Seams stay closed: vertices that started together end together.
    for i in 0..start.len() {
        for j in i + 1..(i + 40).min(start.len()) {
            if start[i] == start[j] {
                assert_eq!(moved[i], moved[j], "seam vertices {i} and {j} came apart");
            }
        }
    }
    let f64s = |p: &[Vec3]| p.iter().map(|v| v.as_dvec3().to_array()).collect::<Vec<_>>();
    let edge = reconstruct::fit::geometry_pass::mean_edge_length(&s.atlas.mesh);
    assert_eq!(broken_triangles(&s.atlas.mesh.triangles, &f64s(start), &f64s(&moved), degenerate_area2(edge)), Vec::<usize>::new());
    // Moved, gently: six steps of at most 3 % of an edge each.
    eprintln!("largest vertex move {largest:.2e} (mean edge {edge:.3})");
    assert!(largest > 0.0 && (largest as f64) < 0.18 * edge, "{largest}");
    // Split-sum has no normal input: refused up front.
    let split = FitConfig { mode: ShadingMode::SplitSum, ..cfg.clone() };
    let err = Fit::new(split.clone(), Parameters::initial(&split)?, s.views.clone(), context(&s, &split)).err().expect("refused").to_string();
    assert!(err.contains("--refine-geometry") && err.contains("Monte Carlo"), "{err}");
    Ok(())
}

/// The ellipsoid scene with a known normal map in the truth (a smooth tilt of up to about 17°
/// that varies over the atlas) under a smooth light that changes along every axis, its targets
/// rendered by Monte Carlo (direct light, no shadows: the ellipsoid is convex), 64 spp.
fn normal_mapped_scene() -> Result<Scene> {
    use reconstruct::geometry::tangents::corner_tangents;
    use reconstruct::material::normal_map::NormalMap;
    let mut b = MeshBuilder::new();
    let part = b.part(PartMaterial { name: "body".into(), base_color: BaseColor::Constant(Vec3::new(0.6, 0.55, 0.5)), roughness: Scalar::Constant(0.4), metallic: Scalar::Constant(0.0) });
    b.ellipsoid(part, Vec3::ZERO, Vec3::new(0.8, 0.6, 0.5), Quat::IDENTITY, 32, 16);
    let mesh = b.build();
    let atlas = atlas::build(&mesh, TEX)?;
    let mut truth = MaterialTextures::bake_from(&mesh, &atlas, TEX)?;
    let mut map = NormalMap::flat(TEX, corner_tangents(&atlas.mesh)?.into());
    for (i, m) in map.map.data.chunks_exact_mut(3).enumerate() {
        let (u, v) = ((i % TEX) as f32 / TEX as f32, (i / TEX) as f32 / TEX as f32);
        let tilt = Vec3::new(0.3 * (7.0 * u).sin(), 0.3 * (5.0 * v + 1.0).cos(), 1.0).normalize();
        m.copy_from_slice(&tilt.to_array());
    }
    truth.normal = Some(map);
    let bvh = Arc::new(Bvh::build(&atlas.mesh));
    // Brighter toward +x, +y and +z: a tilt in any direction changes the shading (under a light
    // that varies with height alone, a horizontal tilt would be invisible to first order).
    let light = CubeMap::from_fn(LIGHT, |d| Vec3::new(1.0 + 0.8 * d.x, 1.0 + 0.8 * d.y, 1.0 + 0.8 * d.z).max(Vec3::splat(0.1)));
    let effects = Effects { shadows: false, specular: true, indirect_bounces: 0 };
    let settings = RenderSettings { mode: ShadingMode::MonteCarlo, spp: 64, supersample: 1, seed: 5, effects };
    let views = training_views(&atlas, &bvh, &light, &settings, &truth)?;
    Ok(Scene { atlas, bvh, truth, light, views, effects })
}

/// Mean angle (degrees) between the shading normals two sets of textures give the training
/// views' covered pixels.
fn mean_normal_angle(views: &[TrainingView], a: &MaterialTextures, b: &MaterialTextures) -> f64 {
    use reconstruct::material::MaterialField;
    let (mut sum, mut n) = (0.0f64, 0usize);
    for v in views {
        for s in &v.surfels {
            let na = a.shading_normal(s.triangle, s.bary3(), s.uv, s.normal);
            let nb = b.shading_normal(s.triangle, s.bary3(), s.uv, s.normal);
            sum += (na.dot(nb).clamp(-1.0, 1.0) as f64).acos().to_degrees();
            n += 1;
        }
    }
    sum / n as f64
}

/// Fits only the normal map of `s` (materials and light held at the truth) for `iterations`
/// steps of the fit's own render, loss and update; the mean shading-normal error before and after.
fn fit_map_only(s: &Scene, cfg: &FitConfig, views: Vec<TrainingView>, iterations: usize) -> Result<(f64, f64)> {
    use reconstruct::fit::batch_render::render_batch;
    use reconstruct::fit::objective::{objective, smoothness_jitter_seed};
    use reconstruct::material::normal_map::{NORMAL_MAX, NORMAL_MIN};
    use reconstruct::optim::adam::{Adam, GroupConfig, LrSchedule};
    let start = MaterialTextures { normal: None, ..s.truth.clone() };
    let fit = Fit::new(cfg.clone(), Parameters::from_values(&start, &s.light)?, views, context(s, cfg))?;
    let map = fit.params.normal.as_ref().expect("the fit adds a flat map").map.clone();
    let mut adam = Adam::new(LrSchedule { warmup_steps: 0, decay_steps: 1_000_000, staircase: false });
    adam.add_group(GroupConfig::new("normal", cfg.lr_material).with_channel_clamp(&NORMAL_MIN, &NORMAL_MAX), vec![map])?;
    let before = mean_normal_angle(&fit.views, &fit.params.textures()?, &s.truth);
    for it in 0..iterations {
        let batch: Vec<&TrainingView> = fit.batch_for(it).into_iter().map(|i| &fit.views[i]).collect();
        let render = render_batch(&batch, &fit.params, &fit.ctx, it as u64, None, smoothness_jitter_seed(cfg, &fit.params, it))?;
        let (loss, _) = objective(&batch, &render, &fit.params, cfg, it)?;
        adam.step(&loss.backward()?)?;
        fit.params.normal.as_ref().expect("map").normalize()?;
    }
    Ok((before, mean_normal_angle(&fit.views, &fit.params.textures()?, &s.truth)))
}

#[test]
fn a_normal_map_is_recovered_from_the_images() -> Result<()> {
    let s = normal_mapped_scene()?;
    // 32 spp: the map is a free vector per texel, and the noise of a few samples leaves a floor.
    // Materials and light are the truth and only the map moves: under one light a free albedo
    // can absorb diffuse shading as well as a tilt can (why the fit's flatness term exists), so
    // this checks the map's gradient alone, through the fit's own render, loss and update.
    let cfg = FitConfig { mode: ShadingMode::MonteCarlo, spp: 32, normal_map: true, ..config(0) };
    let (before, after) = fit_map_only(&s, &cfg, s.views.clone(), 300)?;
    eprintln!("mean shading-normal error on the training pixels: {before:.2}° → {after:.2}°");
    assert!(before > 8.0, "the truth's tilt is too small to test ({before:.2}°)");
    // Measured 16.17° → 6.51° at 32 spp (9.2° at 8, 7.8° at 16 spp: the L1 fit of a noisy
    // estimate leaves a floor that falls with the samples).
    assert!(after < 0.5 * before, "the normal map did not learn the tilt: {before:.2}° → {after:.2}°");
    Ok(())
}

#[test]
fn a_normal_map_run_resumes_exactly_and_split_sum_refuses_it() -> Result<()> {
    let s = normal_mapped_scene()?;
    let cfg = FitConfig { mode: ShadingMode::MonteCarlo, spp: 2, normal_map: true, ..config(6) };
    let dir = std::env::temp_dir().join(format!("reconstruct-resume-normal-{}", std::process::id()));
    let (straight, resumed) = straight_and_resumed(&s, &cfg, &dir)?;
    assert!(straight.0.normal.is_some(), "no normal map was learned");
    assert!(straight == resumed, "the resumed run differs");
    std::fs::remove_dir_all(&dir)?;
    let split = FitConfig { mode: ShadingMode::SplitSum, ..cfg };
    let err = Fit::new(split.clone(), Parameters::initial(&split)?, s.views.clone(), context(&s, &split)).err().expect("refused").to_string();
    assert!(err.contains("--normal-map") && err.contains("Monte Carlo"), "{err}");
    Ok(())
}

#[test]
fn a_normal_prior_pulls_a_noisy_normal_map_to_its_labels() -> Result<()> {
    use candle_core::{DType, Device, Tensor};
    use reconstruct::fit::config::PriorWeights;
    use reconstruct::fit::labels::PixelLabels;
    use reconstruct::material::MaterialField;
    let s = normal_mapped_scene()?;
    let dev = &Device::Cpu;
    // 2 spp: alone, the map settles where the noise puts it; labels of the true shading normals
    // (in world space, as `PixelLabels::gather` turns them) must pull it to the truth.
    let fit_map = |weight: f64| -> Result<(f64, f64)> {
        let prior = PriorWeights { albedo: 0.0, roughness: 0.0, metallic: 0.0, normal: weight, ..PriorWeights::default() };
        let cfg = FitConfig { mode: ShadingMode::MonteCarlo, spp: 2, normal_map: true, prior, ..config(0) };
        let mut views = s.views.clone();
        for v in &mut views {
            let n = v.len();
            let normals: Vec<f32> = v.surfels.iter().flat_map(|p| s.truth.shading_normal(p.triangle, p.bary3(), p.uv, p.normal).to_array()).collect();
            let zeros = |c: usize| Tensor::zeros((n, 1, c), DType::F32, dev);
            v.labels = Some(PixelLabels {
                albedo_srgb: zeros(3)?,
                roughness: zeros(1)?,
                metallic: zeros(1)?,
                mask: zeros(1)?,
                normal_world: Tensor::from_vec(normals, (n, 1, 3), dev)?,
                normal_mask: Tensor::ones((n, 1, 1), DType::F32, dev)?,
            });
        }
        fit_map_only(&s, &cfg, views, 150)
    };
    let (before, without) = fit_map(0.0)?;
    let (_, with) = fit_map(1.0)?;
    eprintln!("mean shading-normal error: {before:.2}° at the start, {without:.2}° without the prior, {with:.2}° with it");
    assert!(with < 0.5 * without && with < 0.5 * before, "the normal prior did not pull the map: {before:.2}° → {without:.2}° without, {with:.2}° with");
    // Without normals that move there is nothing for the term to act on: refused, not ignored.
    let fixed = FitConfig { mode: ShadingMode::MonteCarlo, prior: PriorWeights { normal: 1.0, ..PriorWeights::default() }, ..config(0) };
    let err = Fit::new(fixed.clone(), Parameters::initial(&fixed)?, s.views.clone(), context(&s, &fixed)).err().expect("refused").to_string();
    assert!(err.contains("--prior-normal") && err.contains("--normal-map"), "{err}");
    Ok(())
}

//! The geometry pass (NVDiffRecMC's first pass, done the CPU's way): vertex positions optimised
//! together with a per-vertex base colour and a spherical-harmonic light, from the training images
//! and their masks, starting from a closed mesh such as the visual hull.
//!
//! Each step, for a batch of views:
//! 1. every view gets a fresh G-buffer of the current mesh (coverage and surfels change with the
//!    mesh), by projecting the triangles (`render::gbuffer_raster`: the ray tracer's hits without a
//!    BVH to rebuild every step); the views of a step run side by side, each with its own backward;
//! 2. covered pixels are shaded differentiably in the vertices: `surface_op` (the hit point's
//!    barycentrics and the shading normal as functions of the positions), `vertex_normals_op`,
//!    and Lambertian shading under the SH light (`sh_light`);
//! 3. the view is composited over a random background colour (NVDiffRecMC: a flat background would
//!    let the colour hide a wrong outline) with coverage as a fourth channel, and the silhouettes
//!    are antialiased analytically (`silhouette_op`), which gives the outline its gradient;
//! 4. loss: L1 of the tone-mapped colour (`optim::loss::log_srgb`) against the target composited
//!    over the same background, plus the MSE of the coverage against the target alpha, as one
//!    operator over the image (`view_loss_op`);
//! 5. the position gradient goes through the Large Steps parameterisation (`optim::large_steps`):
//!    a uniform-Adam step on u = (I + λL)x, then x = (I + λL)⁻¹u. kd and light take Adam steps.
//!
//! Stages: the pass runs in stages of fixed connectivity, the mesh remeshed to a finer edge
//! between them; each stage renders its views at the resolution where its edge spans the last
//! stage's (`GeometryPassConfig::coarse_views`), so a coarse step costs a fraction of a
//! full-resolution one.
//!
//! A healthy mesh: within a stage the connectivity is fixed (each remesh gives well-shaped
//! triangles), and a step that would flip or collapse a triangle is held back at that triangle's
//! vertices or, when that would hold many, shortened (halved; `optim::guarded_step`). If even 1/256 of
//! the step breaks triangles, the pass stops with an error that names the iteration; it never
//! carries on with a broken mesh. Degenerate triangles never reach the G-buffer.

use std::sync::Arc;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use candle_core::backprop::GradStore;
use candle_core::{DType, Device, Tensor, Var, D};
use glam::{Vec2, Vec3};
use indicatif::{ProgressBar, ProgressStyle};
use rayon::prelude::*;
use serde::Serialize;

use crate::geometry::bvh::Bvh;
use crate::geometry::closest_point::SurfaceQuery;
use crate::geometry::enclosed_surface::enclosed_surface;
use crate::geometry::inward_surface::{inward_share, FOLDED_SHARE, INSIDE_OUT_SHARE, INWARD_SAMPLES};
use crate::geometry::manifold::{check_closed_manifold, signed_volume};
use crate::geometry::remesh::isotropic_remesh;
use crate::geometry::Mesh;
use crate::image::Image;
use crate::optim::adam::{Adam, GroupConfig, LrSchedule};
use crate::optim::guarded_step::{degenerate_area2, guard_step};
use crate::optim::large_steps::{LargeSteps, UniformAdam};
use crate::optim::prior_loss::prior_loss;
use crate::optim::laplacian::UniformLaplacian;
use crate::optim::vertex_smoothness::VertexSmoothness;
use crate::render::gbuffer::GBuffer;
use crate::render::sh_light::{constant_light, shade_diffuse, SH_COEFFICIENTS};
use crate::render::silhouette_op::{antialias, EdgeTopology, Silhouettes};
use crate::render::surface_op::{surface_points, PixelRay, SurfacePoints};
use crate::render::vertex_normals_op::vertex_normals;
use crate::rng::Sampler;
use crate::scene::camera::median_pixel_footprint;
use crate::scene::Camera;

use super::pixel_scatter::PixelMap;
use super::view_loss_op::{view_loss, ViewLoss};

#[derive(Clone, Debug, PartialEq, Serialize, serde::Deserialize)]
pub struct GeometryPassConfig {
    pub iterations: usize,
    /// Views per step.
    pub batch: usize,
    /// λ of the Large Steps system (I + λL).
    pub lambda: f64,
    /// Position step (uniform Adam's learning rate on u) as a fraction of the mesh's mean edge
    /// length: the largest first step moves a vertex about this share of an edge, whatever the
    /// object's size.
    pub step_per_edge: f64,
    pub lr_material: f64,
    pub lr_light: f64,
    /// Weight of the coverage MSE beside the colour L1 (NVDiffRecMC adds them with weight 1).
    pub mask_weight: f64,
    /// Weight of the per-vertex colour's smoothness (`optim::vertex_smoothness`: mean over edges
    /// of |kd_a − kd_b|) beside the image loss; 0 switches it off.
    pub kd_smoothness: f64,
    /// The pass runs in this many stages of equal length; before each stage after the first the
    /// mesh is remeshed isotropically to a finer edge (`geometry::remesh`), so the first stage
    /// moves a coarse mesh far and the later ones resolve detail. 1 keeps the start's connectivity.
    pub stages: usize,
    /// The last stage's edge length, in pixel footprints of the training views at the object
    /// (the stages in between step geometrically from the start mesh's edge to this).
    pub final_edge_pixels: f64,
    /// Render each stage's views at the resolution where that stage's edge spans
    /// `final_edge_pixels` pixels (the last stage at full resolution, earlier ones coarser):
    /// a coarser triangle gets no more from finer pixels than the last stage's triangle gets
    /// from full-resolution ones, and a coarse step costs a fraction of a full-resolution one.
    /// Records written before it existed ran without it, hence `false` when absent.
    #[serde(default)]
    pub coarse_views: bool,
    /// Weight of the normal prior in the last stage: λ · mean over the labelled covered pixels of
    /// ‖n − label‖², the shading normal against the view's world-space normal label
    /// (`GeometryView::normal`), the material pass's normal term. It acts only on views that carry
    /// a label; 0 switches it off. A run without labels records 0
    /// (`jobs::geometry::pass_settings`), which leaves it out of the record, so records written
    /// before it existed read back the same.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub normal_prior: f64,
    /// The earlier stages' weight of the normal prior, as a share of `normal_prior`. Records written
    /// before it existed held one weight in every stage, hence 1 when absent (and 1 is left out).
    #[serde(default = "one", skip_serializing_if = "is_one")]
    pub normal_prior_coarse_share: f64,
    pub seed: u64,
}

impl GeometryPassConfig {
    /// The normal prior's weight in a stage: `normal_prior` in the last, its coarse share before.
    pub fn stage_normal_prior(&self, last_stage: bool) -> f64 {
        if last_stage {
            self.normal_prior
        } else {
            self.normal_prior * self.normal_prior_coarse_share
        }
    }

    /// The pass without the normal prior in any stage (a run without labels), recorded as such
    /// passes were before the prior existed.
    pub fn without_normal_prior(&self) -> GeometryPassConfig {
        GeometryPassConfig { normal_prior: 0.0, normal_prior_coarse_share: 1.0, ..self.clone() }
    }
}

impl Default for GeometryPassConfig {
    fn default() -> Self {
        GeometryPassConfig {
            // 1000 steps per stage. Measured on the hotdog and the default scene (bench_geometry,
            // 3 stages; docs/geometry.md): 600 steps in all give the hotdog Chamfer (visible)
            // 0.0053, 1500 give 0.0027, and 3000 lower the test-view normal error further
            // (11.6° → 10.3°; the default scene 9.7° → 8.8°). With the coarse stages' views
            // reduced (`coarse_views`), 3000 steps take the hotdog 7 minutes on 2 cores.
            iterations: 3000,
            batch: 4,
            lambda: GEOMETRY_LAMBDA,
            // Uniform Adam normalises by the largest second moment, so most vertices move a small
            // share of this, and (I + λL)⁻¹ damps all but the smoothest modes. Measured on
            // tests/geometry_pass.rs (Chamfer reduction after 200 steps): 0.3 → 1.35×, 1 → 2.75×,
            // 2 → 3.7×, 3 → 3.6×; never a flipped triangle. Two edges per step at first, decaying 10×.
            step_per_edge: 2.0,
            // The material pass's rates (fit::config): colours in [0, 1] need no scale.
            lr_material: 0.03,
            lr_light: 0.03,
            mask_weight: 1.0,
            kd_smoothness: KD_SMOOTHNESS,
            // Measured on the hotdog and the default scene (docs/geometry.md): see there.
            stages: 3,
            // An edge of 1.5 pixels: finer triangles than that cover too few pixel centres to get a
            // shading gradient of their own, and the outline is resolved to a pixel anyway.
            final_edge_pixels: 1.5,
            coarse_views: true,
            normal_prior: GEOMETRY_NORMAL_PRIOR,
            normal_prior_coarse_share: GEOMETRY_NORMAL_PRIOR_COARSE_SHARE,
            seed: 0,
        }
    }
}

/// One training view as the pass sees it: camera and linear RGBA target (straight alpha).
#[derive(Clone)]
pub struct GeometryView {
    pub name: String,
    pub camera: Camera,
    pub target: Image,
    /// The prior's normal label, if the view has one: the world-space unit normal (x, y, z in
    /// [−1, 1]) with the label's mask as a straight alpha, at the target's size.
    pub normal: Option<Image>,
}

fn is_zero(v: &f64) -> bool {
    *v == 0.0
}

fn one() -> f64 {
    1.0
}

fn is_one(v: &f64) -> bool {
    *v == 1.0
}

/// Per-step record.
#[derive(Clone, Debug, Serialize, serde::Deserialize)]
pub struct GeometryStep {
    pub iteration: usize,
    pub loss: f64,
    pub mask_mse: f64,
    /// Share of Adam's step taken (below 1 when a full step would have flipped triangles).
    pub step_taken: f64,
    /// Vertices held where they were so that no triangle broke (`optim::guarded_step`).
    #[serde(default)]
    pub held_vertices: usize,
    pub seconds: f64,
}

/// Wall time of each part of a step, summed over the pass (the bench prints them per step). The
/// views of a step run side by side, so their G-buffer, shading and backward times (each measured
/// on its own thread) share out the wall time of the views' block in proportion; the parts still
/// add up to the step.
#[derive(Clone, Debug, Default, Serialize, serde::Deserialize)]
pub struct GeometryTimings {
    pub gbuffer: f64,
    pub shading: f64,
    pub backward: f64,
    pub update: f64,
    /// Remeshing between stages, with the carrying-over of the per-vertex colour, and each stage's
    /// fold check (`StageRecord::inward_share_at_end`).
    pub remesh: f64,
}

/// One stage of the pass: from which iteration, at which edge length, on how many triangles.
#[derive(Clone, Debug, Serialize, serde::Deserialize)]
pub struct StageRecord {
    pub first_iteration: usize,
    /// Target edge length of the remesh that began the stage (the start's mean edge for the first).
    pub target_edge: f64,
    pub vertices: usize,
    pub triangles: usize,
    /// What happened at the stage's remesh (empty for the first stage).
    pub note: String,
    /// The share of the views' resolution the stage rendered at (`GeometryPassConfig::coarse_views`).
    #[serde(default = "full_resolution")]
    pub view_scale: f64,
    /// The share of the surface facing into the mesh when the stage ended
    /// (`geometry::inward_surface`): about 0 for a healthy surface, the area of a fold through
    /// itself otherwise. Absent in records written before it existed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub inward_share_at_end: Option<f64>,
}

/// The share of `mesh`'s surface facing into it (`geometry::inward_surface`), with the pass's seed,
/// at the end of stage `stage` (1-based) before iteration `it`. An error when the mesh has turned
/// inside out (above [`INSIDE_OUT_SHARE`]): the pass has diverged, and nothing after it would mean
/// anything.
fn stage_end_inward_share(mesh: &Mesh, seed: u64, stage: usize, it: usize) -> Result<f64> {
    let share = inward_share(mesh, &Bvh::build(mesh), INWARD_SAMPLES, seed).context("geometry pass: checking the mesh for folds")?;
    if share > INSIDE_OUT_SHARE {
        bail!(
            "geometry pass: the mesh turned inside out in stage {stage} (before iteration {it}, {:.0} % of its surface faces into it); \
             the optimisation diverged: lower the position step (step_per_edge) or the loss weights",
            100.0 * share
        );
    }
    Ok(share)
}

fn full_resolution() -> f64 {
    1.0
}

pub struct GeometryPassResult {
    /// The optimised mesh (the last stage's connectivity; normals recomputed).
    pub mesh: Mesh,
    /// Per-vertex base colour and the SH light at the end.
    pub vertex_kd: Vec<Vec3>,
    pub light_sh: Vec<f32>,
    pub history: Vec<GeometryStep>,
    pub stages: Vec<StageRecord>,
    pub timings: GeometryTimings,
}

/// A view's per-step render ingredients.
struct ViewTarget {
    camera: Camera,
    /// Linear RGB and alpha, row-major.
    rgb: Arc<[[f32; 3]]>,
    alpha: Arc<[f32]>,
    /// The normal label at the view's size, [H, W, 4]: the world-space unit normal (renormalised
    /// after any resampling) and each pixel's weight (its mask).
    normal: Option<Tensor>,
}

fn to_vec3(v: &[f64; 3]) -> Vec3 {
    Vec3::new(v[0] as f32, v[1] as f32, v[2] as f32)
}

/// The mesh at positions `x` with `start`'s connectivity (normals recomputed).
fn mesh_at(start: &Mesh, x: &[[f64; 3]]) -> Mesh {
    let mut m = start.clone();
    m.positions = x.iter().map(to_vec3).collect();
    m.recompute_normals();
    m
}

pub fn mean_edge_length(mesh: &Mesh) -> f64 {
    let mut sum = 0.0;
    for t in 0..mesh.triangles.len() {
        let p = mesh.triangle_positions(t);
        sum += ((p[1] - p[0]).length() + (p[2] - p[1]).length() + (p[0] - p[2]).length()) as f64;
    }
    sum / (3 * mesh.triangles.len()).max(1) as f64
}

/// One view's share of a step: its loss (already divided by the batch size), the gradients of that
/// share, and the wall time of its phases on the thread that ran it.
struct ViewGradients {
    loss: f64,
    mask_mse: f64,
    grads: GradStore,
    /// G-buffer, shading, backward.
    seconds: [f64; 3],
}

/// What every view of a step shares: the mesh at this step and the tensors it is differentiated in.
struct StepInputs<'a> {
    mesh: &'a Mesh,
    triangles: &'a Arc<[[u32; 3]]>,
    topology: &'a EdgeTopology,
    positions: &'a Tensor,
    normals: &'a Tensor,
    kd: &'a Tensor,
    light: &'a Tensor,
    mask_weight: f64,
    normal_prior: f64,
    /// 1 / views in the step: each view's loss is scaled by it, so the views' gradients add up to
    /// the gradient of the batch's mean.
    share: f64,
}

/// One view's scaled loss (`StepInputs::share` of colour L1 + weighted coverage MSE) as a tensor on
/// the tape, its scaled coverage MSE, and the wall time of its G-buffer and shading.
struct ViewLossTerm {
    loss: Tensor,
    mask_mse: f64,
    seconds: [f64; 2],
}

/// Render one view over `background` and score it against its target.
fn view_loss_term(view: &ViewTarget, step: &StepInputs, background: Vec3) -> Result<ViewLossTerm> {
    let cam = &view.camera;
    let (w, h) = (cam.width, cam.height);
    let t = Instant::now();
    let gbuf = GBuffer::rasterize(step.mesh, cam);
    let t_gbuffer = t.elapsed().as_secs_f64();

    let t = Instant::now();
    let origin = cam.origin().as_dvec3();
    let (mut pixels, mut rays) = (Vec::new(), Vec::new());
    for (i, s) in gbuf.surfels.iter().enumerate() {
        if let Some(s) = s {
            let dir = cam.ray_dir((i % w) as f32 + 0.5, (i / w) as f32 + 0.5).as_dvec3();
            pixels.push(i as u32);
            rays.push(PixelRay { origin, dir, triangle: s.triangle });
        }
    }
    let n = pixels.len();
    let map = PixelMap { pixels: pixels.into(), width: w, height: h };
    let mut prior = None;
    let rgb = if n > 0 {
        let sp = surface_points(SurfacePoints { rays: rays.into(), triangles: step.triangles.clone() }, step.positions, step.normals, step.kd)?;
        let normal = sp.narrow(D::Minus1, 0, 3)?;
        let kd_px = sp.narrow(D::Minus1, 3, 3)?;
        if let (Some(label), true) = (&view.normal, step.normal_prior > 0.0) {
            let rows = map.gather(label)?;
            let (labels, mask) = (rows.narrow(D::Minus1, 0, 3)?.reshape((n, 1, 3))?, rows.narrow(D::Minus1, 3, 1)?.reshape((n, 1, 1))?);
            prior = Some(prior_loss(&normal.reshape((n, 1, 3))?, &labels, &mask, step.normal_prior)?);
        }
        shade_diffuse(&kd_px, &normal, step.light)?
    } else {
        Tensor::zeros((0, 3), DType::F32, &Device::Cpu)?
    };
    // Colour over the background, coverage as the fourth channel.
    let image = map.composite(&rgb, &background.to_array())?;
    let aa = antialias(Silhouettes::new(cam, &gbuf, step.triangles.clone(), step.topology.clone()), &image, step.positions)?;
    // L1 of the tone-mapped colour against the target over the same background, coverage MSE.
    let terms = view_loss(ViewLoss { rgb: view.rgb.clone(), alpha: view.alpha.clone(), background }, &aa)?;
    let (colour, mask) = (terms.get(0)?, terms.get(1)?);
    let mask_mse = mask.to_scalar::<f32>()? as f64 * step.share;
    let mut loss = (colour + (mask * step.mask_weight)?)?;
    if let Some(p) = prior {
        loss = (loss + p)?;
    }
    let loss = (loss * step.share)?;
    Ok(ViewLossTerm { loss, mask_mse, seconds: [t_gbuffer, t.elapsed().as_secs_f64()] })
}

/// [`view_loss_term`] and its backward. Each view runs its own backward, so the views of a step
/// run side by side on the cores: a step's candle ops are small and mostly single-threaded, and
/// one backward over the whole batch would run them one after another.
fn view_gradients(view: &ViewTarget, step: &StepInputs, background: Vec3) -> Result<ViewGradients> {
    let term = view_loss_term(view, step, background)?;
    let t = Instant::now();
    let grads = term.loss.backward()?;
    let [t_gbuffer, t_shading] = term.seconds;
    Ok(ViewGradients { loss: term.loss.to_scalar::<f32>()? as f64, mask_mse: term.mask_mse, grads, seconds: [t_gbuffer, t_shading, t.elapsed().as_secs_f64()] })
}

/// Add `other`'s gradients of `vars` into `acc`.
fn accumulate(acc: &mut GradStore, other: &GradStore, vars: &[&Tensor]) -> Result<()> {
    for v in vars {
        if let Some(g) = other.get(v) {
            let sum = match acc.get(v) {
                Some(a) => (a + g)?,
                None => g.clone(),
            };
            acc.insert(v, sum);
        }
    }
    Ok(())
}

/// Views per step of a stage whose views are at `scale` of their resolution: `batch` / scale.
/// The outline's gradient comes from the outline's pixels, whose number per view grows with the
/// resolution (not its square), so this keeps the outline pixels per step, while the step costs
/// `scale` of a full-resolution one.
fn stage_batch(batch: usize, scale: f64) -> usize {
    if scale >= 1.0 {
        batch
    } else {
        (batch as f64 / scale).round() as usize
    }
}

/// The views as a stage renders them: at `scale` of their resolution (the target resampled with
/// its alpha, the camera's field of view kept), or as given when `scale` is 1 or more.
fn view_targets(views: &[GeometryView], scale: f64) -> Result<Vec<ViewTarget>> {
    views
        .iter()
        .map(|v| {
            let camera = if scale < 1.0 {
                let c = &v.camera;
                let w = ((c.width as f64 * scale).round() as usize).max(1);
                // The height from the width's ratio, so that the pixels stay square (the camera's
                // focal length follows its width).
                let h = ((c.height * w) as f64 / c.width as f64).round().max(1.0) as usize;
                c.resized(w, h)
            } else {
                v.camera.clone()
            };
            // An RGBA picture of the view (target or label) at the camera's size.
            let at_size = |image: &Image| -> Result<Image> {
                if image.width == camera.width && image.height == camera.height {
                    Ok(image.clone())
                } else {
                    image.resized_straight_alpha(camera.width, camera.height).with_context(|| format!("geometry pass: view {}", v.name))
                }
            };
            let target = at_size(&v.target)?;
            let rgb = target.data.chunks_exact(4).map(|p| [p[0], p[1], p[2]]).collect();
            let alpha = target.data.chunks_exact(4).map(|p| p[3]).collect();
            let normal = match &v.normal {
                Some(label) => {
                    let label = at_size(label)?;
                    let rows: Vec<f32> = label.data.chunks_exact(4).flat_map(|p| {
                        let n = Vec3::new(p[0], p[1], p[2]).normalize_or_zero();
                        [n.x, n.y, n.z, p[3]]
                    }).collect();
                    Some(Tensor::from_vec(rows, (camera.height, camera.width, 4), &Device::Cpu)?)
                }
                None => None,
            };
            Ok(ViewTarget { camera, rgb, alpha, normal })
        })
        .collect()
}

/// The per-connectivity state of the pass: rebuilt at each stage's remesh.
struct StageState {
    /// The mesh the stage started from (its connectivity, parts and materials).
    template: Mesh,
    triangles: Arc<[[u32; 3]]>,
    topology: EdgeTopology,
    kd_reg: VertexSmoothness,
    ls: LargeSteps,
    x: Vec<[f64; 3]>,
    u: Vec<[f64; 3]>,
    pos_adam: UniformAdam,
    /// A triangle whose doubled area squared falls below this is degenerate.
    min_area2: f64,
    kd: Var,
    /// kd and light; rebuilt with the stage (new kd) but continuing the schedule.
    adam: Adam,
}

impl StageState {
    fn new(template: Mesh, vertex_kd: &[Vec3], light: &Var, config: &GeometryPassConfig, schedule: LrSchedule, step: usize) -> Result<StageState> {
        let triangles: Arc<[[u32; 3]]> = template.triangles.clone().into();
        let topology = EdgeTopology::new(&triangles);
        let kd_reg = VertexSmoothness::new(&UniformLaplacian::new(template.positions.len(), &triangles).context("geometry pass")?)?;
        let ls = LargeSteps::new(template.positions.len(), &triangles, config.lambda).context("geometry pass")?;
        let x: Vec<[f64; 3]> = template.positions.iter().map(|p| p.as_dvec3().to_array()).collect();
        let u = ls.to_u(&x);
        let edge = mean_edge_length(&template);
        let pos_adam = UniformAdam::new(x.len(), config.step_per_edge * edge);
        let min_area2 = degenerate_area2(edge);
        let dev = &Device::Cpu;
        let kd_rows: Vec<f32> = vertex_kd.iter().flat_map(|c| c.to_array()).collect();
        let kd = Var::from_tensor(&Tensor::from_vec(kd_rows, (x.len(), 3), dev)?)?;
        let mut adam = Adam::new(schedule).starting_at(step);
        adam.add_group(GroupConfig::new("vertex kd", config.lr_material).with_clamp(0.0, 1.0), vec![kd.clone()])?;
        adam.add_group(GroupConfig::new("sh light", config.lr_light), vec![light.clone()])?;
        Ok(StageState { template, triangles, topology, kd_reg, ls, x, u, pos_adam, min_area2, kd, adam })
    }

    fn mesh(&self) -> Mesh {
        mesh_at(&self.template, &self.x)
    }

    fn vertex_kd(&self) -> Result<Vec<Vec3>> {
        Ok(self.kd.as_tensor().flatten_all()?.to_vec1::<f32>()?.chunks_exact(3).map(|c| Vec3::new(c[0], c[1], c[2])).collect())
    }
}

/// The stage's mesh with a fold repaired, and what was done (empty when nothing was): when more
/// than `FOLDED_SHARE` of its surface faces into it, the surface of what it encloses
/// (`geometry::enclosed_surface`), sampled at half the next stage's edge so that the remesh to that
/// edge loses nothing the grid could hold; `None` when the mesh is not folded or the extraction failed
/// (the note then says why, and the stage goes on with the folded mesh).
fn unfold(mesh: &Mesh, inward_share: f64, next_edge: f64) -> (Option<Mesh>, String) {
    if inward_share <= FOLDED_SHARE {
        return (None, String::new());
    }
    match enclosed_surface(mesh, 0.5 * next_edge as f32) {
        Ok(e) => {
            let note = format!(
                "{:.1} % of the surface faced into the mesh: re-extracted the surface it encloses on a {}×{}×{} grid (voxel {:.4}{})",
                100.0 * inward_share,
                e.dims[0],
                e.dims[1],
                e.dims[2],
                e.voxel,
                if e.attempts > 1 { format!("; {} shifted grids tried", e.attempts) } else { String::new() }
            );
            (Some(e.mesh), note)
        }
        Err(err) => (None, format!("{:.1} % of the surface faced into the mesh, and re-extracting its surface failed ({err:#}); kept the folded mesh", 100.0 * inward_share)),
    }
}

/// A successful remesh stage: the new mesh, its per-vertex colour, and the note on what was
/// tolerated (needle triangles; empty when nothing was).
type Remeshed = (Mesh, Vec<Vec3>, String);

/// `surface` remeshed to `target_edge` with the per-vertex colour of `colour` (a mesh and its
/// vertices' colours; `surface` itself, or what it was extracted from) carried over: each new vertex
/// takes the colour interpolated at its closest point on that mesh. `Err` with the reason when the
/// remesher's result is not a clean closed surface (the stage then keeps the old mesh).
fn remesh_stage(surface: &Mesh, colour: (&Mesh, &[Vec3]), target_edge: f64) -> Result<std::result::Result<Remeshed, String>> {
    let (mut outcome, mut problems) = (None, Vec::new());
    for flips in [true, false] {
        let (p, t) = isotropic_remesh(&surface.positions, &surface.triangles, target_edge as f32, REMESH_ROUNDS, flips)?;
        let m = surface.with_geometry(p, t);
        let degenerate = degenerate_triangles(&m, target_edge);
        // A few needles are tolerated (they cover no pixel centre and the step holds their vertices
        // rather than shrink them further; see `optim::guarded_step`), more than 1 in 1000 triangles is not.
        if check_closed_manifold(&m).is_ok() && signed_volume(&m) > 0.0 && degenerate * 1000 <= m.triangles.len() {
            problems.push(if degenerate > 0 { format!("{degenerate} needle triangles tolerated") } else { String::new() });
            outcome = Some(m);
            break;
        }
        problems.push(format!(
            "{}: {}",
            if flips { "with flips" } else { "without flips" },
            match check_closed_manifold(&m) {
                Err(e) => e,
                Ok(_) if degenerate * 1000 > m.triangles.len() => format!("{degenerate} degenerate triangles"),
                Ok(_) => "faces inward".to_string(),
            }
        ));
    }
    let Some(new) = outcome else {
        return Ok(Err(format!("the remesh to edge {target_edge:.4} did not give a clean closed surface ({}); kept the previous mesh", problems.join("; "))));
    };
    let (mesh, vertex_kd) = colour;
    let query = SurfaceQuery::new(mesh)?;
    let kd = new
        .positions
        .iter()
        .map(|&p| match query.closest(p) {
            Some(c) => {
                let [a, b, cc] = mesh.triangle_positions(c.triangle as usize);
                let bary = barycentric(a, b, cc, c.point);
                interpolate(mesh, vertex_kd, c.triangle as usize, bary)
            }
            None => Vec3::splat(0.5),
        })
        .collect();
    Ok(Ok((new, kd, problems.into_iter().filter(|p| !p.is_empty()).collect::<Vec<_>>().join("; "))))
}

/// Triangles of `mesh` whose doubled area is below 1e-6 of `edge`² (the pass's own test of a
/// degenerate triangle; see `StageState::min_area2`).
fn degenerate_triangles(mesh: &Mesh, edge: f64) -> usize {
    let min_area2 = degenerate_area2(edge);
    (0..mesh.triangles.len())
        .filter(|&t| {
            let [a, b, c] = mesh.triangle_positions(t).map(|p| p.as_dvec3());
            let n2 = (b - a).cross(c - a).length_squared();
            // Not `n2 < min_area2`: a NaN area must count as degenerate.
            n2.partial_cmp(&min_area2).is_none_or(|o| o.is_lt())
        })
        .count()
}

/// Barycentrics (b1, b2) of `p` (assumed in the triangle's plane) in triangle (a, b, c), clamped
/// to the triangle.
fn barycentric(a: Vec3, b: Vec3, c: Vec3, p: Vec3) -> Vec2 {
    let (e1, e2, d) = (b - a, c - a, p - a);
    let (d11, d12, d22) = (e1.dot(e1), e1.dot(e2), e2.dot(e2));
    let (d1, d2) = (d.dot(e1), d.dot(e2));
    let det = d11 * d22 - d12 * d12;
    if det.abs() <= f32::EPSILON * d11 * d22 {
        return Vec2::ZERO;
    }
    let b1 = ((d22 * d1 - d12 * d2) / det).clamp(0.0, 1.0);
    let b2 = ((d11 * d2 - d12 * d1) / det).clamp(0.0, 1.0 - b1);
    Vec2::new(b1, b2)
}

/// The per-vertex colour's smoothness weight: the material pass's kd smoothness weight
/// (`optim::weights`, NVDiffRecMC's λ_kd = 0.1), the neighbour one edge away instead of a
/// jittered lookup. Measured on the default scene (docs/geometry.md): 0.1 lowers Chamfer and the
/// normal error, 1 holds the colour too flat to follow the albedo's real edges.
const KD_SMOOTHNESS: f64 = 0.1;

/// λ of Large Steps' (I + λL) in the pass. An update spreads over about √λ vertex rings
/// (`optim::large_steps`); at the last stage's edge of 1.5 pixels the paper's default 19 spreads
/// it over some 6 pixels, wider than the details the shading must grow inside the outline (a
/// bun's crease, a blob of sauce on a plate), which then never form. Measured on the default scene
/// and the hotdog (docs/geometry.md): 19 → 5 → 2 lowered the test-view normal error on both
/// (16.5° → 12.0° → 9.7° and 16.3° → 12.4° → 11.6°). λ = 1 spreads an update over about one ring,
/// 1.5 pixels: once the first stage's folds were repaired and the labels' normals held the last
/// stage, it placed the hotdog's surface closer at each of three seeds (Chamfer (visible) −0.0002
/// to −0.0004) and relit it 0.6 dB better on average (gap to known geometry 3.4 → 2.8 dB), the
/// default scene equal or better in every row, and without labels the hotdog's pass the same
/// (0.0027 / 0.937 / 0.949 / 10.69° against 0.0028 / 0.931 / 0.955 / 10.66°).
pub const GEOMETRY_LAMBDA: f64 = 1.0;

/// Weight of the normal prior in the pass's last stage (`GeometryPassConfig::normal_prior`). The
/// prior is ‖n − label‖² ≈ θ² (θ the angle to the label), beside an L1 colour loss of a few
/// hundredths: IDArb-quality labels (about 20° off) give a term of about 0.1 per pixel, so a weight
/// near 1 makes the labels, not the images, shape the mesh, and their smooth errors get written
/// into it. Measured with simulated IDArb labels (`bench_geometry --prior idarb-sim`;
/// docs/geometry.md, *The normal labels in the geometry pass*). One weight in every stage: on the
/// default scene 1 / 0.1 / 0.01 / 0.003 / 0.001 take the test-view normal error from 8.47° to
/// 13.40 / 10.90 / 5.49 / 6.86 / 7.85°, but on the hotdog 0.01 already costs F-score (0.931 →
/// 0.900), so 0.003 was the default. In the last stage alone (`GEOMETRY_NORMAL_PRIOR_COARSE_SHARE`)
/// 0.01 / 0.02 give 5.34 / 4.79° on the default scene and 6.83 / 6.67° on the hotdog (6.86° and
/// 8.66° with 0.003 throughout), with every position score as good or better. Again at λ = 1,
/// three seeds of the hotdog: 0.01 / 0.02 / 0.03 give a mean normal error of 7.30 / 6.78 / 7.27°.
pub const GEOMETRY_NORMAL_PRIOR: f64 = 0.02;

/// The earlier stages' weight of the normal prior, as a share of the last stage's: none. In the
/// coarse stages the mesh is still far from its place, and a normal held to its label at a point
/// in the wrong place tilts the triangle's neighbours; the labels there bought nothing the last
/// stage does not (docs/geometry.md: 0.003 before a last stage at 0.01 gave 5.18° on the default
/// scene but 7.86° on the hotdog, against 5.34° and 6.83° with none before it; before 0.02, 5.14°
/// and 7.41° against 4.79° and 6.67°).
pub const GEOMETRY_NORMAL_PRIOR_COARSE_SHARE: f64 = 0.0;

/// Rounds of the remesher between stages: the remesher's own default, as for the hull.
const REMESH_ROUNDS: u16 = 10;

/// The target edge of each stage: geometric steps from `start_edge` to `final_edge` (never
/// coarser than the start: a final edge above the start's keeps the start's connectivity).
fn stage_edges(start_edge: f64, final_edge: f64, stages: usize) -> Vec<f64> {
    let stages = stages.max(1);
    let last = final_edge.min(start_edge);
    (0..stages).map(|s| if stages == 1 { start_edge } else { start_edge * (last / start_edge).powf(s as f64 / (stages - 1) as f64) }).collect()
}

/// Runs the pass from `start` (a closed mesh; see [`GeometryPassConfig::stages`] for when its
/// connectivity changes).
pub fn run_geometry_pass(start: &Mesh, views: &[GeometryView], config: &GeometryPassConfig, progress: bool) -> Result<GeometryPassResult> {
    if start.triangles.is_empty() {
        bail!("geometry pass: the start mesh is empty");
    }
    if views.is_empty() {
        bail!("geometry pass: no training views");
    }
    for v in views {
        let c = &v.camera;
        anyhow::ensure!(
            v.target.width == c.width && v.target.height == c.height && v.target.channels == 4,
            "geometry pass: view {} has a {}×{}×{} target for a {}×{} camera (RGBA expected)",
            v.name,
            v.target.width,
            v.target.height,
            v.target.channels,
            c.width,
            c.height
        );
    }

    let dev = &Device::Cpu;
    let schedule = LrSchedule { warmup_steps: 0, decay_steps: config.iterations.max(1), staircase: false };
    let light = Var::from_tensor(&Tensor::from_vec(constant_light(1.0), (SH_COEFFICIENTS, 3), dev)?)?;
    let (lo, hi) = start.bounds().context("geometry pass: the start mesh has no vertices")?;
    let footprint = median_pixel_footprint(views.iter().map(|v| &v.camera), 0.5 * (lo + hi)) as f64;
    let edges = stage_edges(mean_edge_length(start), config.final_edge_pixels * footprint, config.stages);
    let stage_starts: Vec<usize> = (0..edges.len()).map(|s| s * config.iterations / edges.len()).collect();
    let stage_scale = |s: usize| if config.coarse_views { edges[edges.len() - 1] / edges[s] } else { 1.0 };
    let mut targets = view_targets(views, stage_scale(0))?;
    let mut state = StageState::new(start.clone(), &vec![Vec3::splat(0.5); start.positions.len()], &light, config, schedule, 0)?;
    let mut stages = vec![StageRecord {
        first_iteration: 0,
        target_edge: edges[0],
        vertices: start.positions.len(),
        triangles: start.triangles.len(),
        note: String::new(),
        view_scale: stage_scale(0),
        inward_share_at_end: None,
    }];

    let bar = if progress { ProgressBar::new(config.iterations as u64) } else { ProgressBar::hidden() };
    bar.set_style(
        ProgressStyle::with_template("geometry [{bar:30}] {pos}/{len} {msg} (ETA {eta})")
            .map_err(|e| anyhow::anyhow!("progress bar template: {e}"))?
            .progress_chars("=> "),
    );
    let mut history = Vec::with_capacity(config.iterations);
    let mut timings = GeometryTimings::default();
    let mut order: Vec<usize> = Vec::new();
    for it in 0..config.iterations {
        if let Some(s) = stage_starts.iter().skip(1).position(|&first| first == it).map(|k| k + 1) {
            let t = Instant::now();
            let mesh = state.mesh();
            let share = stage_end_inward_share(&mesh, config.seed, s, it)?;
            if let Some(ended) = stages.last_mut() {
                ended.inward_share_at_end = Some(share);
            }
            let kd = state.vertex_kd()?;
            let (unfolded, repair) = unfold(&mesh, share, edges[s]);
            let remeshed = remesh_stage(unfolded.as_ref().unwrap_or(&mesh), (&mesh, &kd), edges[s]).with_context(|| format!("geometry pass: remeshing before iteration {it}"))?;
            let remesh_note = match remeshed {
                Ok((new, kd, note)) => {
                    state = StageState::new(new, &kd, &light, config, schedule, it)?;
                    note
                }
                Err(why) => why,
            };
            let note = [repair, remesh_note].into_iter().filter(|n| !n.is_empty()).collect::<Vec<_>>().join("; ");
            if stage_scale(s) != stage_scale(s - 1) {
                targets = view_targets(views, stage_scale(s))?;
            }
            stages.push(StageRecord { first_iteration: it, target_edge: edges[s], vertices: state.x.len(), triangles: state.triangles.len(), note, view_scale: stage_scale(s), inward_share_at_end: None });
            timings.remesh += t.elapsed().as_secs_f64();
        }
        let t_step = Instant::now();
        let mesh = state.mesh();

        // Views: consecutive slices of a seeded shuffle, one epoch after another.
        let mut rng = Sampler::new(config.seed, 0x6e0_0000 + it as u64);
        let views_per_step = stage_batch(config.batch, stage_scale(stages.len() - 1));
        let mut batch = Vec::with_capacity(views_per_step);
        while batch.len() < views_per_step.min(targets.len()) {
            if order.is_empty() {
                order = (0..targets.len()).collect();
                for i in (1..order.len()).rev() {
                    order.swap(i, ((rng.next_f32() * (i + 1) as f32) as usize).min(i));
                }
            }
            batch.push(order.pop().expect("refilled above"));
        }

        let v = state.x.len();
        let positions = Var::from_tensor(&Tensor::from_vec(state.x.iter().flat_map(|p| p.map(|c| c as f32)).collect::<Vec<_>>(), (v, 3), dev)?)?;
        let t = Instant::now();
        let normals = vertex_normals(state.triangles.clone(), positions.as_tensor())?;
        let backgrounds: Vec<Vec3> = batch.iter().map(|_| Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32())).collect();
        let inputs = StepInputs {
            mesh: &mesh,
            triangles: &state.triangles,
            topology: &state.topology,
            positions: positions.as_tensor(),
            normals: &normals,
            kd: state.kd.as_tensor(),
            light: light.as_tensor(),
            mask_weight: config.mask_weight,
            normal_prior: config.stage_normal_prior(stages.len() == edges.len()),
            share: 1.0 / batch.len() as f64,
        };
        let per_view: Vec<ViewGradients> = batch.par_iter().zip(&backgrounds).map(|(&i, &bg)| view_gradients(&targets[i], &inputs, bg)).collect::<Result<_>>()?;
        // The views ran side by side: their phases' thread times share out the block's wall time.
        let (wall, phases) = (t.elapsed().as_secs_f64(), per_view.iter().fold([0.0; 3], |acc, r| [0, 1, 2].map(|k| acc[k] + r.seconds[k])));
        let to_wall = wall / phases.iter().sum::<f64>().max(f64::MIN_POSITIVE);
        timings.gbuffer += phases[0] * to_wall;
        timings.shading += phases[1] * to_wall;
        timings.backward += phases[2] * to_wall;

        let vars = [positions.as_tensor(), state.kd.as_tensor(), light.as_tensor()];
        let mut per_view = per_view.into_iter();
        let first = per_view.next().context("geometry pass: a step with no views")?;
        let (mut loss_value, mut mask_mse, mut grads) = (first.loss, first.mask_mse, first.grads);
        for r in per_view {
            accumulate(&mut grads, &r.grads, &vars)?;
            loss_value += r.loss;
            mask_mse += r.mask_mse;
        }
        if config.kd_smoothness > 0.0 {
            let t = Instant::now();
            let reg = (state.kd_reg.apply(state.kd.as_tensor())? * config.kd_smoothness)?;
            loss_value += reg.to_scalar::<f32>()? as f64;
            accumulate(&mut grads, &reg.backward()?, &vars)?;
            timings.backward += t.elapsed().as_secs_f64();
        }
        if !loss_value.is_finite() {
            bail!("geometry pass: the loss became non-finite at iteration {it}");
        }

        let t = Instant::now();
        let lr_factor = state.adam.lr_factor();
        state.adam.step(&grads)?;
        let g_x: Vec<[f64; 3]> = match grads.get(positions.as_tensor()) {
            Some(g) => g.flatten_all()?.to_vec1::<f32>()?.chunks_exact(3).map(|c| [c[0] as f64, c[1] as f64, c[2] as f64]).collect(),
            None => vec![[0.0; 3]; v],
        };
        if g_x.iter().flatten().any(|g| !g.is_finite()) {
            bail!("geometry pass: non-finite position gradient at iteration {it}");
        }
        let du = state.pos_adam.step(&state.ls.solve(&g_x), lr_factor);
        let step = guard_step(&state.ls, &state.triangles, &state.u, &state.x, &du, state.min_area2).map_err(|c| {
            anyhow::anyhow!(
                "geometry pass: the mesh collapsed at iteration {it} (stage {} of {}, {} triangles): even 1/256 of the step \
                 flips or degenerates {} triangles, too many to hold back; lower the position step (step_per_edge) or start \
                 from a cleaner mesh",
                stages.len(),
                edges.len(),
                state.triangles.len(),
                c.broken
            )
        })?;
        let (share, held) = (step.share, step.held);
        state.u = step.u;
        state.x = step.x;
        timings.update += t.elapsed().as_secs_f64();

        history.push(GeometryStep { iteration: it, loss: loss_value, mask_mse, step_taken: share, held_vertices: held, seconds: t_step.elapsed().as_secs_f64() });
        bar.set_message(format!("loss {loss_value:.4} mask MSE {mask_mse:.4}"));
        bar.inc(1);
    }
    bar.finish();
    let mesh = state.mesh();
    let stages_len = stages.len();
    if let Some(last) = stages.last_mut() {
        let t = Instant::now();
        last.inward_share_at_end = Some(stage_end_inward_share(&mesh, config.seed, stages_len, config.iterations)?);
        timings.remesh += t.elapsed().as_secs_f64();
    }
    let vertex_kd = state.vertex_kd()?;
    let light_sh = light.as_tensor().flatten_all()?.to_vec1::<f32>()?;
    Ok(GeometryPassResult { mesh, vertex_kd, light_sh, history, stages, timings })
}

/// Per-vertex values `attr` of `source` carried to a mesh whose triangles are the same in the
/// same order with vertices split at seams (the UV atlas's mesh): each corner takes its source
/// corner's value.
pub fn transfer_vertex_values<T: Copy + Default>(source: &Mesh, attr: &[T], target: &Mesh) -> Vec<T> {
    let mut out = vec![T::default(); target.positions.len()];
    for (ts, tt) in source.triangles.iter().zip(&target.triangles) {
        for c in 0..3 {
            out[tt[c] as usize] = attr[ts[c] as usize];
        }
    }
    out
}

/// Interpolates per-vertex values at barycentrics `bary` (b1, b2) of triangle `t`.
pub fn interpolate(mesh: &Mesh, attr: &[Vec3], t: usize, bary: Vec2) -> Vec3 {
    let [a, b, c] = mesh.triangles[t].map(|i| i as usize);
    (1.0 - bary.x - bary.y) * attr[a] + bary.x * attr[b] + bary.y * attr[c]
}

/// The pass's image model without gradients: `mesh` with per-vertex `vertex_kd` under the SH
/// `light_sh` [9 × 3], as straight-alpha linear RGBA, with `supersample`² rays per pixel
/// (box-filtered coverage). For validation images, and for targets in tests.
pub fn render_sh(mesh: &Mesh, vertex_kd: &[Vec3], light_sh: &[f32], camera: &Camera, supersample: usize) -> Result<Image> {
    let s = supersample.max(1);
    let big = camera.resized(camera.width * s, camera.height * s);
    let gbuf = GBuffer::rasterize(mesh, &big);
    let hits: Vec<(usize, Vec3, Vec3)> = gbuf
        .surfels
        .iter()
        .enumerate()
        .filter_map(|(i, s)| s.map(|s| (i, s.normal, interpolate(mesh, vertex_kd, s.triangle as usize, s.bary))))
        .collect();
    let dev = &Device::Cpu;
    let mut img = Image::new(big.width, big.height, 4);
    if !hits.is_empty() {
        let n = Tensor::from_vec(hits.iter().flat_map(|h| h.1.to_array()).collect::<Vec<_>>(), (hits.len(), 3), dev)?;
        let kd = Tensor::from_vec(hits.iter().flat_map(|h| h.2.to_array()).collect::<Vec<_>>(), (hits.len(), 3), dev)?;
        let light = Tensor::from_vec(light_sh.to_vec(), (SH_COEFFICIENTS, 3), dev)?;
        let rgb = shade_diffuse(&kd, &n, &light)?.flatten_all()?.to_vec1::<f32>()?;
        for (k, h) in hits.iter().enumerate() {
            img.data[4 * h.0..4 * h.0 + 3].copy_from_slice(&rgb[3 * k..3 * k + 3]);
            img.data[4 * h.0 + 3] = 1.0;
        }
    }
    // Premultiplied colour averages correctly; divide by the averaged coverage afterwards.
    Ok(img.downsample_box(s).unpremultiplied())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_record_without_the_coarse_share_held_one_prior_weight_in_every_stage() -> Result<()> {
        let new = GeometryPassConfig { normal_prior: 0.02, normal_prior_coarse_share: 0.25, ..Default::default() };
        assert_eq!((new.stage_normal_prior(false), new.stage_normal_prior(true)), (0.005, 0.02));
        let mut old = serde_json::to_value(&new)?;
        old.as_object_mut().context("a record is an object")?.remove("normal_prior_coarse_share");
        let old: GeometryPassConfig = serde_json::from_value(old)?;
        assert_eq!((old.stage_normal_prior(false), old.stage_normal_prior(true)), (0.02, 0.02));
        // A pass without the prior records neither field, as records before the prior did.
        let text = serde_json::to_string(&new.without_normal_prior())?;
        assert!(!text.contains("normal_prior"), "{text}");
        Ok(())
    }

    #[test]
    fn the_views_gradients_add_up_to_the_gradient_of_the_batch_loss() -> Result<()> {
        // Each view runs its own backward and the step adds the results; that must be the
        // gradient of the batch's mean loss taken in one backward. Two views of a sphere, the
        // mesh a coarser sphere off-centre (so outlines and shading both give gradients).
        let truth = crate::geometry::icosphere::icosphere(Vec3::ZERO, 0.8, 3);
        let mesh = crate::geometry::icosphere::icosphere(Vec3::new(0.05, -0.03, 0.02), 0.75, 2);
        let kd_truth = vec![Vec3::new(0.7, 0.5, 0.3); truth.positions.len()];
        let light_sh = constant_light(1.0);
        let views: Vec<GeometryView> = [Vec3::new(0.0, -3.0, 1.0), Vec3::new(2.5, 1.0, -1.5)]
            .iter()
            .enumerate()
            .map(|(k, &eye)| {
                let camera = Camera::look_at(eye, Vec3::ZERO, Vec3::Z, 0.8, 40, 32);
                Ok(GeometryView { name: format!("v{k}"), target: render_sh(&truth, &kd_truth, &light_sh, &camera, 2)?, camera, normal: None })
            })
            .collect::<Result<_>>()?;
        let targets = view_targets(&views, 1.0)?;
        let dev = &Device::Cpu;
        let triangles: Arc<[[u32; 3]]> = mesh.triangles.clone().into();
        let topology = EdgeTopology::new(&triangles);
        let positions = Var::from_tensor(&Tensor::from_vec(mesh.positions.iter().flat_map(|p| p.to_array()).collect::<Vec<_>>(), (mesh.positions.len(), 3), dev)?)?;
        let kd = Var::from_tensor(&Tensor::full(0.4f32, (mesh.positions.len(), 3), dev)?)?;
        let light = Var::from_tensor(&Tensor::from_vec(light_sh.clone(), (SH_COEFFICIENTS, 3), dev)?)?;
        let normals = vertex_normals(triangles.clone(), positions.as_tensor())?;
        let inputs = StepInputs {
            mesh: &mesh,
            triangles: &triangles,
            topology: &topology,
            positions: positions.as_tensor(),
            normals: &normals,
            kd: kd.as_tensor(),
            light: light.as_tensor(),
            mask_weight: 2.0,
            normal_prior: 0.0,
            share: 0.5,
        };
        let backgrounds = [Vec3::new(0.2, 0.9, 0.4), Vec3::new(0.6, 0.1, 0.8)];
        let joint = (view_loss_term(&targets[0], &inputs, backgrounds[0])?.loss + view_loss_term(&targets[1], &inputs, backgrounds[1])?.loss)?.backward()?;
        let mut per_view: Vec<ViewGradients> = (0..2).into_par_iter().map(|k| view_gradients(&targets[k], &inputs, backgrounds[k])).collect::<Result<_>>()?;
        let vars = [positions.as_tensor(), kd.as_tensor(), light.as_tensor()];
        let second = per_view.pop().context("two views")?;
        let mut summed = per_view.pop().context("two views")?.grads;
        accumulate(&mut summed, &second.grads, &vars)?;
        for (name, v) in ["positions", "kd", "light"].iter().zip(vars) {
            let (a, b) = (joint.get(v).context("joint gradient")?, summed.get(v).context("summed gradient")?);
            let (a, b) = (a.flatten_all()?.to_vec1::<f32>()?, b.flatten_all()?.to_vec1::<f32>()?);
            let scale = a.iter().fold(0.0f32, |m, x| m.max(x.abs()));
            assert!(scale > 0.0, "{name}: no gradient");
            let worst = a.iter().zip(&b).fold(0.0f32, |m, (x, y)| m.max((x - y).abs()));
            assert!(worst <= 1e-5 * scale, "{name}: summed per-view gradients differ from the joint one by {worst} (largest {scale})");
        }
        Ok(())
    }

    /// A mesh turned inside out at a stage's end stops the pass with an error naming the stage
    /// and the iteration, where a fold (below half the surface) is left to the repair.
    #[test]
    fn a_mesh_turned_inside_out_stops_the_pass_naming_the_stage_and_iteration() -> Result<()> {
        use crate::geometry::icosphere::icosphere;
        let mut inverted = icosphere(Vec3::ZERO, 1.0, 3);
        for t in inverted.triangles.iter_mut() {
            t.swap(1, 2);
        }
        let err = stage_end_inward_share(&inverted, 0, 2, 2000).expect_err("an inside-out mesh must stop the pass");
        let text = format!("{err:#}");
        assert!(text.contains("inside out in stage 2") && text.contains("iteration 2000"), "{text}");

        let mut folded = icosphere(Vec3::ZERO, 1.0, 3);
        folded.append(icosphere(Vec3::new(0.1, 0.0, 0.0), 0.5, 3));
        let share = stage_end_inward_share(&folded, 0, 2, 2000)?;
        assert!(share > FOLDED_SHARE && share < INSIDE_OUT_SHARE, "a fold, not an inversion: {share}");
        Ok(())
    }

    /// A stage boundary's repair: a folded mesh (a sphere with a second one inside it, whose whole
    /// surface faces into the first) comes out as the outer sphere alone, and its colour carries over
    /// through the remesh; a healthy mesh is left to the remesh as it is.
    #[test]
    fn a_folded_stage_mesh_is_unfolded_and_keeps_its_colour() -> Result<()> {
        use crate::geometry::icosphere::icosphere;
        let outer = icosphere(Vec3::ZERO, 1.0, 3);
        let (healthy, note) = unfold(&outer, stage_end_inward_share(&outer, 0, 1, 10)?, 0.1);
        assert!(healthy.is_none() && note.is_empty(), "a healthy mesh was changed: {note}");

        let mut folded = outer.clone();
        folded.append(icosphere(Vec3::new(0.1, 0.0, 0.0), 0.5, 3));
        let share = stage_end_inward_share(&folded, 0, 1, 10)?;
        assert!(share > 0.1, "the inner sphere faces inward: {share}");
        let (unfolded, note) = unfold(&folded, share, 0.1);
        let unfolded = unfolded.with_context(|| format!("the folded mesh was not repaired: {note}"))?;
        assert!(stage_end_inward_share(&unfolded, 0, 1, 10)? <= FOLDED_SHARE, "{note}");
        // Colour by height on the folded mesh, carried to the remeshed outer sphere.
        let kd: Vec<Vec3> = folded.positions.iter().map(|p| Vec3::splat(0.5 + 0.5 * p.z)).collect();
        let (new, new_kd, _) = remesh_stage(&unfolded, (&folded, &kd), 0.1)?.map_err(anyhow::Error::msg)?;
        let worst_radius = new.positions.iter().map(|p| (p.length() - 1.0).abs()).fold(0.0f32, f32::max);
        assert!(worst_radius < 0.03, "a vertex {worst_radius} off the outer sphere");
        let worst_colour = new.positions.iter().zip(&new_kd).map(|(p, c)| (c.x - (0.5 + 0.5 * p.z)).abs()).fold(0.0f32, f32::max);
        assert!(worst_colour < 0.05, "colour off by {worst_colour}");
        Ok(())
    }

    #[test]
    fn stage_edges_step_geometrically_and_never_coarsen() {
        let e = stage_edges(0.04, 0.01, 3);
        assert_eq!(e.len(), 3);
        assert!((e[0] - 0.04).abs() < 1e-12 && (e[1] - 0.02).abs() < 1e-12 && (e[2] - 0.01).abs() < 1e-12, "{e:?}");
        // A final edge coarser than the start keeps the start's.
        assert!(stage_edges(0.01, 0.04, 3).iter().all(|&x| (x - 0.01).abs() < 1e-12));
        assert_eq!(stage_edges(0.02, 0.01, 1), vec![0.02]);
        assert_eq!(stage_edges(0.02, 0.01, 0), vec![0.02]);
    }

    #[test]
    fn a_coarse_stage_view_lines_up_with_a_render_at_its_resolution() -> Result<()> {
        // The resampled target and the resized camera must describe the same picture: an
        // off-centre sphere's non-square 100×70 view reduced to 0.6, against the sphere rendered
        // directly at that size. The covered area and its centroid must agree (a shift of half a
        // pixel would move the centroid by half a pixel).
        let sphere = crate::geometry::icosphere::icosphere(Vec3::new(0.4, -0.2, 0.1), 0.8, 4);
        let kd = vec![Vec3::splat(0.6); sphere.positions.len()];
        let light = constant_light(1.0);
        let camera = Camera::look_at(Vec3::new(0.3, -3.5, 1.5), Vec3::ZERO, Vec3::Z, 0.9, 100, 70);
        let target = render_sh(&sphere, &kd, &light, &camera, 4)?;
        let coarse = view_targets(&[GeometryView { name: "v".into(), camera: camera.clone(), target, normal: None }], 0.6)?;
        let c = &coarse[0].camera;
        assert_eq!((c.width, c.height), (60, 42));
        let direct = render_sh(&sphere, &kd, &light, c, 4)?;
        let alpha_direct: Vec<f32> = direct.data.chunks_exact(4).map(|p| p[3]).collect();
        let moments = |a: &[f32]| {
            let (mut m, mut mx, mut my) = (0.0, 0.0, 0.0);
            for (i, &v) in a.iter().enumerate() {
                m += v as f64;
                mx += v as f64 * (i % 60) as f64;
                my += v as f64 * (i / 60) as f64;
            }
            (m, mx / m, my / m)
        };
        let ((m0, x0, y0), (m1, x1, y1)) = (moments(&coarse[0].alpha), moments(&alpha_direct));
        assert!(m1 > 100.0 && (m0 / m1 - 1.0).abs() < 0.01, "covered {m0} vs {m1}");
        assert!((x0 - x1).abs() < 0.05 && (y0 - y1).abs() < 0.05, "centroid ({x0}, {y0}) vs ({x1}, {y1})");
        // Scale 1 keeps the view as it is.
        assert_eq!(view_targets(&[GeometryView { name: "v".into(), camera: camera.clone(), target: direct.clone(), normal: None }], 1.0)?[0].camera.width, 100);
        Ok(())
    }

    #[test]
    fn barycentric_recovers_interior_points_and_clamps_outside_ones() {
        let (a, b, c) = (Vec3::new(0.0, 0.0, 1.0), Vec3::new(2.0, 0.0, 1.0), Vec3::new(0.0, 3.0, 1.0));
        let p = a + 0.25 * (b - a) + 0.5 * (c - a);
        let w = barycentric(a, b, c, p);
        assert!((w - Vec2::new(0.25, 0.5)).length() < 1e-6, "{w}");
        // Beyond the edge b–c: clamped onto the triangle.
        let w = barycentric(a, b, c, a + 0.9 * (b - a) + 0.9 * (c - a));
        assert!(w.x >= 0.0 && w.y >= 0.0 && w.x + w.y <= 1.0 + 1e-6, "{w}");
        // A degenerate triangle gives its first corner.
        assert_eq!(barycentric(a, a, a, p), Vec2::ZERO);
    }
}

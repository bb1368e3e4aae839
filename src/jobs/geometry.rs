//! The geometry stage of a run: where the mesh comes from, and what the material pass starts
//! from. Either the scene's ground-truth mesh (NVDiffRecMC's second pass alone), or the shape
//! reconstructed from the training images: the visual hull of the masks
//! (`geometry::hull`), then the geometry pass (`fit::geometry_pass`), whose per-vertex colour
//! becomes the material pass's starting textures.
//!
//! `auto` takes the scene's mesh when its data has one and reconstructs otherwise. The choice and
//! its reason are printed and reported. With reconstruction nothing under the scene's
//! ground-truth folder is read here: only the training images, their masks and cameras.

use std::time::Instant;

use anyhow::{bail, Context, Result};
use glam::Vec3;
use serde::Serialize;

use crate::fit::geometry_pass::{run_geometry_pass, GeometryPassConfig, GeometryStep, GeometryTimings, GeometryView, StageRecord};
use crate::geometry::inward_surface::FOLDED_SHARE;
use crate::geometry::hull::{visual_hull, HullOptions, MaskView};
use crate::eval::geometry_metrics::{geometry_metrics, load_judge_views, view_metrics, GeometryMetricOptions, GeometryMetrics, ViewMetrics};
use crate::geometry::bvh::Bvh;
use crate::geometry::Mesh;
use crate::image::Image;
use crate::prior::source::Prior;
use crate::prior::view_labels::ViewLabels;
use crate::scene::dataset::{mask_pixels, Dataset, MASK_THRESHOLD};
use crate::scene::SceneSpec;
use crate::scene_data::{ground_truth_mesh, ground_truth_source};

/// Where the geometry comes from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum GeometrySource {
    /// The scene's ground-truth mesh (NVDiffRecMC's second pass on known geometry).
    GroundTruth,
    /// Reconstructed from the training images: visual hull, then the geometry pass.
    Reconstruct,
    /// The scene's mesh when its data has one, else reconstructed.
    Auto,
}

impl GeometrySource {
    pub fn tag(self) -> &'static str {
        match self {
            GeometrySource::GroundTruth => "gt",
            GeometrySource::Reconstruct => "reconstruct",
            GeometrySource::Auto => "auto",
        }
    }
}

/// Training views are brought to at most this many pixels on their longer side for the geometry
/// pass: the outline gradient lives on outline pixels (about 4·side of them per view), and 256
/// already puts a pixel at ~1/200 of an object that fills the frame, finer than the hull's mesh.
/// The material pass later trains on the full resolution.
pub const GEOMETRY_MAX_SIDE: usize = 256;

#[derive(Clone, Debug, Serialize, serde::Deserialize)]
pub struct HullRecord {
    pub vertices: usize,
    pub triangles: usize,
    pub voxel_size: f32,
    pub target_edge: f32,
    pub summary: String,
    pub seconds: f64,
}

#[derive(Clone, Debug, Serialize, serde::Deserialize)]
pub struct PassRecord {
    pub config: GeometryPassConfig,
    pub views: usize,
    pub resolution: [usize; 2],
    pub seconds: f64,
    pub timings: GeometryTimings,
    pub history: Vec<GeometryStep>,
    /// The pass's stages (the mesh it refined to before each).
    pub stages: Vec<StageRecord>,
}

/// What the run reports about its geometry.
#[derive(Clone, Debug, Serialize)]
pub struct GeometryReport {
    /// `ground-truth` or `reconstruct` (what was used, after `auto`).
    pub used: GeometrySource,
    pub why: String,
    pub hull: Option<HullRecord>,
    pub pass: Option<PassRecord>,
    /// Scores of the mesh (and of the hull it started from), filled by [`score_geometry`].
    pub scores: Option<GeometryScores>,
}

/// The geometry scores of a run (evaluation only: this is the one place the stage reads the
/// ground truth, and only to score).
#[derive(Clone, Debug, Serialize)]
pub struct GeometryScores {
    /// Silhouette IoU and normal error on the test views (needs no mesh).
    pub test_views: Option<ViewMetrics>,
    /// Against the ground-truth mesh, over what the training views' depth maps can judge.
    pub mesh: Option<GeometryMetrics>,
    pub hull: Option<GeometryMetrics>,
    /// What could not be scored, and why.
    pub not_computed: Vec<String>,
    pub seconds: f64,
}

/// Scores `mesh` (and `hull`) as far as the data allows.
pub fn score_geometry(spec: &SceneSpec, dataset: &Dataset, mesh: &Mesh, bvh: &Bvh, hull: Option<&Mesh>) -> GeometryScores {
    let t = Instant::now();
    let mut not_computed = Vec::new();
    let test_views = if dataset.test.is_empty() {
        not_computed.push("silhouette IoU and normal error: the data has no test views".to_string());
        None
    } else {
        view_metrics(mesh, bvh, &dataset.test).map_err(|e| not_computed.push(format!("silhouette IoU and normal error: {e:#}"))).ok()
    };
    let (mut mesh_scores, mut hull_scores) = (None, None);
    let gt = match ground_truth_source(spec) {
        Ok(Some(_)) => ground_truth_mesh(spec).map_err(|e| format!("{e:#}")),
        Ok(None) => Err("the data has no ground-truth mesh".to_string()),
        Err(e) => Err(format!("{e:#}")),
    };
    let judges = if dataset.train.iter().all(|v| v.has_depth()) {
        load_judge_views(&dataset.train).map_err(|e| format!("{e:#}"))
    } else {
        Err("the training views have no depth maps".to_string())
    };
    match (gt, judges) {
        (Ok(gt), Ok(judges)) => {
            let opts = GeometryMetricOptions::default();
            match geometry_metrics(mesh, &gt, &judges, &opts) {
                Ok(m) => mesh_scores = Some(m),
                Err(e) => not_computed.push(format!("mesh metrics: {e:#}")),
            }
            if let Some(h) = hull {
                hull_scores = geometry_metrics(h, &gt, &judges, &opts).map_err(|e| not_computed.push(format!("hull metrics: {e:#}"))).ok();
            }
        }
        (Err(e), _) | (_, Err(e)) => not_computed.push(format!("Chamfer, F-score and normal consistency: {e}")),
    }
    GeometryScores { test_views, mesh: mesh_scores, hull: hull_scores, not_computed, seconds: t.elapsed().as_secs_f64() }
}

/// The stage's result.
pub struct GeometryOutcome {
    pub mesh: Mesh,
    /// The geometry pass's per-vertex base colour (reconstruction only), for the starting textures.
    pub vertex_kd: Option<Vec<Vec3>>,
    /// The visual hull (reconstruction only), kept for the geometry metrics.
    pub hull: Option<Mesh>,
    pub report: GeometryReport,
}

/// What `source` means for `spec` (`auto` decided), and why.
pub fn resolve_source(spec: &SceneSpec, source: GeometrySource) -> Result<(GeometrySource, String)> {
    Ok(match source {
        GeometrySource::GroundTruth => (GeometrySource::GroundTruth, "set by the run (--geometry gt)".to_string()),
        GeometrySource::Reconstruct => (GeometrySource::Reconstruct, "set by the run (--geometry reconstruct)".to_string()),
        GeometrySource::Auto if ground_truth_source(spec)?.is_some() => {
            (GeometrySource::GroundTruth, "auto: the scene's data has a ground-truth mesh".to_string())
        }
        GeometrySource::Auto => (GeometrySource::Reconstruct, "auto: the scene's data has no mesh, so it is reconstructed from the images".to_string()),
    })
}

/// The labels a reconstruction's geometry pass holds its shading normals to
/// (`GeometryPassConfig::normal_prior`): the run's prior, asked only when the pass runs (a
/// geometry reused from the run folder needs none).
pub struct PassLabels<'a> {
    pub prior: &'a dyn Prior,
    /// The labelled training views, as indices into `dataset.train`.
    pub views: Vec<usize>,
}

impl PassLabels<'_> {
    /// The labels indexed like `dataset.train` (`None` for a view without one).
    fn get(&self, dataset: &Dataset) -> Result<Vec<Option<ViewLabels>>> {
        let mut all = vec![None; dataset.train.len()];
        for (&i, l) in self.views.iter().zip(self.prior.labels(dataset, &self.views).context("labels for the geometry pass's normal prior")?) {
            all[i] = l;
        }
        Ok(all)
    }
}

/// The pass settings a reconstruction runs with: the normal prior only when there are labels
/// (`labelled`) and a weight, so a run without a prior, or with its weight at 0, records (and is
/// identified by) a pass without one.
pub fn pass_settings(pass: &GeometryPassConfig, labelled: bool) -> GeometryPassConfig {
    if labelled && pass.normal_prior > 0.0 {
        pass.clone()
    } else {
        pass.without_normal_prior()
    }
}

/// The geometry of a run on `dataset` from `source`. A reconstruction's pass holds its normals
/// to `labels` when given (and its normal prior's weight is not 0).
pub fn obtain_geometry(spec: &SceneSpec, dataset: &Dataset, source: GeometrySource, pass: &GeometryPassConfig, labels: Option<&PassLabels>, progress: bool) -> Result<GeometryOutcome> {
    let (used, why) = resolve_source(spec, source)?;
    if progress {
        eprintln!("geometry: {} ({why})", if used == GeometrySource::GroundTruth { "the scene's mesh" } else { "reconstructed from the images" });
    }
    if used == GeometrySource::GroundTruth {
        let mesh = ground_truth_mesh(spec)?;
        return Ok(GeometryOutcome { mesh, vertex_kd: None, hull: None, report: GeometryReport { used, why, hull: None, pass: None, scores: None } });
    }
    reconstruct(dataset, pass, labels, progress, why)
}

/// The training views brought to at most [`GEOMETRY_MAX_SIDE`] pixels (box filter over
/// premultiplied colour, like the material pass's downscaling). A view whose mask is empty does not
/// show the object, and its silhouette loss would push the mesh out of the frame: it is left out with
/// a warning (the visual hull skips it too).
fn geometry_views(dataset: &Dataset, labels: Option<&[Option<ViewLabels>]>) -> Result<Vec<GeometryView>> {
    let mut views = Vec::with_capacity(dataset.train.len());
    let mut empty = Vec::new();
    for (k, v) in dataset.train.iter().enumerate() {
        let rgba = v.load_rgba().with_context(|| format!("geometry pass: training view {}", v.name))?;
        if mask_pixels(rgba.data.chunks_exact(4).map(|p| p[3]), MASK_THRESHOLD) == 0 {
            empty.push(v.name.clone());
            continue;
        }
        let side = v.camera.width.max(v.camera.height);
        let s = side.div_ceil(GEOMETRY_MAX_SIDE).max(1);
        let s = if v.camera.width % s == 0 && v.camera.height % s == 0 { s } else { 1 };
        let normal = match labels.and_then(|l| l.get(k)).and_then(Option::as_ref) {
            Some(l) => Some(normal_label(l, rgba.width, rgba.height, v.camera.c2w).with_context(|| format!("geometry pass: the normal label of view {}", v.name))?),
            None => None,
        };
        views.push(if s == 1 {
            GeometryView { name: v.name.clone(), camera: v.camera.clone(), target: rgba, normal }
        } else {
            GeometryView {
                name: v.name.clone(),
                camera: v.camera.resized(v.camera.width / s, v.camera.height / s),
                target: rgba.downsample_straight_alpha(s),
                normal: normal.map(|a| a.downsample_straight_alpha(s)),
            }
        });
    }
    if !empty.is_empty() {
        eprintln!("warning: geometry pass: skipping {} of {} training views whose mask is empty: {}", empty.len(), dataset.train.len(), empty.join(", "));
    }
    if views.is_empty() {
        bail!("geometry pass: every training view's mask is empty ({}); nothing shows the object", empty.join(", "));
    }
    Ok(views)
}

/// A label's normal as the geometry pass takes it: the world-space unit normal with the label's
/// mask as alpha.
fn normal_label(labels: &ViewLabels, width: usize, height: usize, c2w: glam::Mat4) -> Result<Image> {
    let (n, m) = (&labels.normal, &labels.mask);
    anyhow::ensure!(
        n.width == width && n.height == height && m.width == width && m.height == height && n.channels >= 3 && m.channels == 1,
        "normal {}×{}×{} and mask {}×{}×{} for a {width}×{height} view",
        n.width,
        n.height,
        n.channels,
        m.width,
        m.height,
        m.channels
    );
    let c = n.channels;
    let mut out = Image::new(width, height, 4);
    for i in 0..width * height {
        let w = crate::fit::labels::world_normal(glam::Vec3::from_slice(&n.data[c * i..c * i + 3]), c2w);
        let mask = if w == glam::Vec3::ZERO { 0.0 } else { m.data[i] };
        out.data[4 * i..4 * i + 4].copy_from_slice(&[w.x, w.y, w.z, mask]);
    }
    Ok(out)
}

fn reconstruct(dataset: &Dataset, pass: &GeometryPassConfig, labels: Option<&PassLabels>, progress: bool, why: String) -> Result<GeometryOutcome> {
    let pass = &pass_settings(pass, labels.is_some());
    let t = Instant::now();
    let masks: Vec<MaskView> = dataset
        .train
        .iter()
        .map(|v| Ok(MaskView { name: v.name.clone(), camera: v.camera.clone(), alpha: v.load_alpha().with_context(|| format!("mask of view {}", v.name))? }))
        .collect::<Result<_>>()?;
    let hull = visual_hull(&masks, &HullOptions::default()).context("visual hull of the training masks")?;
    let hull_seconds = t.elapsed().as_secs_f64();
    if progress {
        eprintln!("visual hull: {} vertices, {} triangles in {hull_seconds:.1} s ({})", hull.mesh.positions.len(), hull.mesh.triangles.len(), hull.summary);
    }
    let hull_record = HullRecord {
        vertices: hull.mesh.positions.len(),
        triangles: hull.mesh.triangles.len(),
        voxel_size: hull.voxel_size,
        target_edge: hull.target_edge,
        summary: hull.summary.clone(),
        seconds: hull_seconds,
    };

    let t = Instant::now();
    let labels = match labels {
        Some(l) if pass.normal_prior > 0.0 => Some(l.get(dataset)?),
        _ => None,
    };
    let views = geometry_views(dataset, labels.as_deref())?;
    let resolution = [views[0].camera.width, views[0].camera.height];
    let result = run_geometry_pass(&hull.mesh, &views, pass, progress).context("geometry pass")?;
    if let Some(share) = result.stages.last().and_then(|s| s.inward_share_at_end).filter(|&s| s > FOLDED_SHARE) {
        eprintln!(
            "warning: geometry pass: {:.1} % of the reconstructed surface faces into the mesh, which has folded through \
             itself; the fold's surface lies inside the object and can spoil the shading normals near it (docs/geometry.md, \
             *Folds through the surface*)",
            100.0 * share
        );
    }
    let pass_record = PassRecord {
        config: pass.clone(),
        views: views.len(),
        resolution,
        seconds: t.elapsed().as_secs_f64(),
        timings: result.timings.clone(),
        history: result.history.clone(),
        stages: result.stages.clone(),
    };
    Ok(GeometryOutcome {
        mesh: result.mesh,
        vertex_kd: Some(result.vertex_kd),
        hull: Some(hull.mesh),
        report: GeometryReport { used: GeometrySource::Reconstruct, why, hull: Some(hull_record), pass: Some(pass_record), scores: None },
    })
}

/// The scores in a few lines for the terminal and the Markdown report.
pub fn scores_summary(s: &GeometryScores) -> String {
    let mut out = String::from("geometry scores:");
    let row = |name: &str, m: &GeometryMetrics| {
        format!(
            "\n- {name}: Chamfer (visible) {:.4}, F-score@1% {:.3}, normal consistency {:.3} (accuracy {:.4}, completeness {:.4}; distances / GT diagonal)",
            m.chamfer_visible, m.fscore, m.normal_consistency, m.accuracy, m.completeness
        )
    };
    if let Some(m) = &s.hull {
        out.push_str(&row("visual hull", m));
    }
    if let Some(m) = &s.mesh {
        out.push_str(&row("reconstructed mesh", m));
    }
    if let Some(v) = &s.test_views {
        let n = v.normal_error_deg.map_or("-".to_string(), |e| format!("{e:.2}°"));
        out.push_str(&format!("\n- test views: silhouette IoU {:.4}, normal error {n}", v.silhouette_iou));
    }
    for line in &s.not_computed {
        out.push_str(&format!("\n- not computed: {line}"));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::prior::oracle::camera_normals;
    use crate::scene::Camera;

    /// The pass's normal label is the world normal the label encodes in camera space, with the
    /// label's mask; a pixel without a normal gets no weight, and a label of another size is
    /// refused.
    #[test]
    fn a_normal_label_reads_back_as_the_world_normal_it_encodes() -> Result<()> {
        let camera = Camera::look_at(Vec3::new(2.0, -3.0, 1.5), Vec3::ZERO, Vec3::Z, 0.8, 3, 2);
        let world = [Vec3::X, Vec3::new(0.3, -0.8, 0.5).normalize(), Vec3::ZERO, -Vec3::Z, Vec3::new(-0.6, 0.0, 0.8), Vec3::Y];
        let mut normals = Image::new(3, 2, 3);
        for (i, n) in world.iter().enumerate() {
            normals.set_rgb(i, *n);
        }
        let mask = Image { data: vec![1.0, 0.5, 1.0, 1.0, 0.0, 1.0], ..Image::new(3, 2, 1) };
        let labels = ViewLabels { albedo: Image::new(3, 2, 3), normal: camera_normals(&normals, camera.c2w), metallic: Image::new(3, 2, 1), roughness: Image::new(3, 2, 1), mask: mask.clone() };
        let label = normal_label(&labels, 3, 2, camera.c2w)?;
        for (i, n) in world.iter().enumerate() {
            let px = &label.data[4 * i..4 * i + 4];
            assert!(Vec3::from_slice(&px[..3]).distance(*n) < 1e-5, "pixel {i}: {px:?} for {n}");
            let weight = if *n == Vec3::ZERO { 0.0 } else { mask.data[i] };
            assert_eq!(px[3], weight, "pixel {i}");
        }
        let err = normal_label(&labels, 4, 2, camera.c2w).expect_err("another size").to_string();
        assert!(err.contains("normal 3×2×3") && err.contains("4×2 view"), "{err}");
        Ok(())
    }
}

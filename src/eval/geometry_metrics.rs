//! Geometry metrics: how close a reconstructed mesh is to the ground truth, scored only where the
//! training cameras can tell (docs/geometry.md, "Geometry metrics"). What no camera sees, such as
//! the underside of a plate, is closed by guesswork in any reconstruction and is left out on both
//! sides:
//! - **accuracy**: mean distance from the reconstruction's surface to the ground-truth mesh, over
//!   the reconstructed points some training view can judge (outside its mask, or inside and not
//!   behind its depth map);
//! - **completeness**: mean distance from the *visible* ground truth (points back-projected from the
//!   training views' depth maps, away from depth discontinuities) to the reconstruction;
//! - precision / recall / F-score at a distance threshold, "Chamfer (visible)" (the mean of accuracy
//!   and completeness) and normal consistency.
//!
//! Every distance is an exact point-to-triangle distance ([`SurfaceQuery`]) divided by the
//! ground-truth bounding-box diagonal. [`view_metrics`] adds what needs no ground-truth mesh:
//! silhouette IoU and normal angular error on the dataset's views.

use anyhow::{bail, Context, Result};
use glam::Vec3;
use rand::SeedableRng;
use rand_pcg::Pcg32;
use rayon::prelude::*;
use serde::Serialize;

use crate::eval::metrics::{mask_from_alpha, mask_iou, mean_angular_error_deg};
use crate::geometry::bvh::Bvh;
use crate::geometry::closest_point::SurfaceQuery;
use crate::geometry::surface_samples::sample_surface;
use crate::geometry::Mesh;
use crate::image::Image;
use crate::render::gbuffer::GBuffer;
use crate::scene::dataset::View;
use crate::scene::camera::Projector;
use crate::scene::Camera;

/// A pixel is inside the silhouette when the object covers more than half of it: the symmetric
/// choice, so an exact outline neither grows nor shrinks the mask.
pub const MASK_THRESHOLD: f32 = 0.5;

/// A training view as the judge of geometry: its camera, planar depth along the view axis
/// (1 channel, 0 on the background, like the dataset's `depth.exr`) and coverage (1 channel).
#[derive(Clone, Debug)]
pub struct JudgeView {
    pub name: String,
    pub camera: Camera,
    pub depth: Image,
    pub alpha: Image,
    projector: Projector,
}

impl JudgeView {
    /// Checks that depth and alpha are single-channel images of the camera's size.
    pub fn new(name: String, camera: Camera, depth: Image, alpha: Image) -> Result<JudgeView> {
        for (what, img) in [("depth map", &depth), ("alpha", &alpha)] {
            if img.channels != 1 || (img.width, img.height) != (camera.width, camera.height) {
                bail!(
                    "view {name}: the {what} is {}×{} with {} channel(s), expected {}×{} with 1",
                    img.width,
                    img.height,
                    img.channels,
                    camera.width,
                    camera.height
                );
            }
        }
        Ok(JudgeView { name, projector: camera.projector(), camera, depth, alpha })
    }

    /// A dataset view's `depth.exr` and alpha.
    pub fn load(view: &View) -> Result<JudgeView> {
        let depth = view
            .load_depth()
            .with_context(|| format!("the geometry metrics need the depth map of view {}", view.name))?;
        JudgeView::new(view.name.clone(), view.camera.clone(), depth, view.load_alpha()?)
    }

    /// Whether this view can judge a point at `p`: it lies in front of the camera, inside the
    /// frame, and either outside the mask (the view sees nothing there) or inside it and not
    /// behind the depth map by more than `tolerance` (the view sees the point or what is in front
    /// of it within `tolerance`). The pixel is the one the point falls in (no interpolation).
    pub fn judges(&self, p: Vec3, tolerance: f32) -> bool {
        let (xy, z) = self.projector.project(p);
        let (w, h) = (self.camera.width, self.camera.height);
        if !(z > 0.0 && xy.x >= 0.0 && xy.y >= 0.0 && xy.x < w as f32 && xy.y < h as f32) {
            return false;
        }
        let i = xy.y as usize * w + xy.x as usize;
        if self.alpha.data[i] <= MASK_THRESHOLD {
            return true;
        }
        let d = self.depth.data[i];
        d > 0.0 && z <= d + tolerance
    }

    /// Whether pixel `i` shows a surface: inside the mask with a positive, finite depth.
    fn has_surface(&self, i: usize) -> bool {
        let d = self.depth.data[i];
        self.alpha.data[i] > MASK_THRESHOLD && d > 0.0 && d.is_finite()
    }

    /// The pixels whose depth is a point of the surface: they show a surface, and no 4-neighbour
    /// that shows one differs in depth by more than `tolerance`. A pixel across an occluding
    /// outline may hold the depth of either side while its centre's ray meets the other, so its
    /// back-projected point floats off every surface; such pixels are left out. Returns the kept
    /// pixels and how many surface pixels were left out.
    fn surface_pixels(&self, tolerance: f32) -> (Vec<usize>, usize) {
        let (w, h) = (self.camera.width, self.camera.height);
        let (mut kept, mut dropped) = (Vec::new(), 0);
        for i in (0..w * h).filter(|&i| self.has_surface(i)) {
            let (x, y) = (i % w, i / w);
            let neighbours = [(x > 0).then(|| i - 1), (x + 1 < w).then(|| i + 1), (y > 0).then(|| i - w), (y + 1 < h).then(|| i + w)];
            let d = self.depth.data[i];
            if neighbours.into_iter().flatten().any(|j| self.has_surface(j) && (self.depth.data[j] - d).abs() > tolerance) {
                dropped += 1;
            } else {
                kept.push(i);
            }
        }
        (kept, dropped)
    }

    /// The world point seen at pixel `i`: along the pixel centre's ray, at its planar depth.
    fn back_project(&self, i: usize) -> Vec3 {
        let (x, y) = (i % self.camera.width, i / self.camera.width);
        let dir = self.camera.ray_dir(x as f32 + 0.5, y as f32 + 0.5);
        self.camera.origin() + dir * (self.depth.data[i] / dir.dot(self.camera.forward()))
    }
}

/// The judges for a list of dataset views (normally the training views), loaded in parallel.
/// Fails, naming the view, when one has no depth map.
pub fn load_judge_views(views: &[View]) -> Result<Vec<JudgeView>> {
    views.par_iter().map(JudgeView::load).collect()
}

#[derive(Clone, Debug)]
pub struct GeometryMetricOptions {
    /// Area-weighted samples of the reconstructed surface (accuracy, precision, normal consistency).
    pub recon_samples: usize,
    /// Back-projected depth pixels drawn from all training views (completeness, recall).
    pub visible_gt_samples: usize,
    /// The F-score distance, as a fraction of the ground-truth diagonal; a point at exactly this
    /// distance counts as within.
    pub threshold: f64,
    /// How far behind a view's depth map a point may lie and still be judged by it, and the largest
    /// depth step between neighbouring pixels of a visible ground-truth point, as a fraction of the
    /// ground-truth diagonal.
    pub depth_tolerance: f64,
    pub seed: u64,
}

impl Default for GeometryMetricOptions {
    /// 100 000 points on each side: the standard error of a share (precision, recall) is at most
    /// 0.5/√n = 0.0016, below the two decimals reported, and a query costs microseconds, so both
    /// sides take about a second. 1 % of the diagonal for both distances (issue 11's protocol):
    /// a few pixels at the datasets' resolution, above depth-map and tessellation noise.
    fn default() -> Self {
        GeometryMetricOptions { recon_samples: 100_000, visible_gt_samples: 100_000, threshold: 0.01, depth_tolerance: 0.01, seed: 0 }
    }
}

/// The scores of one reconstruction; distances are fractions of the ground-truth diagonal.
#[derive(Clone, Debug, Serialize)]
pub struct GeometryMetrics {
    /// Mean distance of the judged reconstructed points to the ground-truth mesh.
    pub accuracy: f64,
    /// Mean distance of the visible ground-truth points to the reconstruction.
    pub completeness: f64,
    /// (accuracy + completeness) / 2.
    pub chamfer_visible: f64,
    /// Harmonic mean of precision and recall (0 when both are 0).
    pub fscore: f64,
    /// Share of the judged reconstructed points within `threshold` of the ground truth.
    pub precision: f64,
    /// Share of the visible ground-truth points within `threshold` of the reconstruction.
    pub recall: f64,
    /// Mean |cos| between a judged point's face normal and that of its closest ground-truth point.
    pub normal_consistency: f64,
    pub threshold: f64,
    pub depth_tolerance: f64,
    /// The ground-truth bounding-box diagonal, in world units.
    pub diagonal: f64,
    /// Reconstructed surface samples drawn, and how many of them some view judges.
    pub recon_points: usize,
    pub scored_points: usize,
    /// Pixels with a surface point over all views, and how many were drawn for completeness.
    pub visible_gt_pixels: usize,
    /// Pixels inside the masks left out because they straddle a depth discontinuity.
    pub outline_pixels: usize,
    pub visible_gt_points: usize,
    pub views: usize,
}

/// Share of `distances` at most `limit`.
fn share_within(distances: &[f64], limit: f64) -> f64 {
    distances.iter().filter(|&&d| d <= limit).count() as f64 / distances.len() as f64
}

fn mean(values: &[f64]) -> f64 {
    values.iter().sum::<f64>() / values.len() as f64
}

/// Score `recon` against `gt` as seen by `views` (the training views). See the module comment.
pub fn geometry_metrics(recon: &Mesh, gt: &Mesh, views: &[JudgeView], opts: &GeometryMetricOptions) -> Result<GeometryMetrics> {
    if views.is_empty() {
        bail!("the geometry metrics need at least one training view with a depth map");
    }
    let (lo, hi) = gt.bounds().context("the ground-truth mesh has no vertices")?;
    let diagonal = (hi - lo).as_dvec3().length();
    if !(diagonal > 0.0 && diagonal.is_finite()) {
        bail!("the ground-truth mesh's bounding box has diagonal {diagonal}: nothing to normalise distances by");
    }
    let gt_query = SurfaceQuery::new(gt).context("the ground-truth mesh")?;
    let recon_query = SurfaceQuery::new(recon).context("the reconstructed mesh")?;
    let tolerance = (opts.depth_tolerance * diagonal) as f32;

    // Accuracy side: judged reconstructed points against the ground-truth mesh.
    let samples = sample_surface(recon, opts.recon_samples, opts.seed).context("the reconstructed mesh")?;
    let judged: Vec<(f64, f64)> = samples
        .par_iter()
        .filter(|s| views.iter().any(|v| v.judges(s.position, tolerance)))
        .filter_map(|s| {
            let c = gt_query.closest(s.position)?;
            let n_recon = recon.face_normal_scaled(s.triangle as usize).normalize();
            let n_gt = gt.face_normal_scaled(c.triangle as usize).normalize();
            Some((c.distance as f64 / diagonal, n_recon.dot(n_gt).abs() as f64))
        })
        .collect();
    if judged.is_empty() {
        bail!(
            "none of the {} points sampled on the reconstruction is judged by any of the {} training views \
             (each lies behind every view's depth map, or outside every frame)",
            samples.len(),
            views.len()
        );
    }
    let (acc_d, cosines): (Vec<f64>, Vec<f64>) = judged.into_iter().unzip();

    // Completeness side: a seeded draw of the depth pixels of all views, back-projected.
    let per_view: Vec<(Vec<usize>, usize)> = views.par_iter().map(|v| v.surface_pixels(tolerance)).collect();
    let outline_pixels = per_view.iter().map(|(_, dropped)| dropped).sum();
    let pixels: Vec<(u32, u32)> =
        per_view.iter().enumerate().flat_map(|(k, (kept, _))| kept.iter().map(move |&i| (k as u32, i as u32))).collect();
    if pixels.is_empty() {
        bail!("the {} training views' depth maps show no surface inside their masks", views.len());
    }
    let mut rng = Pcg32::seed_from_u64(opts.seed ^ 0x9e37_79b9_7f4a_7c15);
    let drawn = rand::seq::index::sample(&mut rng, pixels.len(), opts.visible_gt_samples.min(pixels.len())).into_vec();
    let comp_d: Vec<f64> = drawn
        .par_iter()
        .filter_map(|&j| {
            let (k, i) = pixels[j];
            recon_query.closest(views[k as usize].back_project(i as usize)).map(|c| c.distance as f64 / diagonal)
        })
        .collect();
    if comp_d.is_empty() {
        bail!("no back-projected depth pixel is a finite point (check the cameras and depth maps)");
    }

    let (accuracy, completeness) = (mean(&acc_d), mean(&comp_d));
    let (precision, recall) = (share_within(&acc_d, opts.threshold), share_within(&comp_d, opts.threshold));
    let fscore = if precision + recall > 0.0 { 2.0 * precision * recall / (precision + recall) } else { 0.0 };
    Ok(GeometryMetrics {
        accuracy,
        completeness,
        chamfer_visible: 0.5 * (accuracy + completeness),
        fscore,
        precision,
        recall,
        normal_consistency: mean(&cosines),
        threshold: opts.threshold,
        depth_tolerance: opts.depth_tolerance,
        diagonal,
        recon_points: samples.len(),
        scored_points: acc_d.len(),
        visible_gt_pixels: pixels.len(),
        outline_pixels,
        visible_gt_points: comp_d.len(),
        views: views.len(),
    })
}

/// Silhouette and normal scores of one view.
#[derive(Clone, Debug, Serialize)]
pub struct ViewScore {
    pub view: String,
    /// IoU of the reconstruction's coverage (one ray per pixel centre) and the dataset's alpha > 0.5.
    pub silhouette_iou: f64,
    /// Mean angle between the reconstruction's shading normal and `normal.png` over the pixels both
    /// cover (None when the view has no normal map or no such pixel).
    pub normal_error_deg: Option<f64>,
}

/// [`ViewScore`]s and their means over the views.
#[derive(Clone, Debug, Serialize)]
pub struct ViewMetrics {
    pub silhouette_iou: f64,
    /// Mean over the views that have a score (None when none has).
    pub normal_error_deg: Option<f64>,
    pub per_view: Vec<ViewScore>,
}

/// One view's scores from the reconstruction's G-buffer, the dataset's alpha (1 channel) and its
/// decoded world-space normal map, if any.
fn score_view(name: &str, g: &GBuffer, alpha: &Image, normal: Option<&Image>) -> ViewScore {
    let covered = g.mask();
    let inside = mask_from_alpha(alpha, MASK_THRESHOLD);
    let normal_error_deg = normal.and_then(|gt| {
        let both: Vec<bool> = covered.iter().zip(&inside).map(|(a, b)| *a && *b).collect();
        Some(mean_angular_error_deg(&g.normal_image(), gt, Some(&both))).filter(|e| e.is_finite())
    });
    ViewScore { view: name.to_owned(), silhouette_iou: mask_iou(&covered, &inside), normal_error_deg }
}

/// Scores that need no ground-truth mesh, only the dataset's pictures: on each of `views` (the test
/// views), the silhouette IoU and the normal angular error of `recon` (traced through `bvh`).
pub fn view_metrics(recon: &Mesh, bvh: &Bvh, views: &[View]) -> Result<ViewMetrics> {
    if views.is_empty() {
        bail!("the view metrics need at least one view");
    }
    let mut per_view = Vec::with_capacity(views.len());
    for view in views {
        let g = GBuffer::trace(recon, bvh, &view.camera);
        let normal = view.has_normal().then(|| view.load_normal()).transpose()?;
        per_view.push(score_view(&view.name, &g, &view.load_alpha()?, normal.as_ref()));
    }
    let ious: Vec<f64> = per_view.iter().map(|s| s.silhouette_iou).collect();
    let normals: Vec<f64> = per_view.iter().filter_map(|s| s.normal_error_deg).collect();
    Ok(ViewMetrics {
        silhouette_iou: mean(&ious),
        normal_error_deg: (!normals.is_empty()).then(|| mean(&normals)),
        per_view,
    })
}

#[cfg(test)]
mod tests {
    use glam::{Mat4, Vec2};

    use super::*;

    /// The axis-aligned cube [−h, h]³ as 12 triangles.
    fn cube(h: f32) -> Mesh {
        let corner = |i: usize| Vec3::new(if i & 1 == 0 { -h } else { h }, if i & 2 == 0 { -h } else { h }, if i & 4 == 0 { -h } else { h });
        let mut m = Mesh {
            positions: (0..8).map(corner).collect(),
            triangles: vec![
                [0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6], // z = −h, z = +h
                [0, 1, 4], [1, 5, 4], [2, 6, 3], [3, 6, 7], // y = −h, y = +h
                [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5], // x = −h, x = +h
            ],
            uvs: vec![Vec2::ZERO; 8],
            ..Default::default()
        };
        m.recompute_normals();
        m
    }

    /// Six frontal views of a cube at the origin, from 4 units along ±x, ±y, ±z, rendered by the
    /// project's tracer (depth and coverage as the dataset stores them).
    fn frontal_views(gt: &Mesh) -> Vec<JudgeView> {
        let bvh = Bvh::build(gt);
        let axes = [Vec3::X, -Vec3::X, Vec3::Y, -Vec3::Y, Vec3::Z, -Vec3::Z];
        axes.iter()
            .enumerate()
            .map(|(k, &a)| {
                let up = if a.z != 0.0 { Vec3::Y } else { Vec3::Z };
                let cam = Camera::look_at(4.0 * a, Vec3::ZERO, up, 0.6, 40, 40);
                let g = GBuffer::trace(gt, &bvh, &cam);
                JudgeView::new(format!("v{k}"), cam, g.depth_image(), g.coverage_image()).unwrap()
            })
            .collect()
    }

    fn opts(n: usize) -> GeometryMetricOptions {
        GeometryMetricOptions { recon_samples: n, visible_gt_samples: n, ..Default::default() }
    }

    #[test]
    fn a_cube_against_itself_scores_perfectly() {
        let gt = cube(0.5);
        let m = geometry_metrics(&gt, &gt, &frontal_views(&gt), &opts(5_000)).unwrap();
        assert!((m.diagonal - 3f64.sqrt()).abs() < 1e-6);
        // Frontal views judge every point of the face they look at.
        assert_eq!(m.scored_points, m.recon_points);
        // A frontal view's depth is flat inside the face: no pixel straddles a discontinuity.
        assert_eq!(m.outline_pixels, 0);
        assert!(m.accuracy < 1e-6 && m.completeness < 1e-6 && m.chamfer_visible < 1e-6, "{m:?}");
        assert!(m.fscore == 1.0 && m.precision == 1.0 && m.recall == 1.0, "{m:?}");
        assert!(m.normal_consistency > 0.9999, "{m:?}");
    }

    #[test]
    fn a_cube_against_a_cube_scaled_by_1_02() {
        // Ground truth [−½, ½]³, reconstruction [−0.51, 0.51]³ (a = 0.01), diagonal √3.
        // Completeness: a ground-truth point on a face is inside the larger cube, a from its surface.
        // Accuracy, per face of side 1 + 2a: the centre square (area 1) is a from the ground truth;
        // four strips (a × 1) are √(a² + u²) away (u uniform in [0, a]: mean a·c1 with
        // c1 = (√2 + asinh 1)/2); four corner squares (a × a) are √(a² + u² + v²) away (mean a·c2,
        // c2 = ∫∫ √(1 + s² + t²) over the unit square = 1.28079 by quadrature).
        // Precision at r₀ = 1.05a: the centre square, the strip parts with u ≤ r = √(r₀² − a²)
        // (area 4r) and four quarter discs of radius r (area πr²) are within r₀.
        let (gt, recon) = (cube(0.5), cube(0.51));
        let a = 0.01f64;
        let c1 = (2f64.sqrt() + 1f64.asinh()) / 2.0;
        let c2 = 1.28079;
        let face = (1.0 + 2.0 * a).powi(2);
        let want_accuracy = (a + 4.0 * a * (a * c1) + 4.0 * a * a * (a * c2)) / face / 3f64.sqrt();
        let want_completeness = a / 3f64.sqrt();
        let r = ((1.05 * a).powi(2) - a * a).sqrt();
        let want_precision = (1.0 + 4.0 * r + std::f64::consts::PI * r * r) / face;

        let n = 40_000;
        let o = GeometryMetricOptions { threshold: 1.05 * a / 3f64.sqrt(), ..opts(n) };
        let m = geometry_metrics(&recon, &gt, &frontal_views(&gt), &o).unwrap();
        assert_eq!(m.scored_points, n);
        // Distances range over [a, √3·a]; their sample mean is within 0.1 % of the expectation.
        assert!((m.accuracy / want_accuracy - 1.0).abs() < 1e-3, "accuracy {} want {want_accuracy}", m.accuracy);
        assert!((m.completeness / want_completeness - 1.0).abs() < 1e-4, "completeness {} want {want_completeness}", m.completeness);
        assert!((m.chamfer_visible - 0.5 * (want_accuracy + want_completeness)).abs() < 1e-5);
        // Binomial standard deviation √(p(1 − p)/n) ≈ 0.0008; allow 5σ.
        assert!((m.precision - want_precision).abs() < 0.004, "precision {} want {want_precision}", m.precision);
        assert_eq!(m.recall, 1.0);
        assert!((m.fscore - 2.0 * m.precision / (m.precision + 1.0)).abs() < 1e-12);
        // A point in a strip may be nearest to a ground-truth edge, whose triangle is either
        // neighbour (|cos| 1 or 0): the strips' share of the area bounds the loss.
        assert!(m.normal_consistency > 1.0 / face - 1e-9 && m.normal_consistency <= 1.0, "{m:?}");

        // Below and above the default 1 % threshold (√3·a is the largest distance, at the corners).
        let m = geometry_metrics(&recon, &gt, &frontal_views(&gt), &GeometryMetricOptions { threshold: 0.99 * a / 3f64.sqrt(), ..opts(2_000) }).unwrap();
        assert!(m.precision == 0.0 && m.recall == 0.0 && m.fscore == 0.0, "{m:?}");
        let m = geometry_metrics(&recon, &gt, &frontal_views(&gt), &GeometryMetricOptions { threshold: 1.01 * a, ..opts(2_000) }).unwrap();
        assert!(m.precision == 1.0 && m.recall == 1.0 && m.fscore == 1.0, "{m:?}");
    }

    #[test]
    fn the_threshold_is_inclusive() {
        let d = [0.01, 0.01 + 1e-12, 0.0, 0.02];
        assert_eq!(share_within(&d, 0.01), 0.5);
        assert_eq!(share_within(&d, 0.02), 1.0);
        assert_eq!(share_within(&d, -1.0), 0.0);
    }

    #[test]
    fn points_behind_the_depth_map_are_not_judged() {
        // Looking down −z from (0, 0, 4) at the plane z = 0 (planar depth 4); the left column is
        // outside the mask.
        let cam = Camera { c2w: Mat4::from_translation(Vec3::new(0.0, 0.0, 4.0)), fov_x: 90f32.to_radians(), width: 8, height: 8 };
        let mut alpha = Image::filled(8, 8, &[1.0]);
        for y in 0..8 {
            alpha.data[y * 8] = 0.0;
        }
        let view = JudgeView::new("plane".into(), cam, Image::filled(8, 8, &[4.0]), alpha).unwrap();
        let tol = 0.1;
        assert!(view.judges(Vec3::new(0.3, 0.2, 0.0), tol), "on the visible surface");
        assert!(view.judges(Vec3::new(0.3, 0.2, 1.0), tol), "in front of it");
        assert!(view.judges(Vec3::new(0.3, 0.2, -0.09), tol), "behind it within the tolerance");
        assert!(!view.judges(Vec3::new(0.3, 0.2, -0.11), tol), "behind it by more than the tolerance");
        // Column 0 spans x/depth in [−1, −0.75]: a point there is outside the mask, judged at any depth.
        assert!(view.judges(Vec3::new(-3.5, 0.0, -0.5), tol), "outside the mask");
        assert!(!view.judges(Vec3::new(9.0, 0.0, 0.0), tol), "outside the frame");
        assert!(!view.judges(Vec3::new(0.0, 0.0, 5.0), tol), "behind the camera");

        // In the pipeline: a small cube hidden inside the ground-truth cube is never scored, so the
        // reconstruction "cube + hidden cube" keeps a perfect accuracy on the points that count.
        let gt = cube(0.5);
        let mut recon = cube(0.5);
        recon.append(cube(0.2));
        let n = 4_000;
        let m = geometry_metrics(&recon, &gt, &frontal_views(&gt), &opts(n)).unwrap();
        let outer = sample_surface(&recon, n, 0).unwrap().iter().filter(|s| s.triangle < 12).count();
        assert_eq!(m.scored_points, outer, "{m:?}");
        assert!(m.scored_points < n && m.accuracy < 1e-6 && m.precision == 1.0, "{m:?}");
    }

    #[test]
    fn pixels_across_a_depth_step_are_not_ground_truth() {
        // 4×2 pixels, depth 2.0 2.1 5.0 –  /  2.0 2.1 5.0 5.1, the top-right pixel outside the mask.
        // With tolerance 0.5: the pixels on either side of the step 2.1 → 5.0 are left out; the slope
        // 2.0 → 2.1 is kept; the bottom-right pixel borders only the mask's outline and is kept.
        let cam = Camera { c2w: Mat4::IDENTITY, fov_x: 1.0, width: 4, height: 2 };
        let depth = Image { width: 4, height: 2, channels: 1, data: vec![2.0, 2.1, 5.0, 0.0, 2.0, 2.1, 5.0, 5.1] };
        let mut alpha = Image::filled(4, 2, &[1.0]);
        alpha.data[3] = 0.0;
        let view = JudgeView::new("step".into(), cam, depth, alpha).unwrap();
        let (kept, dropped) = view.surface_pixels(0.5);
        assert_eq!((kept, dropped), (vec![0, 4, 7], 4));
    }

    #[test]
    fn view_scores_of_a_known_square() {
        // The square [−1, 1]² at z = 0 seen from (0, 0, 4) with a 90° field of view over 8×8 pixels:
        // one pixel spans one unit at depth 4, so the square covers the 2×2 pixels around the
        // centre (columns and rows 3-4), with normal +z.
        let mut square = Mesh {
            positions: vec![Vec3::new(-1.0, -1.0, 0.0), Vec3::new(1.0, -1.0, 0.0), Vec3::new(1.0, 1.0, 0.0), Vec3::new(-1.0, 1.0, 0.0)],
            triangles: vec![[0, 1, 2], [0, 2, 3]],
            uvs: vec![Vec2::ZERO; 4],
            ..Default::default()
        };
        square.recompute_normals();
        let cam = Camera { c2w: Mat4::from_translation(Vec3::new(0.0, 0.0, 4.0)), fov_x: 90f32.to_radians(), width: 8, height: 8 };
        let g = GBuffer::trace(&square, &Bvh::build(&square), &cam);
        // The dataset's mask covers columns 3-6 of rows 3-4: 4 pixels in both, 8 in either.
        let mut alpha = Image::new(8, 8, 1);
        let mut normal = Image::new(8, 8, 4);
        for y in 3..5 {
            for x in 3..7 {
                alpha.data[y * 8 + x] = 1.0;
                // Ground-truth normal +z in column 3, +x elsewhere: of the 4 shared pixels, 2 agree
                // and 2 are 90° off, a mean of 45°.
                let n = if x == 3 { [0.0, 0.0, 1.0, 1.0] } else { [1.0, 0.0, 0.0, 1.0] };
                normal.data[4 * (y * 8 + x)..4 * (y * 8 + x) + 4].copy_from_slice(&n);
            }
        }
        let s = score_view("square", &g, &alpha, Some(&normal));
        assert_eq!(s.silhouette_iou, 0.5);
        assert!((s.normal_error_deg.unwrap() - 45.0).abs() < 1e-3, "{s:?}");
        let s = score_view("square", &g, &alpha, None);
        assert_eq!(s.normal_error_deg, None);
        // No pixel in common: IoU 0 and no normal score.
        let s = score_view("square", &g, &Image::new(8, 8, 1), Some(&normal));
        assert!(s.silhouette_iou == 0.0 && s.normal_error_deg.is_none(), "{s:?}");
    }

    #[test]
    fn bad_views_are_named() {
        let cam = Camera::look_at(Vec3::Z * 4.0, Vec3::ZERO, Vec3::Y, 0.6, 8, 8);
        let err = JudgeView::new("train_007".into(), cam, Image::new(8, 4, 1), Image::new(8, 8, 1)).unwrap_err().to_string();
        assert!(err.contains("train_007") && err.contains("depth map"), "{err}");
        let gt = cube(0.5);
        assert!(geometry_metrics(&gt, &gt, &[], &opts(10)).is_err());
    }
}

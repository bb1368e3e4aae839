//! The hotdog's ground-truth mesh scored against itself through the training views' depth maps:
//! what is left is depth-map and sampling noise, so every score must be near perfect; prints the
//! numbers and the time. Ignored in the suite (it reads 100 depth maps and 100 alphas):
//! `cargo test --release --test geometry_metrics_hotdog -- --ignored --nocapture`.

mod common;

use std::time::Instant;

use reconstruct::eval::geometry_metrics::{geometry_metrics, load_judge_views, view_metrics, GeometryMetricOptions};
use reconstruct::geometry::bvh::Bvh;
use reconstruct::geometry::ground_truth::load_ground_truth;
use reconstruct::scene::Dataset;

#[test]
#[ignore = "reads the shared hotdog (100 depth maps); run with --ignored --nocapture"]
fn hotdog_ground_truth_against_itself() {
    let Some(shared) = common::shared_data::require("geometry_metrics_hotdog::hotdog_ground_truth_against_itself (ignored by default)") else { return };
    let root = shared.join("data/nerfactor/hotdog_2163");
    let t = Instant::now();
    let dataset = Dataset::load(&root).unwrap();
    let gt = load_ground_truth(root.join("gt")).unwrap();
    let views = load_judge_views(&dataset.train).unwrap();
    println!("load: {} training views, {} triangles in {:.2} s", views.len(), gt.triangles.len(), t.elapsed().as_secs_f64());

    let t = Instant::now();
    let m = geometry_metrics(&gt, &gt, &views, &GeometryMetricOptions::default()).unwrap();
    let metrics_time = t.elapsed().as_secs_f64();
    println!("{}", serde_json::to_string_pretty(&m).unwrap());
    println!(
        "geometry metrics in {metrics_time:.2} s: Chamfer (visible) {:.5}, F-score@1% {:.4}, normal consistency {:.4} \
         (accuracy {:.6}, completeness {:.6}, {} of {} points judged)",
        m.chamfer_visible, m.fscore, m.normal_consistency, m.accuracy, m.completeness, m.scored_points, m.recon_points
    );

    // Every vertex moved outward along its normal by 0.5 % of the diagonal: the surface moves by
    // about that much (less where vertex normals average across a crease), well within the 1 %
    // threshold, so the distances land near 0.005 and the shares near 1.
    let offset = 0.005 * m.diagonal as f32;
    let mut moved = gt.clone();
    for (p, n) in moved.positions.iter_mut().zip(&gt.normals) {
        *p += offset * *n;
    }
    let t = Instant::now();
    let d = geometry_metrics(&moved, &gt, &views, &GeometryMetricOptions::default()).unwrap();
    println!(
        "displaced by 0.5 % in {:.2} s: Chamfer (visible) {:.5}, F-score@1% {:.4}, normal consistency {:.4} \
         (accuracy {:.5}, completeness {:.5}, {} of {} points judged)",
        t.elapsed().as_secs_f64(),
        d.chamfer_visible, d.fscore, d.normal_consistency, d.accuracy, d.completeness, d.scored_points, d.recon_points
    );

    let t = Instant::now();
    let bvh = Bvh::build(&gt);
    let v = view_metrics(&gt, &bvh, &dataset.test).unwrap();
    println!(
        "view metrics on {} test views in {:.2} s: silhouette IoU {:.4}, normal error {:.2}°",
        v.per_view.len(),
        t.elapsed().as_secs_f64(),
        v.silhouette_iou,
        v.normal_error_deg.unwrap_or(f64::NAN)
    );

    // The mesh against itself: a judged point lies on the mesh (distance at rounding level); the
    // depth maps were rendered from this mesh, so their points lie on it up to their precision.
    assert!(m.accuracy < 1e-5, "{m:?}");
    assert!(m.completeness < 1e-3 && m.recall > 0.99 && m.fscore > 0.99, "{m:?}");
    assert!(m.normal_consistency > 0.99, "{m:?}");
    // Most of the surface is seen by some view; the plate's underside and hidden parts are not.
    assert!(m.scored_points as f64 > 0.5 * m.recon_points as f64, "{m:?}");
    assert!(d.accuracy > 0.0025 && d.accuracy < 0.006 && d.completeness > 0.0025 && d.completeness < 0.006, "{d:?}");
    assert!(d.fscore > 0.9, "{d:?}");
    // The traced silhouette is the dataset's alpha up to antialiasing along the outline.
    assert!(v.silhouette_iou > 0.97, "{v:?}");
}

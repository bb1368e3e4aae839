//! The geometry pass on inputs that break naive mesh optimisers: a start mesh with collapsed
//! triangles, one with a vertex pushed through the opposite surface, views where the object
//! leaves the frame, and a step so large that the mesh cannot stay valid. Losses and gradients
//! stay finite, the mesh that comes out is finite, closed and free of triangles the pass itself
//! flipped or collapsed, and a mesh that cannot be kept valid stops with an error naming the
//! iteration.

use glam::Vec3;
use reconstruct::fit::geometry_pass::{render_sh, run_geometry_pass, GeometryPassConfig, GeometryPassResult, GeometryView};
use reconstruct::geometry::icosphere::icosphere;
use reconstruct::geometry::manifold::check_closed_manifold;
use reconstruct::geometry::Mesh;
use reconstruct::render::sh_light::constant_light;
use reconstruct::scene::Camera;

/// 12 views of a sphere of radius 0.8 at distance `distance` (closer than about 2.4 crops it at
/// fov 0.7), rendered by the pass's own image model.
fn sphere_views(distance: f32, size: usize) -> Vec<GeometryView> {
    let truth = icosphere(Vec3::ZERO, 0.8, 4);
    let kd = vec![Vec3::new(0.6, 0.5, 0.4); truth.positions.len()];
    let mut light = constant_light(0.6);
    light[2 * 3] = 0.4;
    (0..12)
        .map(|i| {
            let a = i as f32 * 2.399_963;
            let z = 1.0 - 2.0 * (i as f32 + 0.5) / 12.0;
            let r = (1.0 - z * z).sqrt();
            let eye = distance * Vec3::new(r * a.cos(), r * a.sin(), z);
            let up = if z.abs() > 0.9 { Vec3::X } else { Vec3::Z };
            let camera = Camera::look_at(eye, Vec3::ZERO, up, 0.7, size, size);
            let target = render_sh(&truth, &kd, &light, &camera, 2).unwrap();
            GeometryView { name: format!("view {i}"), camera, target, normal: None }
        })
        .collect()
}

/// Short single-stage runs: the cases are about validity, not convergence.
fn config(iterations: usize) -> GeometryPassConfig {
    GeometryPassConfig { iterations, batch: 3, stages: 1, ..GeometryPassConfig::default() }
}

/// Twice the signed area vector of triangle `t`.
fn area_vector(m: &Mesh, t: usize) -> Vec3 {
    let [a, b, c] = m.triangle_positions(t);
    (b - a).cross(c - a)
}

/// The properties every pass result must have: finite losses and positions, a closed manifold,
/// and no triangle that was healthy at the start and is flipped or collapsed at the end.
fn assert_valid(start: &Mesh, result: &GeometryPassResult) {
    assert!(result.history.iter().all(|s| s.loss.is_finite() && s.mask_mse.is_finite()), "non-finite loss");
    assert!(result.mesh.positions.iter().all(|p| p.is_finite()), "non-finite vertex");
    check_closed_manifold(&result.mesh).expect("the result stays a closed manifold");
    // Twice the area below which a triangle counts as collapsed: 1e-6 of a typical edge squared.
    let [a, b, _] = start.triangle_positions(start.triangles.len() / 2);
    let tiny = 1e-6 * (b - a).length_squared();
    let mut broken = 0;
    for t in 0..start.triangles.len() {
        let (before, after) = (area_vector(start, t), area_vector(&result.mesh, t));
        if before.length() > tiny && (before.dot(after) <= 0.0 || after.length() < tiny) {
            broken += 1;
        }
    }
    assert_eq!(broken, 0, "triangles flipped or collapsed by the pass");
}

#[test]
fn collapsed_triangles_in_the_start_mesh_stay_finite_and_are_never_shrunk_further() -> anyhow::Result<()> {
    let views = sphere_views(4.0, 32);
    let mut start = icosphere(Vec3::ZERO, 0.7, 3);
    // Collapse three triangles to needles: move one corner onto the midpoint of its opposite edge.
    for t in [0usize, 40, 200] {
        let [a, b, c] = start.triangles[t].map(|i| i as usize);
        start.positions[a] = 0.5 * (start.positions[b] + start.positions[c]);
    }
    start.recompute_normals();
    let needles_before: Vec<f32> = [0usize, 40, 200].iter().map(|&t| area_vector(&start, t).length()).collect();
    let result = run_geometry_pass(&start, &views, &config(40), false)?;
    assert_valid(&start, &result);
    for (k, &t) in [0usize, 40, 200].iter().enumerate() {
        let after = area_vector(&result.mesh, t).length();
        assert!(after.is_finite(), "needle {t} became non-finite");
        // A needle may grow back (its neighbours pull it open) but the pass never shrinks it.
        assert!(after >= needles_before[k] * 0.999 || after > 1e-4, "needle {t}: {} → {after}", needles_before[k]);
    }
    Ok(())
}

#[test]
fn a_vertex_pushed_through_the_opposite_surface_keeps_the_pass_finite() -> anyhow::Result<()> {
    let views = sphere_views(4.0, 32);
    let mut start = icosphere(Vec3::ZERO, 0.7, 3);
    // Vertex 0 through the centre and out the other side: its fan is inverted and crosses the
    // far surface.
    start.positions[0] = -1.3 * start.positions[0];
    start.recompute_normals();
    let result = run_geometry_pass(&start, &views, &config(40), false)?;
    assert_valid(&start, &result);
    Ok(())
}

#[test]
fn views_where_the_object_leaves_the_frame_give_finite_gradients() -> anyhow::Result<()> {
    // At distance 1.6 with fov 0.7 the frame is about 1.2 wide at the centre: the sphere of
    // radius 0.8 overflows every border, so the target alpha is 1 along the image edges.
    let views = sphere_views(1.6, 32);
    assert!(views.iter().all(|v| v.target.data.chunks_exact(4).take(32).all(|p| p[3] > 0.99)), "the object must fill the top row");
    let start = icosphere(Vec3::ZERO, 0.7, 3);
    let result = run_geometry_pass(&start, &views, &config(40), false)?;
    assert_valid(&start, &result);
    Ok(())
}

#[test]
fn a_step_that_cannot_keep_the_mesh_valid_stops_with_the_iteration_named() {
    let views = sphere_views(4.0, 32);
    let start = icosphere(Vec3::ZERO, 0.7, 2);
    // A first step of a million edge lengths: even 1/256 of it turns triangles inside out.
    let cfg = GeometryPassConfig { step_per_edge: 1e6, lambda: 0.0, ..config(5) };
    let err = run_geometry_pass(&start, &views, &cfg, false).err().expect("the pass must refuse to go on");
    let text = format!("{err:#}");
    assert!(text.contains("collapsed at iteration 0"), "{text}");
}

//! The geometry pass recovers a known shape from its images and masks: an ellipsoid rendered by
//! the pass's own image model, starting from a sphere that is too small along one axis and too
//! large along another. Chamfer distance to the true shape must fall by a stated factor. Under a
//! light that does not depend on the normal, the images tell only the outline, and the normal
//! prior toward exact normal labels must bring the normals closer to the truth than the outline
//! alone does.

use glam::{Quat, Vec3};
use reconstruct::fit::geometry_pass::{render_sh, run_geometry_pass, GeometryPassConfig, GeometryView};
use reconstruct::geometry::icosphere::icosphere;
use reconstruct::geometry::manifold::{check_closed_manifold, signed_volume};
use reconstruct::geometry::Mesh;
use reconstruct::image::Image;
use reconstruct::render::gbuffer::GBuffer;
use reconstruct::render::sh_light::constant_light;
use reconstruct::scene::Camera;

/// The views of the tests: 16 cameras spread over the sphere, looking at the origin.
fn cameras() -> Vec<Camera> {
    (0..16)
        .map(|i| {
            let a = i as f32 * 2.399_963;
            let z = 1.0 - 2.0 * (i as f32 + 0.5) / 16.0;
            let r = (1.0 - z * z).sqrt();
            let eye = 4.0 * Vec3::new(r * a.cos(), r * a.sin(), z);
            let up = if z.abs() > 0.9 { Vec3::X } else { Vec3::Z };
            Camera::look_at(eye, Vec3::ZERO, up, 0.7, 48, 48)
        })
        .collect()
}

/// The world-space shading normals `camera` sees on `mesh` (alpha 1 where covered).
fn normal_image(mesh: &Mesh, camera: &Camera) -> Image {
    let g = GBuffer::rasterize(mesh, camera);
    let mut out = Image::new(camera.width, camera.height, 4);
    for (px, s) in out.data.chunks_exact_mut(4).zip(&g.surfels) {
        if let Some(s) = s {
            px.copy_from_slice(&[s.normal.x, s.normal.y, s.normal.z, 1.0]);
        }
    }
    out
}

/// Mean angle (degrees) between the shading normals of `mesh` and `truth` over the pixels both
/// cover in `cameras`.
fn normal_error(mesh: &Mesh, truth: &Mesh, cameras: &[Camera]) -> f32 {
    let (mut sum, mut n) = (0.0, 0);
    for c in cameras {
        let (a, b) = (GBuffer::rasterize(mesh, c), GBuffer::rasterize(truth, c));
        for (a, b) in a.surfels.iter().zip(&b.surfels) {
            if let (Some(a), Some(b)) = (a, b) {
                sum += a.normal.dot(b.normal).clamp(-1.0, 1.0).acos().to_degrees();
                n += 1;
            }
        }
    }
    sum / n as f32
}

fn ellipsoid() -> Mesh {
    let mut m = icosphere(Vec3::ZERO, 1.0, 4);
    let rot = Quat::from_rotation_z(0.4) * Quat::from_rotation_x(0.3);
    for p in &mut m.positions {
        *p = rot * (*p * Vec3::new(1.0, 0.7, 0.5));
    }
    m.recompute_normals();
    m
}

/// Symmetric mean distance between the vertex sets (dense meshes, so close to the surface distance).
fn chamfer(a: &Mesh, b: &Mesh) -> f32 {
    let one_way = |a: &Mesh, b: &Mesh| {
        a.positions.iter().map(|p| b.positions.iter().map(|q| p.distance(*q)).fold(f32::MAX, f32::min)).sum::<f32>() / a.positions.len() as f32
    };
    0.5 * (one_way(a, b) + one_way(b, a))
}

#[test]
fn a_sphere_becomes_the_ellipsoid_in_its_images() -> anyhow::Result<()> {
    let truth = ellipsoid();
    let kd = vec![Vec3::new(0.7, 0.55, 0.4); truth.positions.len()];
    // Light from above-left plus ambient: shading varies with the normal.
    let mut light = constant_light(0.6);
    light[2 * 3] = 0.5; // band-1 z
    light[3 * 3 + 1] = 0.3; // band-1 x, green
    let views: Vec<GeometryView> = cameras()
        .into_iter()
        .enumerate()
        .map(|(i, camera)| {
            let target = render_sh(&truth, &kd, &light, &camera, 3).unwrap();
            GeometryView { name: format!("view {i}"), camera, target, normal: None }
        })
        .collect();
    let start = icosphere(Vec3::ZERO, 0.8, 3);
    let before = chamfer(&start, &truth);
    let config = GeometryPassConfig { iterations: 200, ..Default::default() };
    let result = run_geometry_pass(&start, &views, &config, false)?;
    let after = chamfer(&result.mesh, &truth);
    let last = &result.history[result.history.len() - 1];
    println!("first loss {:.4} mask {:.5}", result.history[0].loss, result.history[0].mask_mse);
    println!("chamfer {before:.4} → {after:.4}; last loss {:.4}, mask MSE {:.5}; {:?}", last.loss, last.mask_mse, result.timings);
    // Bound: a factor of 3 (measured 3.7: 0.136 → 0.037). The start is off by 0.2–0.3 along the
    // axes; what is left is below a pixel's footprint (2·4·tan(0.35)/48 ≈ 0.06 at the object) and
    // near this vertex-to-vertex metric's own floor for the start mesh's vertex spacing (~0.05).
    assert!(after < before / 3.0, "chamfer {before} → {after}");
    assert!(result.history.iter().all(|s| s.loss.is_finite()));
    // The stages' remeshes left a closed, outward-facing surface.
    assert_eq!(result.stages.len(), config.stages);
    check_closed_manifold(&result.mesh).map_err(anyhow::Error::msg)?;
    assert!(signed_volume(&result.mesh) > 0.0);
    Ok(())
}

#[test]
fn the_normal_prior_brings_the_normals_the_outline_leaves_open_to_the_labels() -> anyhow::Result<()> {
    let truth = ellipsoid();
    let kd = vec![Vec3::new(0.7, 0.55, 0.4); truth.positions.len()];
    // Ambient light only: the colour is the same whatever the normal, so only the outline and the
    // labels can shape the mesh.
    let light = constant_light(0.6);
    let cams = cameras();
    let views: Vec<GeometryView> = cams
        .iter()
        .enumerate()
        .map(|(i, camera)| {
            let target = render_sh(&truth, &kd, &light, camera, 3).unwrap();
            GeometryView { name: format!("view {i}"), camera: camera.clone(), target, normal: Some(normal_image(&truth, camera)) }
        })
        .collect();
    let start = icosphere(Vec3::ZERO, 0.8, 3);
    let run = |weight: f64| -> anyhow::Result<f32> {
        let config = GeometryPassConfig { iterations: 200, normal_prior: weight, ..Default::default() };
        let result = run_geometry_pass(&start, &views, &config, false)?;
        check_closed_manifold(&result.mesh).map_err(anyhow::Error::msg)?;
        Ok(normal_error(&result.mesh, &truth, &cams))
    };
    let (without, with) = (run(0.0)?, run(0.1)?);
    println!("normal error against the truth: outline alone {without:.2}°, with the prior {with:.2}°");
    assert!(with < 0.7 * without, "outline alone {without:.2}°, with the prior {with:.2}°");
    Ok(())
}

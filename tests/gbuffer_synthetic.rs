//! G-buffer on small synthetic meshes: degenerate triangles trace without NaN, and the surfel
//! fields (depth, normals facing the camera, UV, material) match hand-computed values.

use glam::{Mat4, Vec2, Vec3};
use reconstruct::geometry::bvh::Bvh;
use reconstruct::geometry::{Mesh, Part};
use reconstruct::material::{BaseColor, PartMaterial, Scalar};
use reconstruct::render::gbuffer::GBuffer;
use reconstruct::scene::camera::Camera;

/// A 2×2 quad in the z = 0 plane (uv = (x+1)/2, (y+1)/2), with extra degenerate triangles
/// (repeated and collinear vertices) and a vertex whose normals cancel.
fn quad_with_degenerates(face_up: bool) -> Mesh {
    let mut mesh = Mesh::default();
    mesh.positions = vec![
        Vec3::new(-1.0, -1.0, 0.0),
        Vec3::new(1.0, -1.0, 0.0),
        Vec3::new(1.0, 1.0, 0.0),
        Vec3::new(-1.0, 1.0, 0.0),
        Vec3::new(0.0, 0.0, 0.5),
        Vec3::new(0.3, 0.0, 0.5),
        Vec3::new(0.6, 0.0, 0.5),
    ];
    mesh.uvs = mesh.positions.iter().map(|p| Vec2::new(0.5 * (p.x + 1.0), 0.5 * (p.y + 1.0))).collect();
    mesh.triangles = if face_up {
        vec![[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 4, 4], [5, 6, 6]]
    } else {
        vec![[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 4, 4], [5, 6, 6]]
    };
    mesh.triangle_part = vec![0; 5];
    mesh.normals = Mesh::area_weighted_normals(&mesh.positions, &mesh.triangles);
    mesh.parts.push(Part { name: "quad".into(), material: 0, has_uv: true });
    mesh.materials.push(PartMaterial {
        name: "m".into(),
        base_color: BaseColor::Constant(Vec3::new(0.2, 0.4, 0.6)),
        roughness: Scalar::Constant(0.3),
        metallic: Scalar::Constant(0.1),
    });
    mesh
}

fn camera_above(size: usize) -> Camera {
    // Looking straight down −z from height 3, 60° field of view.
    Camera { c2w: Mat4::from_translation(Vec3::new(0.0, 0.0, 3.0)), fov_x: 60f32.to_radians(), width: size, height: size }
}

#[test]
fn degenerate_triangles_trace_without_nan_and_surfels_are_right() {
    for face_up in [true, false] {
        let mesh = quad_with_degenerates(face_up);
        mesh.validate().unwrap();
        let cam = camera_above(32);
        let gb = GBuffer::trace(&mesh, &Bvh::build(&mesh), &cam);
        assert_eq!((gb.width, gb.height, gb.surfels.len()), (32, 32, 1024));
        let mut hits = 0;
        for (i, s) in gb.surfels.iter().enumerate() {
            // The quad spans ±1 at distance 3: tan(30°)·3 = 1.73 > 1, so the border misses.
            let (x, y) = ((i % 32) as f32 + 0.5, (i / 32) as f32 + 0.5);
            let d = cam.ray_dir(x, y);
            let p = cam.origin() + d * (3.0 / -d.z);
            let expect_hit = p.x.abs() < 1.0 && p.y.abs() < 1.0;
            let Some(s) = s else {
                assert!(!expect_hit || p.x.abs() > 0.99 || p.y.abs() > 0.99, "pixel {i} missed the quad");
                continue;
            };
            hits += 1;
            for v in [s.position, s.normal, s.geo_normal] {
                assert!(v.is_finite());
            }
            assert!(s.uv.is_finite() && s.bary.is_finite() && s.depth.is_finite());
            assert!(s.triangle < 2, "hit degenerate triangle {}", s.triangle);
            assert!((s.position - p).length() < 1e-5);
            assert!((s.depth - 3.0).abs() < 1e-5, "planar depth {}", s.depth);
            // Both winding orders show a normal facing the camera (+z).
            assert!((s.normal - Vec3::Z).length() < 1e-5 && (s.geo_normal - Vec3::Z).length() < 1e-5);
            assert!((s.uv - Vec2::new(0.5 * (p.x + 1.0), 0.5 * (p.y + 1.0))).length() < 1e-5);
        }
        assert!(hits > 300, "hits {hits}");
        let params = gb.material_params(&mesh);
        let mask = gb.mask();
        assert_eq!(params.iter().filter(|p| p.is_some()).count(), hits);
        assert!(params.iter().zip(&mask).all(|(p, &m)| p.is_some() == m));
        let p = params.iter().flatten().next().unwrap();
        assert_eq!((p.kd, p.roughness, p.metallic), (Vec3::new(0.2, 0.4, 0.6), 0.3, 0.1));
        // Helper images agree with the surfels.
        let (cov, depth, normal) = (gb.coverage_image(), gb.depth_image(), gb.normal_image());
        for (i, (surfel, &m)) in gb.surfels.iter().zip(&mask).enumerate() {
            assert_eq!(cov.data[i] == 1.0, m);
            assert_eq!(depth.data[i], surfel.map_or(0.0, |s| s.depth));
            assert_eq!(normal.rgb(i), surfel.map_or(Vec3::ZERO, |s| s.normal));
        }
    }
}

#[test]
fn planar_depth_is_along_the_view_axis_not_the_ray() {
    // Off-centre pixels see the plane at the same planar depth but a longer ray distance.
    let mesh = quad_with_degenerates(true);
    let cam = camera_above(16);
    let gb = GBuffer::trace(&mesh, &Bvh::build(&mesh), &cam);
    let corner = gb.surfels[3 * 16 + 3].unwrap();
    assert!((corner.depth - 3.0).abs() < 1e-5);
    assert!((corner.position - cam.origin()).length() > 3.05);
}

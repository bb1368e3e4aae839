//! BVH queries agree with a brute-force loop over every triangle, on random rays against a
//! random triangle soup that includes degenerate (zero-area) triangles.

use glam::{Vec2, Vec3};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use obvhs::BvhBuildParams;
use reconstruct::geometry::bvh::{intersect_triangle, Bvh, Layout};
use reconstruct::geometry::bvh_wide::NodeTest;
use reconstruct::geometry::{Mesh, Part};

fn random_unit(rng: &mut Pcg64) -> Vec3 {
    loop {
        let v = Vec3::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0));
        if v.length_squared() > 1e-4 && v.length_squared() <= 1.0 {
            return v.normalize();
        }
    }
}

/// `n` random small triangles in the unit cube, every 10th one degenerate (repeated vertex,
/// collinear points, or all three equal).
fn random_mesh(rng: &mut Pcg64, n: usize) -> (Mesh, usize) {
    let mut mesh = Mesh::default();
    let mut degenerate = 0;
    for t in 0..n {
        let c = Vec3::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0));
        let (a, b) = (0.2 * random_unit(rng), 0.2 * random_unit(rng));
        let corners = match (t % 10 == 9, t % 3) {
            (false, _) => [c, c + a, c + b],
            (true, 0) => [c, c + a, c + a],
            (true, 1) => [c, c + a, c + 2.0 * a],
            (true, _) => [c, c, c],
        };
        degenerate += (t % 10 == 9) as usize;
        let base = mesh.positions.len() as u32;
        mesh.positions.extend(corners);
        mesh.triangles.push([base, base + 1, base + 2]);
        mesh.triangle_part.push(0);
    }
    mesh.normals = Mesh::area_weighted_normals(&mesh.positions, &mesh.triangles);
    mesh.uvs = vec![Vec2::ZERO; mesh.positions.len()];
    mesh.parts.push(Part { name: "soup".into(), material: 0, has_uv: false });
    (mesh, degenerate)
}

fn brute_force(mesh: &Mesh, o: Vec3, d: Vec3, tmin: f32, tmax: f32) -> Option<(u32, f32, Vec2)> {
    let mut best: Option<(u32, f32, Vec2)> = None;
    for t in 0..mesh.triangles.len() {
        if let Some((dist, bary)) = intersect_triangle(mesh.triangle_positions(t), o, d, tmin, tmax) {
            if best.is_none_or(|b| dist < b.1) {
                best = Some((t as u32, dist, bary));
            }
        }
    }
    best
}

#[test]
fn bvh_agrees_with_brute_force_on_random_rays() {
    let mut rng = Pcg64::seed_from_u64(7);
    let (mesh, degenerate) = random_mesh(&mut rng, 3000);
    let bvh = Bvh::build(&mesh);
    // Exactly-zero-area triangles are left out; float-collinear ones may keep a tiny area.
    assert!(bvh.primitive_count() <= mesh.triangles.len() && bvh.primitive_count() >= mesh.triangles.len() - degenerate);

    let (mut hits, mut occluded_checks) = (0, 0);
    for i in 0..4000 {
        // Half the rays start outside and aim into the cube, half start inside in random directions;
        // some have a finite tmax so that any-hit's segment test matters.
        let (o, d) = if i % 2 == 0 {
            let o = 3.0 * random_unit(&mut rng);
            let target = Vec3::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0));
            (o, target - o) // not unit length on purpose
        } else {
            (Vec3::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)), random_unit(&mut rng))
        };
        // Axis-aligned directions with signed zeros (−z = (−0, −0, −1)) exercise the slab tests'
        // handling of zero components.
        let d = match i % 16 {
            3 => -Vec3::Z,
            5 => -Vec3::X,
            7 => Vec3::Y,
            _ => d,
        };
        let tmin = 1e-4;
        let tmax = if i % 4 < 2 { f32::INFINITY } else { rng.random_range(0.05..1.5) };
        let reference = brute_force(&mesh, o, d, tmin, tmax);
        let got = bvh.closest_hit(o, d, tmin, tmax);
        match (reference, got) {
            (None, None) => {}
            (Some((rt, rdist, _)), Some(h)) => {
                hits += 1;
                assert!(h.t.is_finite() && h.bary.is_finite(), "non-finite hit {h:?}");
                assert!((h.t - rdist).abs() <= 1e-5 * rdist.max(1.0), "ray {i}: t {} vs brute force {rdist}", h.t);
                // Ties (shared t) may pick another triangle; otherwise it must be the same one and
                // its barycentrics must reproduce the hit point.
                if h.triangle != rt {
                    let alt = intersect_triangle(mesh.triangle_positions(h.triangle as usize), o, d, tmin, tmax);
                    assert!(alt.is_some_and(|(t, _)| (t - rdist).abs() <= 1e-5 * rdist.max(1.0)), "ray {i}: wrong triangle");
                }
                let [p0, p1, p2] = mesh.triangle_positions(h.triangle as usize);
                let x = (1.0 - h.bary.x - h.bary.y) * p0 + h.bary.x * p1 + h.bary.y * p2;
                assert!((x - (o + h.t * d)).length() < 1e-4, "ray {i}: barycentric point off the ray");
            }
            (r, g) => panic!("ray {i}: brute force {r:?} but BVH {g:?}"),
        }
        let occluded = bvh.any_hit(o, d, tmin, tmax);
        assert_eq!(occluded, reference.is_some(), "ray {i}: any_hit disagrees");
        occluded_checks += occluded as usize;
    }
    // The test only means something if both outcomes occur often.
    assert!(hits > 800 && hits < 3800, "hits {hits}");
    assert!(occluded_checks == hits);
}

#[test]
fn rays_through_degenerate_triangles_stay_finite() {
    // A unit quad plus degenerate triangles lying exactly where rays pass.
    let mut mesh = Mesh::default();
    mesh.positions = vec![
        Vec3::new(-1.0, -1.0, 0.0),
        Vec3::new(1.0, -1.0, 0.0),
        Vec3::new(1.0, 1.0, 0.0),
        Vec3::new(-1.0, 1.0, 0.0),
        Vec3::new(0.0, 0.0, 0.5),
        Vec3::new(0.1, 0.0, 0.5),
        Vec3::new(0.2, 0.0, 0.5),
    ];
    mesh.triangles = vec![[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 4, 4], [5, 5, 6]];
    mesh.triangle_part = vec![0; 5];
    mesh.normals = Mesh::area_weighted_normals(&mesh.positions, &mesh.triangles);
    mesh.uvs = vec![Vec2::ZERO; 7];
    let bvh = Bvh::build(&mesh);
    for x in [-0.05f32, 0.0, 0.05, 0.1, 0.15, 0.2] {
        for d in [-Vec3::Z, Vec3::new(0.0, 1e-8, -1.0), Vec3::new(0.2, 0.0, -1.0).normalize()] {
            let o = Vec3::new(x, 0.0, 2.0);
            let brute = (0..2).find_map(|t| intersect_triangle(mesh.triangle_positions(t), o, d, 0.0, f32::INFINITY));
            let h = bvh.closest_hit(o, d, 0.0, f32::INFINITY);
            assert!(brute.is_some());
            let h = h.expect("the quad is below every ray");
            assert!(h.triangle < 2, "hit a degenerate triangle: {h:?}");
            assert!(h.t.is_finite() && h.bary.is_finite());
        }
    }
}

/// Every layout and node test returns the hits of obvhs' CWBVH with its own node test (the
/// reference): on random rays, rays with ±0.0 components, rays running along triangle edges and
/// through degenerate triangles. The CWBVH's wide node tests visit the same nodes, so they must
/// return the same triangle; the float layout visits nodes in another order, so where two
/// triangles are hit at the same distance (a ray along a shared edge) it may return the other one.
/// t agrees within 1e-5 relative, occlusion answers are equal.
#[test]
fn layouts_and_node_tests_return_the_reference_hits() {
    let mut rng = Pcg64::seed_from_u64(9);
    let (mesh, _) = random_mesh(&mut rng, 3000);
    let reference = Bvh::build_layout(&mesh, BvhBuildParams::medium_build(), Layout::Cwbvh);
    let float8 = Bvh::build(&mesh);
    assert_eq!(float8.layout(), Some(Layout::Float8));
    assert_eq!(float8.uses_wide_node_test(), NodeTest::Avx2.supported());
    let mut rays: Vec<(Vec3, Vec3, f32)> = Vec::new();
    for i in 0..6000 {
        let o = Vec3::new(rng.random_range(-1.5..1.5), rng.random_range(-1.5..1.5), rng.random_range(-1.5..1.5));
        let mut d = random_unit(&mut rng);
        // Zero and negative-zero components.
        match i % 8 {
            1 => d.x = 0.0,
            2 => d.y = -0.0,
            3 => d = Vec3::new(-0.0, 0.0, -1.0),
            _ => {}
        }
        let tmax = if i % 3 == 0 { rng.random_range(0.05..2.0) } else { f32::INFINITY };
        rays.push((o, d, tmax));
    }
    // Along edges: start before a vertex and run along the edge to the next one, and just beside it.
    for t in (0..mesh.triangles.len()).step_by(7) {
        let [p0, p1, p2] = mesh.triangle_positions(t);
        for (a, b) in [(p0, p1), (p1, p2), (p2, p0)] {
            let e = b - a;
            if e.length_squared() > 0.0 {
                rays.push((a - 0.5 * e, e, f32::INFINITY));
                rays.push((a - 0.5 * e + 1e-7 * (p2 - p0), e, f32::INFINITY));
                // Across the edge's midpoint from above.
                rays.push((0.5 * (a + b) + Vec3::Z, -Vec3::Z, f32::INFINITY));
            }
        }
    }
    let mut variants: Vec<(&Bvh, NodeTest)> = [NodeTest::Avx2, NodeTest::Avx512].into_iter().filter(|t| t.supported()).map(|t| (&reference, t)).collect();
    // The float layout's scalar node test (`Obvhs` selects it) and its AVX2 test.
    variants.push((&float8, NodeTest::Obvhs));
    if NodeTest::Avx2.supported() {
        variants.push((&float8, NodeTest::Avx2));
    }
    for (bvh, test) in variants {
        let name = format!("{:?} {test:?}", bvh.layout());
        let (mut hits, mut ties) = (0, 0);
        for (i, &(o, d, tmax)) in rays.iter().enumerate() {
            let (got, want) = (bvh.closest_hit_using(test, o, d, 1e-4, tmax), reference.closest_hit_scalar(o, d, 1e-4, tmax));
            match (got, want) {
                (None, None) => {}
                (Some(g), Some(w)) => {
                    hits += 1;
                    assert!((g.t - w.t).abs() <= 1e-5 * w.t.abs(), "{name}, ray {i}: t {} vs {}", g.t, w.t);
                    if g.triangle != w.triangle {
                        // Only a tie may pick another triangle, and only in the other layout.
                        assert!(bvh.layout() == Some(Layout::Float8), "{name}, ray {i}: {g:?} vs {w:?}");
                        let alt = intersect_triangle(mesh.triangle_positions(g.triangle as usize), o, d, 1e-4, tmax);
                        assert!(alt.is_some_and(|(t, _)| t == w.t), "{name}, ray {i}: {g:?} vs {w:?} is not a tie");
                        ties += 1;
                    }
                }
                (g, w) => panic!("{name}, ray {i}: got {g:?}, reference {w:?}"),
            }
            assert_eq!(bvh.any_hit_using(test, o, d, 1e-4, tmax), reference.any_hit_scalar(o, d, 1e-4, tmax), "{name}, ray {i}: any_hit differs");
        }
        assert!(hits > rays.len() / 5 && hits < rays.len(), "{name}: {hits} hits of {} rays", rays.len());
        assert!(ties < hits / 100, "{name}: {ties} ties of {hits} hits");
    }
}

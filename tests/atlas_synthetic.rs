//! UV atlas on procedural meshes: own UVs are judged correctly, the generated atlas has no
//! overlaps, keeps the triangles and positions, has a bounded texel-density spread, and baked
//! textures reproduce the per-part materials.

use glam::{Quat, Vec2, Vec3};
use reconstruct::geometry::atlas::{build, own_uvs_problem, AtlasSource};
use reconstruct::geometry::primitives::MeshBuilder;
use reconstruct::geometry::Mesh;
use reconstruct::image::Image;
use reconstruct::material::texture_maps::MaterialTextures;
use reconstruct::material::{BaseColor, PartMaterial, Scalar};
use std::sync::Arc;

fn constant(name: &str, kd: Vec3, roughness: f32, metallic: f32) -> PartMaterial {
    PartMaterial::constant(name, kd, roughness, metallic)
}

/// A smooth colour ramp texture so that a baked texture shows whether the UV mapping is right.
fn ramp_texture(res: usize) -> Arc<Image> {
    let mut img = Image::new(res, res, 3);
    for y in 0..res {
        for x in 0..res {
            let (u, v) = ((x as f32 + 0.5) / res as f32, (y as f32 + 0.5) / res as f32);
            img.pixel_mut(x, y).copy_from_slice(&[u, v, 0.5 + 0.4 * (6.0 * u).sin() * (4.0 * v).cos()]);
        }
    }
    Arc::new(img)
}

/// Two ellipsoids on the same UV square, a cylinder (caps share UVs), and a part without UVs.
fn multi_part_mesh() -> Mesh {
    let mut b = MeshBuilder::new();
    let textured = PartMaterial { name: "ramp".into(), base_color: BaseColor::Texture(ramp_texture(64)), roughness: Scalar::Constant(0.4), metallic: Scalar::Constant(0.0) };
    let e1 = b.part(textured.clone());
    let e2 = b.part(PartMaterial { name: "ramp2".into(), ..textured });
    let cyl = b.part(constant("cyl", Vec3::new(0.8, 0.2, 0.1), 0.3, 1.0));
    let bare = b.part(constant("bare", Vec3::new(0.1, 0.6, 0.3), 0.9, 0.0));
    b.ellipsoid(e1, Vec3::new(-1.0, 0.0, 0.0), Vec3::new(0.5, 0.3, 0.4), Quat::from_rotation_z(0.3), 48, 24);
    b.ellipsoid(e2, Vec3::new(1.0, 0.0, 0.0), Vec3::new(0.3, 0.6, 0.2), Quat::IDENTITY, 32, 16);
    b.cylinder(cyl, Vec2::new(0.0, 1.0), 0.4, -0.2, 0.5, 40);
    b.ellipsoid(bare, Vec3::new(0.0, -1.0, 0.0), Vec3::splat(0.3), Quat::IDENTITY, 24, 12);
    let mut m = b.build();
    m.parts[bare as usize].has_uv = false;
    m
}

fn area3(m: &Mesh, t: usize) -> f32 {
    0.5 * m.face_normal_scaled(t).length()
}

#[test]
fn own_uvs_problem_names_the_reason() {
    let m = multi_part_mesh();
    assert!(own_uvs_problem(&m).unwrap().contains("bare"), "{:?}", own_uvs_problem(&m));

    // Two ellipsoids with valid UVs each, on the same square: overlap between parts.
    let mut b = MeshBuilder::new();
    let p = b.part(constant("a", Vec3::ONE, 0.5, 0.0));
    let q = b.part(constant("b", Vec3::ONE, 0.5, 0.0));
    b.ellipsoid(p, Vec3::ZERO, Vec3::ONE, Quat::IDENTITY, 32, 16);
    b.ellipsoid(q, Vec3::X * 3.0, Vec3::ONE, Quat::IDENTITY, 32, 16);
    let two = b.build();
    let why = own_uvs_problem(&two).expect("shared UV square must be reported");
    assert!(why.contains("parts a and b share UV space"), "{why}");

    // A cylinder's two caps map onto the same disc: overlap inside one part.
    let mut b = MeshBuilder::new();
    let p = b.part(constant("can", Vec3::ONE, 0.5, 0.0));
    b.cylinder(p, Vec2::ZERO, 1.0, 0.0, 1.0, 32);
    let why = own_uvs_problem(&b.build()).expect("cap overlap must be reported");
    assert!(why.contains("part can overlap"), "{why}");

    // Tiling UVs.
    let mut one = MeshBuilder::new();
    let p = one.part(constant("tile", Vec3::ONE, 0.5, 0.0));
    one.ellipsoid(p, Vec3::ZERO, Vec3::ONE, Quat::IDENTITY, 16, 8);
    let mut tiled = one.build();
    for uv in &mut tiled.uvs {
        *uv *= 2.0;
    }
    assert!(own_uvs_problem(&tiled).unwrap().contains("outside"));
}

#[test]
fn valid_own_uvs_are_kept() {
    let mut b = MeshBuilder::new();
    let p = b.part(constant("ball", Vec3::ONE, 0.5, 0.0));
    b.ellipsoid(p, Vec3::ZERO, Vec3::new(1.0, 0.5, 0.7), Quat::IDENTITY, 32, 16);
    let m = b.build();
    assert_eq!(own_uvs_problem(&m), None);
    let atlas = build(&m, 256).unwrap();
    assert_eq!(atlas.source, AtlasSource::OwnUvs);
    assert_eq!(atlas.mesh.uvs, m.uvs);
    assert_eq!(atlas.mesh.triangles, m.triangles);
}

#[test]
fn generated_atlas_is_overlap_free_and_keeps_the_geometry() {
    let m = multi_part_mesh();
    let t0 = std::time::Instant::now();
    let atlas = build(&m, 512).unwrap();
    let secs = t0.elapsed().as_secs_f32();
    let AtlasSource::Generated { reason, charts } = &atlas.source else { panic!("expected a generated atlas") };
    println!(
        "synthetic atlas: {} triangles, {charts} charts, {secs:.3} s, utilisation {:.1} %, density spread (max/min UV÷3D area over charts) {:.2}, reason: {reason}",
        m.triangles.len(),
        atlas.stats.utilisation * 100.0,
        atlas.stats.area_ratio_spread
    );
    let out = &atlas.mesh;
    out.validate().unwrap();
    assert_eq!(own_uvs_problem(out), None);
    assert!(out.uvs.iter().all(|uv| uv.min_element() >= 0.0 && uv.max_element() <= 1.0));
    assert_eq!(out.triangles.len(), m.triangles.len());
    assert_eq!(out.triangle_part, m.triangle_part);
    for t in 0..m.triangles.len() {
        assert_eq!(out.triangle_positions(t), m.triangle_positions(t), "triangle {t}");
    }
    // Bounded texel-density distortion: planar projection within a 35° cone tilts no face by
    // more than 70°, so per chart the ratio lies in [cos 70°, 1] × density².
    assert!(atlas.stats.area_ratio_spread < 1.0 / 70f32.to_radians().cos(), "{}", atlas.stats.area_ratio_spread);
    // Per triangle too: UV area / 3D area within the same bound.
    let density = atlas.stats.texels_per_unit / 512.0;
    for t in 0..out.triangles.len() {
        let a3 = area3(out, t);
        if a3 > 1e-9 {
            let [a, b, c] = out.triangles[t].map(|i| out.uvs[i as usize]);
            let ratio = 0.5 * (b - a).perp_dot(c - a).abs() / (a3 * density * density);
            assert!((0.3..=1.0 + 1e-3).contains(&ratio), "triangle {t}: UV/3D area ratio {ratio}");
        }
    }
    assert!(atlas.stats.utilisation > 0.3, "utilisation {}", atlas.stats.utilisation);
}

#[test]
fn degenerate_triangles_get_an_atlas_too() {
    let mut m = multi_part_mesh();
    // A part of zero-area faces: a point, a collinear sliver, and a repeated vertex index.
    let base = m.positions.len() as u32;
    for p in [Vec3::new(3.0, 0.0, 0.0), Vec3::new(3.5, 0.0, 0.0), Vec3::new(4.0, 0.0, 0.0)] {
        m.positions.push(p);
        m.normals.push(Vec3::Z);
        m.uvs.push(Vec2::ZERO);
    }
    m.parts.push(reconstruct::geometry::Part { name: "slivers".into(), material: 0, has_uv: false });
    let part = (m.parts.len() - 1) as u32;
    for tri in [[base, base, base], [base, base + 1, base + 2], [base, base + 2, base + 2]] {
        m.triangles.push(tri);
        m.triangle_part.push(part);
    }
    // And a zero-area face inside a textured part (its corners on existing vertices).
    m.triangles.push([0, 0, 1]);
    m.triangle_part.push(0);
    let atlas = build(&m, 256).unwrap();
    atlas.mesh.validate().unwrap();
    assert_eq!(own_uvs_problem(&atlas.mesh), None);
    assert!(atlas.mesh.uvs.iter().all(|uv| uv.is_finite() && uv.min_element() >= 0.0 && uv.max_element() <= 1.0));
    for t in 0..m.triangles.len() {
        assert_eq!(atlas.mesh.triangle_positions(t), m.triangle_positions(t));
    }
    assert_eq!(atlas.stats.zero_uv_area_triangles, 0);
    MaterialTextures::bake_from(&m, &atlas, 256).unwrap();
}

#[test]
fn baked_textures_reproduce_the_part_materials() {
    let m = multi_part_mesh();
    let res = 512;
    let atlas = build(&m, res).unwrap();
    let tex = MaterialTextures::bake_from(&m, &atlas, res).unwrap();
    // Random surface points: the atlas lookup must match the material at the original UV.
    let mut rng = reconstruct::rng::Sampler::from_seed(7);
    let (mut err, mut worst, n) = (0.0f32, 0.0f32, 4000);
    let (mut err_rm, mut n_pts) = (0.0f32, 0);
    for _ in 0..n {
        let t = ((rng_next(&mut rng) * m.triangles.len() as f32) as usize).min(m.triangles.len() - 1);
        if area3(&m, t) < 1e-9 {
            continue;
        }
        let (r1, r2) = (rng_next(&mut rng), rng_next(&mut rng));
        let s = r1.sqrt();
        let w = Vec3::new(1.0 - s, s * (1.0 - r2), s * r2);
        let interp = |mesh: &Mesh| {
            let [a, b, c] = mesh.triangles[t].map(|i| mesh.uvs[i as usize]);
            a * w.x + b * w.y + c * w.z
        };
        let want = m.triangle_material(t).eval(interp(&m));
        let got = tex.eval(interp(&atlas.mesh));
        let e = (want.kd - got.kd).abs().element_sum() / 3.0;
        err += e;
        worst = worst.max(e);
        err_rm += (want.roughness - got.roughness).abs() + (want.metallic - got.metallic).abs();
        n_pts += 1;
    }
    let (mean, mean_rm) = (err / n_pts as f32, err_rm / n_pts as f32);
    println!("synthetic bake ({res}²): kd mean abs error {mean:.5}, worst {worst:.4}; roughness+metallic mean abs error {mean_rm:.6} over {n_pts} points");
    assert!(mean < 0.01, "kd mean abs error {mean}");
    // Constant per part: conservative coverage must give the exact value at every lookup.
    assert!(mean_rm < 1e-5, "roughness/metallic error {mean_rm}");
}

#[test]
fn textures_survive_save_and_load() {
    let m = multi_part_mesh();
    let atlas = build(&m, 128).unwrap();
    let tex = MaterialTextures::bake_from(&m, &atlas, 128).unwrap();
    let dir = std::env::temp_dir().join(format!("reconstruct-atlas-roundtrip-{}", std::process::id()));
    tex.save(&dir).unwrap();
    let back = MaterialTextures::load(&dir).unwrap();
    assert_eq!((back.kd.width, back.ks.width), (128, 128));
    // 8-bit: ks within half a code; kd within half a code in sRGB space.
    let ks_err = tex.ks.data.iter().zip(&back.ks.data).map(|(a, b)| (a.clamp(0.0, 1.0) - b).abs()).fold(0.0, f32::max);
    assert!(ks_err <= 0.5 / 255.0 + 1e-6, "ks error {ks_err}");
    let enc = |x: f32| reconstruct::color::linear_to_srgb(x).clamp(0.0, 1.0);
    let kd_err = tex.kd.data.iter().zip(&back.kd.data).map(|(a, b)| (enc(*a) - enc(*b)).abs()).fold(0.0, f32::max);
    assert!(kd_err <= 0.5 / 255.0 + 1e-5, "kd error {kd_err}");
    // A missing folder is a clear error naming the file.
    let err = MaterialTextures::load(dir.join("nope")).unwrap_err().to_string();
    assert!(err.contains("kd.png"), "{err}");
    std::fs::remove_dir_all(&dir).ok();
}

fn rng_next(s: &mut reconstruct::rng::Sampler) -> f32 {
    s.next_f32()
}

/// A shallow spiral ramp of `turns` turns in `segments` quads: every triangle faces up (within a
/// few degrees), so one chart takes the whole ramp, and its projection onto the chart's plane
/// folds over itself wherever one turn lies above another, without any triangle flipping.
fn spiral_ramp(m: &mut Mesh, centre: Vec3, turns: f32, segments: u32) {
    let base = m.positions.len() as u32;
    for i in 0..=segments {
        let a = turns * std::f32::consts::TAU * i as f32 / segments as f32;
        for r in [0.5f32, 1.0] {
            m.positions.push(centre + Vec3::new(r * a.cos(), r * a.sin(), 0.02 * a));
            m.normals.push(Vec3::Z);
            m.uvs.push(Vec2::ZERO);
        }
    }
    for i in 0..segments {
        let (inner, outer, inner2, outer2) = (base + 2 * i, base + 2 * i + 1, base + 2 * i + 2, base + 2 * i + 3);
        m.triangles.extend([[inner, outer, outer2], [inner, outer2, inner2]]);
        m.triangle_part.extend([0, 0]);
    }
}

#[test]
fn charts_that_fold_over_themselves_are_split_until_clean() {
    // A finely cut ramp and a coarse one of a few triangles: where one turn lies over another,
    // the upper turn's triangles must get a chart of their own.
    let mut m = Mesh { parts: vec![reconstruct::geometry::Part { name: "ramp".into(), material: 0, has_uv: false }], materials: vec![constant("ramp", Vec3::splat(0.5), 0.5, 0.0)], ..Mesh::default() };
    spiral_ramp(&mut m, Vec3::ZERO, 1.6, 400);
    spiral_ramp(&mut m, Vec3::new(3.0, 0.0, 0.0), 1.6, 9);
    m.validate().unwrap();
    let atlas = build(&m, 256).unwrap();
    assert_eq!(own_uvs_problem(&atlas.mesh), None);
    for t in 0..m.triangles.len() {
        assert_eq!(atlas.mesh.triangle_positions(t), m.triangle_positions(t));
    }
    match atlas.source {
        AtlasSource::Generated { charts, .. } => assert!(charts >= 4, "{charts} charts: each ramp must have been split"),
        other => panic!("expected a generated atlas, got {other:?}"),
    }
}

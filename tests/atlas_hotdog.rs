//! The hotdog ground truth (13 parts, several on the same UV square, two without UVs) gets a
//! generated atlas in bounded time, and textures baked onto it reproduce the ground-truth
//! material at random surface points.

mod common;

use std::path::PathBuf;
use std::time::Instant;

use glam::Vec3;
use reconstruct::geometry::atlas::{build, own_uvs_problem, AtlasSource};
use reconstruct::geometry::ground_truth::load_ground_truth;
use reconstruct::geometry::Mesh;
use reconstruct::material::texture_maps::MaterialTextures;
use reconstruct::material::BaseColor;
use reconstruct::rng::Sampler;

fn gt_dir(test: &str) -> Option<PathBuf> {
    common::shared_data::require(test).map(|shared| shared.join("data/nerfactor/hotdog_2163/gt"))
}

fn area3(m: &Mesh, t: usize) -> f32 {
    0.5 * m.face_normal_scaled(t).length()
}

#[test]
fn hotdog_atlas_and_baked_ground_truth() {
    let Some(gt) = gt_dir("atlas_hotdog::hotdog_atlas_and_baked_ground_truth") else { return };
    let mesh = load_ground_truth(&gt).unwrap();
    let why = own_uvs_problem(&mesh).expect("the hotdog's own UVs cannot serve one texture");
    println!("hotdog own UVs: {why}");

    let res = 1024;
    let t0 = Instant::now();
    let atlas = build(&mesh, res).unwrap();
    let atlas_secs = t0.elapsed().as_secs_f32();
    let AtlasSource::Generated { charts, .. } = atlas.source else { panic!("expected a generated atlas") };
    let out = &atlas.mesh;
    let nondegenerate = (0..mesh.triangles.len()).filter(|&t| area3(&mesh, t) > 0.0).count();
    println!(
        "hotdog atlas {res}²: {} triangles, {} vertices (from {}), {charts} charts, {atlas_secs:.2} s, utilisation {:.1} %, \
         density spread {:.2}, {} zero-UV-area triangles of {nondegenerate} with area, {:.1} texels per unit",
        out.triangles.len(),
        out.positions.len(),
        mesh.positions.len(),
        atlas.stats.utilisation * 100.0,
        atlas.stats.area_ratio_spread,
        atlas.stats.zero_uv_area_triangles,
        atlas.stats.texels_per_unit
    );
    out.validate().unwrap();
    assert_eq!(own_uvs_problem(out), None);
    assert!(out.uvs.iter().all(|uv| uv.min_element() >= 0.0 && uv.max_element() <= 1.0));
    assert_eq!(out.triangle_part, mesh.triangle_part);
    for t in (0..mesh.triangles.len()).step_by(7) {
        assert_eq!(out.triangle_positions(t), mesh.triangle_positions(t));
    }
    assert!(atlas.stats.zero_uv_area_triangles * 100 < nondegenerate, "{} zero-area UV triangles", atlas.stats.zero_uv_area_triangles);
    assert!(atlas.stats.area_ratio_spread < 3.0);

    let t0 = Instant::now();
    let tex = MaterialTextures::bake_from(&mesh, &atlas, res).unwrap();
    let bake_secs = t0.elapsed().as_secs_f32();

    // Random surface points, area-weighted within textured and untextured parts alike.
    let mut rng = Sampler::from_seed(11);
    let areas: Vec<f32> = (0..mesh.triangles.len()).map(|t| area3(&mesh, t)).collect();
    let cdf: Vec<f32> = areas.iter().scan(0.0, |s, a| { *s += a; Some(*s) }).collect();
    let total = *cdf.last().unwrap();
    let (mut all, mut n_all, mut textured, mut n_textured, mut rm) = (0.0f64, 0, 0.0f64, 0, 0.0f64);
    for _ in 0..20_000 {
        let x = rng.next_f32() * total;
        let t = cdf.partition_point(|&c| c < x).min(mesh.triangles.len() - 1);
        let (r1, r2) = rng.next_2d();
        let s = r1.sqrt();
        let w = Vec3::new(1.0 - s, s * (1.0 - r2), s * r2);
        let interp = |m: &Mesh| {
            let [a, b, c] = m.triangles[t].map(|i| m.uvs[i as usize]);
            a * w.x + b * w.y + c * w.z
        };
        let want = mesh.triangle_material(t).eval(interp(&mesh));
        let got = tex.eval(interp(out));
        let e = ((want.kd - got.kd).abs().element_sum() / 3.0) as f64;
        all += e;
        n_all += 1;
        if matches!(mesh.triangle_material(t).base_color, BaseColor::Texture(_)) {
            textured += e;
            n_textured += 1;
        }
        rm += ((want.roughness - got.roughness).abs() + (want.metallic - got.metallic).abs()) as f64;
    }
    let (mean, mean_tex, mean_rm) = (all / n_all as f64, textured / n_textured.max(1) as f64, rm / n_all as f64);
    println!(
        "hotdog bake {res}²: {bake_secs:.2} s; kd mean abs error {mean:.4} over {n_all} area-weighted points, \
         {mean_tex:.4} over the {n_textured} on textured (bun) parts; roughness+metallic mean abs error {mean_rm:.2e}"
    );
    assert!(mean < 0.01, "kd mean abs error {mean}");
    assert!(mean_tex < 0.05, "kd mean abs error on textured parts {mean_tex}");
    assert!(mean_rm < 1e-4, "roughness/metallic error {mean_rm}");
}

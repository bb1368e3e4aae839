use anyhow::Result;
use reconstruct::fit::evaluate::{evaluate, EvalSettings};
use reconstruct::jobs::reconstruct::{prepare, GeometrySource};
use reconstruct::jobs::render::ground_truth_mesh;
use reconstruct::light::CubeMap;
use reconstruct::material::texture_maps::MaterialTextures;
use reconstruct::render::view::ShadingMode;
fn main() -> Result<()> {
    let p = prepare("nerfactor_hotdog", None, GeometrySource::GroundTruth, 512)?;
    let gt = ground_truth_mesh(&p.spec)?;
    let tex = MaterialTextures::bake_from(&gt, &p.atlas, 512)?;
    let probe = p.spec.load_train_probe()?;
    let light = CubeMap::from_latlong(&probe.radiance_image(), 64);
    let probes = p.spec.load_test_probes()?;
    for mode in [ShadingMode::SplitSum, ShadingMode::MonteCarlo] {
        let s = EvalSettings { relight_mode: ShadingMode::MonteCarlo, spp: 16, supersample: 2, seed: 0, effects: p.effects.effects, train_mode: mode, train_view_stride: 10, max_test_views: Some(2) };
        let e = evaluate(&p.dataset, &p.atlas.mesh, &p.bvh, &tex, &light, &probes, &s)?;
        println!("{mode:?}: {}", serde_json::to_string(&e.metrics)?.chars().take(600).collect::<String>());
    }
    Ok(())
}

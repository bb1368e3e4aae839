//! Writing a scene the project can render (mesh + materials + light + cameras) into the NeRFactor
//! layout: what the embedded default scene and the synthetic end-to-end tests are made of.

use std::fs;
use std::path::Path;

use anyhow::{Context, Result};
use glam::Vec3;
use serde_json::json;

use crate::color::linear_to_srgb;
use crate::geometry::bvh::Bvh;
use crate::geometry::Mesh;
use crate::image::{io, Image};
use crate::render::gbuffer::GBuffer;
use crate::render::view::{render_view, PreparedLight, RenderSettings};
use crate::scene::{Camera, Probe};

pub struct SyntheticScene {
    pub mesh: Mesh,
    pub train_probe: Probe,
    pub train: Vec<Camera>,
    pub val: Vec<Camera>,
    pub test: Vec<Camera>,
    /// Relighting probes for the test views (strength applied as given).
    pub test_probes: Vec<Probe>,
}

/// Render the scene into `dir` in the NeRFactor layout (transforms_*.json, per-view folders with
/// rgba.png, albedo.png (linear), normal.png, roughness.png, metallic.png, depth.exr, metadata.json,
/// and rgba_<probe>.png for test views), plus the training probe as `<name>.exr`.
pub fn write_nerfactor(scene: &SyntheticScene, dir: &Path, settings: &RenderSettings) -> Result<()> {
    fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let bvh = Bvh::build(&scene.mesh);
    let train_light = PreparedLight::from_probe(&scene.train_probe);
    let test_lights: Vec<(String, PreparedLight)> = scene
        .test_probes
        .iter()
        .map(|p| (p.name.clone(), PreparedLight::from_probe(p)))
        .collect();
    io::write_exr(&dir.join(format!("{}.exr", scene.train_probe.name)), &scene.train_probe.image)?;

    for (split, cameras) in [("train", &scene.train), ("val", &scene.val), ("test", &scene.test)] {
        let mut frames = Vec::new();
        for (i, cam) in cameras.iter().enumerate() {
            let name = format!("{split}_{i:03}");
            let view_dir = dir.join(&name);
            fs::create_dir_all(&view_dir).with_context(|| format!("cannot create {}", view_dir.display()))?;
            let view_settings = RenderSettings { seed: settings.seed.wrapping_add(hash_name(&name)), ..*settings };
            let rgba = render_view(&scene.mesh, &bvh, &train_light, cam, &view_settings);
            io::write_png(&view_dir.join("rgba.png"), &encode_srgb(&rgba))?;
            write_ground_truth_maps(&scene.mesh, &bvh, cam, settings.supersample, &view_dir)?;
            if split == "test" {
                for (probe, light) in &test_lights {
                    let relit = render_view(&scene.mesh, &bvh, light, cam, &view_settings);
                    io::write_png(&view_dir.join(format!("rgba_{probe}.png")), &encode_srgb(&relit))?;
                }
            }
            let matrix = cam.c2w.transpose().to_cols_array_2d(); // rows of the c2w matrix
            let metadata = json!({
                "scene": "reconstruct-synthetic",
                "cam_transform_mat": matrix.iter().flatten().map(|v| v.to_string()).collect::<Vec<_>>().join(","),
                "cam_angle_x": cam.fov_x,
                "envmap": format!("{}.exr", scene.train_probe.name),
                "envmap_inten": scene.train_probe.strength,
                "imh": cam.height, "imw": cam.width, "spp": settings.spp,
            });
            write_json(&view_dir.join("metadata.json"), &metadata)?;
            frames.push(json!({ "file_path": format!("./{name}/rgba"), "rotation": 0.0, "transform_matrix": matrix }));
        }
        let fov = cameras.first().map_or(0.69, |c| c.fov_x);
        write_json(&dir.join(format!("transforms_{split}.json")), &json!({ "camera_angle_x": fov, "frames": frames }))?;
    }
    Ok(())
}

fn hash_name(name: &str) -> u64 {
    name.bytes().fold(0xcbf2_9ce4_8422_2325u64, |h, b| (h ^ b as u64).wrapping_mul(0x0100_0000_01b3))
}

fn write_json(path: &Path, value: &serde_json::Value) -> Result<()> {
    let text = serde_json::to_string_pretty(value)?;
    fs::write(path, text).with_context(|| format!("cannot write {}", path.display()))
}

/// Straight linear RGBA → sRGB-encoded colour with the same alpha (what rgba.png stores).
pub fn encode_srgb(img: &Image) -> Image {
    img.map_channels(3, linear_to_srgb)
}

/// albedo.png (linear base colour), normal.png ((n+1)/2, world), roughness.png and metallic.png:
/// per-pixel averages over the covered sub-samples (straight, like the hotdog data), alpha = coverage;
/// depth.exr: planar depth along the view axis ("Z"), averaged the same way, 0 on the background.
fn write_ground_truth_maps(mesh: &Mesh, bvh: &Bvh, cam: &Camera, supersample: usize, dir: &Path) -> Result<()> {
    let s = supersample.max(1);
    let fine = cam.resized(cam.width * s, cam.height * s);
    let gbuf = GBuffer::trace(mesh, bvh, &fine);
    let params = gbuf.material_params(mesh);
    let (w, h) = (fine.width, fine.height);
    let mut albedo = Image::new(w, h, 4);
    let mut normal = Image::new(w, h, 4);
    let mut rough = Image::new(w, h, 4);
    let mut metal = Image::new(w, h, 4);
    let mut depth = Image::new(w, h, 4);
    for (i, (surfel, p)) in gbuf.surfels.iter().zip(&params).enumerate() {
        if let (Some(s), Some(p)) = (surfel, p) {
            let n = s.normal * 0.5 + Vec3::splat(0.5);
            albedo.data[4 * i..4 * i + 4].copy_from_slice(&[p.kd.x, p.kd.y, p.kd.z, 1.0]);
            normal.data[4 * i..4 * i + 4].copy_from_slice(&[n.x, n.y, n.z, 1.0]);
            rough.data[4 * i..4 * i + 4].copy_from_slice(&[p.roughness, p.roughness, p.roughness, 1.0]);
            metal.data[4 * i..4 * i + 4].copy_from_slice(&[p.metallic, p.metallic, p.metallic, 1.0]);
            depth.data[4 * i..4 * i + 4].copy_from_slice(&[s.depth, s.depth, s.depth, 1.0]);
        }
    }
    let resolve = |img: Image| img.downsample_box(s).unpremultiplied();
    io::write_png(&dir.join("albedo.png"), &resolve(albedo))?;
    io::write_png(&dir.join("normal.png"), &resolve(normal))?;
    io::write_png(&dir.join("roughness.png"), &resolve(rough).channel(0))?;
    io::write_png(&dir.join("metallic.png"), &resolve(metal).channel(0))?;
    io::write_exr_channels(&dir.join("depth.exr"), &resolve(depth).channel(0), &["Z"])?;
    Ok(())
}

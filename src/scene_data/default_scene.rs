//! The embedded default scene: a hotdog-like object built from primitives with procedural
//! textures, under a procedural sky, rendered by the project itself into the NeRFactor layout on
//! first use and cached. A fresh clone runs without `../shared/`.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{Context, Result};
use glam::{Quat, Vec2, Vec3};

use crate::geometry::primitives::MeshBuilder;
use crate::geometry::Mesh;
use crate::image::Image;
use crate::light::latlong;
use crate::material::{BaseColor, PartMaterial, Scalar};
use crate::render::effects::Effects;
use crate::render::view::{RenderSettings, ShadingMode};
use crate::scene::spec::NERFACTOR_TEST_PROBES;
use crate::scene_data::synthetic::{write_nerfactor, SyntheticScene};
use crate::scene::{Camera, Probe};

/// Bump when the scene or its rendering changes, so stale caches are rebuilt.
pub const VERSION: u32 = 3;
pub const RESOLUTION: usize = 128;
/// Indirect bounces of the dataset's renders (beyond what a reconstruction simulates by default).
pub const DATA_BOUNCES: u32 = 5;
/// The NeRF hotdog cameras' field of view.
pub const FOV_X: f32 = 0.691_111_2;

fn constant(name: &str, rgb: [f32; 3], roughness: f32, metallic: f32) -> PartMaterial {
    PartMaterial::constant(name, Vec3::from_array(rgb), roughness, metallic)
}

/// Bun texture: golden crust darkening towards the top, with baked streaks (linear RGB).
fn bun_texture(size: usize) -> Image {
    let mut img = Image::new(size, size, 3);
    for y in 0..size {
        for x in 0..size {
            let (u, v) = ((x as f32 + 0.5) / size as f32, (y as f32 + 0.5) / size as f32);
            // Row 0 is the top of the image = v_uv 1 = the ellipsoid's +z pole.
            let top = (1.0 - v).powf(0.7);
            let streak = 0.5 + 0.5 * (40.0 * u + 6.0 * (9.0 * v).sin()).sin();
            let crust = Vec3::new(0.62, 0.36, 0.12).lerp(Vec3::new(0.36, 0.16, 0.04), top * (0.6 + 0.4 * streak));
            img.set_rgb(y * size + x, crust);
        }
    }
    img
}

/// The object: a plate, a bun in two halves, a sausage, a dark sauce and a metal spoon.
pub fn mesh() -> Mesh {
    let mut b = MeshBuilder::new();
    let plate = b.part(constant("plate", [0.78, 0.74, 0.66], 0.2, 0.0));
    b.cylinder(plate, Vec2::ZERO, 1.1, -0.22, -0.14, 96);
    let bun = b.part(PartMaterial {
        name: "bun".into(),
        base_color: BaseColor::Texture(Arc::new(bun_texture(128))),
        roughness: Scalar::Constant(0.8),
        metallic: Scalar::Constant(0.0),
    });
    for x in [-0.19, 0.19] {
        b.ellipsoid(bun, Vec3::new(x, -0.1, -0.02), Vec3::new(0.2, 0.72, 0.14), Quat::IDENTITY, 48, 24);
    }
    let sausage = b.part(constant("sausage", [0.6, 0.09, 0.03], 0.4, 0.0));
    b.ellipsoid(sausage, Vec3::new(0.0, -0.1, 0.1), Vec3::new(0.12, 0.86, 0.11), Quat::IDENTITY, 48, 24);
    let sauce = b.part(constant("sauce", [0.25, 0.03, 0.01], 0.15, 0.0));
    b.ellipsoid(sauce, Vec3::new(0.66, 0.42, -0.11), Vec3::new(0.22, 0.2, 0.05), Quat::IDENTITY, 32, 16);
    let spoon = b.part(constant("spoon", [0.9, 0.88, 0.85], 0.3, 1.0));
    b.ellipsoid(spoon, Vec3::new(0.66, -0.45, -0.115), Vec3::new(0.09, 0.32, 0.03), Quat::from_rotation_z(0.3), 32, 16);
    b.build()
}

/// Procedural sky (lat-long, Blender convention, linear): a blue gradient above a dim ground and
/// a sun 35° above the horizon, so shadows and highlights are clear.
pub fn sky(width: usize, height: usize) -> Image {
    let sun = latlong_dir(35f32.to_radians(), 40f32.to_radians());
    let mut img = Image::new(width, height, 3);
    for y in 0..height {
        for x in 0..width {
            let d = latlong::dir_from_uv((x as f32 + 0.5) / width as f32, (y as f32 + 0.5) / height as f32);
            let sky = if d.z > 0.0 {
                Vec3::new(0.35, 0.5, 0.8).lerp(Vec3::new(0.7, 0.75, 0.8), (1.0 - d.z).powi(3))
            } else {
                Vec3::new(0.18, 0.16, 0.14)
            };
            let sun_lobe = (-(1.0 - d.dot(sun)) / 0.004).exp() * 60.0;
            img.set_rgb(y * width + x, sky + Vec3::new(1.0, 0.95, 0.85) * sun_lobe);
        }
    }
    img
}

fn latlong_dir(elevation: f32, azimuth: f32) -> Vec3 {
    Vec3::new(elevation.cos() * azimuth.cos(), elevation.cos() * azimuth.sin(), elevation.sin())
}

/// Cameras on a sphere of radius 4 around the origin, elevations in the upper hemisphere.
fn orbit(count: usize, elevation_deg: (f32, f32), azimuth_offset: f32) -> Vec<Camera> {
    (0..count)
        .map(|i| {
            let t = (i as f32 + 0.5) / count as f32;
            let elevation = (elevation_deg.0 + (elevation_deg.1 - elevation_deg.0) * ((i * 7 % count) as f32 / count as f32)).to_radians();
            let azimuth = 2.0 * std::f32::consts::PI * t + azimuth_offset;
            Camera::look_at(4.0 * latlong_dir(elevation, azimuth), Vec3::ZERO, Vec3::Z, FOV_X, RESOLUTION, RESOLUTION)
        })
        .collect()
}

pub fn scene(test_probes: Vec<Probe>) -> SyntheticScene {
    SyntheticScene {
        mesh: mesh(),
        train_probe: Probe { name: "sky".into(), image: sky(64, 32), strength: 1.0 },
        train: orbit(40, (15.0, 75.0), 0.0),
        val: orbit(4, (30.0, 60.0), 0.4),
        test: orbit(4, (25.0, 55.0), 1.1),
        test_probes,
    }
}

/// Where the committed CC0 probes are.
pub fn fixture_probe_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/probes")
}

/// Render the default dataset into `dir` unless a complete copy of this version is there already
/// (about a minute on 2 cores). An older version's folder is replaced. Safe when several threads
/// or processes (parallel tests) ask at once: one renders per process, into a private folder that
/// is renamed into place; a loser of the rename race keeps the winner's copy.
pub fn ensure_dataset(dir: &Path) -> Result<()> {
    static LOCK: std::sync::Mutex<()> = std::sync::Mutex::new(());
    let _guard = LOCK.lock().unwrap_or_else(|e| e.into_inner());
    let stamp = dir.join("COMPLETE");
    let expected = format!("default scene v{VERSION}\n");
    let complete = || std::fs::read_to_string(&stamp).ok().as_deref() == Some(expected.as_str());
    if complete() {
        return Ok(());
    }
    eprintln!("rendering the embedded default scene into {} (first use only)...", dir.display());
    let probe_dir = fixture_probe_dir();
    let probes = NERFACTOR_TEST_PROBES
        .iter()
        .map(|name| {
            Probe::load(&probe_dir.join(format!("{name}.hdr")), 1.0)
        })
        .collect::<Result<Vec<_>>>()?;
    // Full light transport (shadows, specular, interreflection), as a photographed object has.
    let settings = RenderSettings { mode: ShadingMode::MonteCarlo, spp: 64, supersample: 2, seed: 7, effects: Effects::with_bounces(DATA_BOUNCES) };
    let name = dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "default".into());
    let partial = dir.with_file_name(format!("{name}.partial-{}", std::process::id()));
    if partial.exists() {
        std::fs::remove_dir_all(&partial).with_context(|| format!("cannot clear {}", partial.display()))?;
    }
    write_nerfactor(&scene(probes), &partial, &settings)?;
    std::fs::write(partial.join("COMPLETE"), &expected).with_context(|| format!("cannot write {}", partial.join("COMPLETE").display()))?;
    if complete() {
        // Another process finished first.
        return std::fs::remove_dir_all(&partial).with_context(|| format!("cannot remove {}", partial.display()));
    }
    if dir.exists() {
        std::fs::remove_dir_all(dir).with_context(|| format!("cannot replace the stale default scene in {}", dir.display()))?;
    }
    if let Err(e) = std::fs::rename(&partial, dir) {
        if complete() {
            return std::fs::remove_dir_all(&partial).with_context(|| format!("cannot remove {}", partial.display()));
        }
        return Err(e).with_context(|| format!("cannot move {} to {}", partial.display(), dir.display()));
    }
    Ok(())
}

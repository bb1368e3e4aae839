//! Rendering one view: G-buffer (optionally supersampled) → per-pixel materials → shading →
//! RGBA with coverage alpha, resolved by a box filter like the dataset's renders.

use std::sync::OnceLock;

use glam::Vec3;
use serde::{Deserialize, Serialize};

use crate::geometry::bvh::Bvh;
use crate::geometry::Mesh;
use crate::image::Image;
use crate::light::brdf_lut::BrdfLut;
use crate::light::prefilter::SplitSumLight;
use crate::light::sampler::LightSampler;
use crate::light::cubemap::PROBE_CUBE_RES;
use crate::light::CubeMap;
use crate::material::{MaterialField, SurfaceParams};
use crate::render::effects::Effects;
use crate::render::gbuffer::GBuffer;
use crate::render::montecarlo::TraceScene;
use crate::render::{montecarlo, splitsum};
use crate::scene::{Camera, Probe};

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ShadingMode {
    SplitSum,
    MonteCarlo,
}

impl ShadingMode {
    /// The short tag in file and run-folder names: `splitsum` or `mc`.
    pub fn tag(self) -> &'static str {
        match self {
            ShadingMode::SplitSum => "splitsum",
            ShadingMode::MonteCarlo => "mc",
        }
    }
}

#[derive(Clone, Copy, Debug)]
pub struct RenderSettings {
    pub mode: ShadingMode,
    /// Samples per pixel (per strategy) in Monte Carlo mode.
    pub spp: u32,
    /// Primary rays per pixel side (s² per pixel), resolved with a box filter.
    pub supersample: usize,
    pub seed: u64,
    pub effects: Effects,
}

impl Default for RenderSettings {
    fn default() -> Self {
        RenderSettings { mode: ShadingMode::MonteCarlo, spp: 16, supersample: 2, seed: 0, effects: Effects::DIRECT }
    }
}

/// An environment light with the derived data each shading mode needs, built on first use only.
pub struct PreparedLight {
    pub cube: CubeMap,
    split_sum: OnceLock<(SplitSumLight, BrdfLut)>,
    sampler: OnceLock<LightSampler>,
}

impl PreparedLight {
    pub fn new(cube: CubeMap) -> Self {
        PreparedLight { cube, split_sum: OnceLock::new(), sampler: OnceLock::new() }
    }

    /// A lat-long probe (at its strength) as a cube map of [`PROBE_CUBE_RES`]² faces.
    pub fn from_probe(probe: &Probe) -> Self {
        PreparedLight::new(CubeMap::from_latlong(&probe.radiance_image(), PROBE_CUBE_RES))
    }

    pub fn split_sum(&self) -> &(SplitSumLight, BrdfLut) {
        self.split_sum.get_or_init(|| (SplitSumLight::new(&self.cube), BrdfLut::standard()))
    }

    pub fn sampler(&self) -> &LightSampler {
        self.sampler.get_or_init(|| LightSampler::new(&self.cube))
    }
}

/// Scene scale for ray offsets.
pub fn ray_epsilon(mesh: &Mesh) -> f32 {
    let (lo, hi) = mesh
        .positions
        .iter()
        .fold((Vec3::splat(f32::MAX), Vec3::splat(f32::MIN)), |(lo, hi), p| (lo.min(*p), hi.max(*p)));
    1e-4 * (hi - lo).length().max(1e-3)
}

/// Shade a traced G-buffer of `mesh` with its own part materials: linear radiance per pixel.
pub fn shade_gbuffer(gbuf: &GBuffer, mesh: &Mesh, bvh: &Bvh, light: &PreparedLight, settings: &RenderSettings, stream_offset: u64) -> Vec<Vec3> {
    let scene = TraceScene { mesh, bvh, materials: mesh };
    shade_with_params(gbuf, &gbuf.material_params(mesh), &scene, light, settings, stream_offset, ray_epsilon(mesh))
}

/// Shade a traced G-buffer whose per-pixel materials are given (e.g. looked up in textures);
/// `scene` is what shadow and bounce rays see.
pub fn shade_with_params(
    gbuf: &GBuffer,
    params: &[Option<SurfaceParams>],
    scene: &TraceScene,
    light: &PreparedLight,
    settings: &RenderSettings,
    stream_offset: u64,
    ray_epsilon: f32,
) -> Vec<Vec3> {
    match settings.mode {
        ShadingMode::SplitSum => {
            let (ss, lut) = light.split_sum();
            splitsum::shade(gbuf, params, ss, lut, settings.effects)
        }
        ShadingMode::MonteCarlo => {
            let mc = montecarlo::McSettings { spp: settings.spp, seed: settings.seed, effects: settings.effects, ray_epsilon };
            montecarlo::shade(gbuf, params, light.sampler(), scene, &mc, stream_offset).radiance(params)
        }
    }
}

/// Render one view to a linear RGBA image with straight (un-premultiplied) colour and coverage
/// alpha, the convention of the dataset's `rgba.png` (before its sRGB encoding).
pub fn render_view(mesh: &Mesh, bvh: &Bvh, light: &PreparedLight, camera: &Camera, settings: &RenderSettings) -> Image {
    render_view_with(mesh, bvh, light, camera, settings, mesh)
}

/// [`render_view`] with the materials given by `materials` (e.g. learned textures looked up at
/// the surfels' atlas UVs), for the visible surface and for the surfaces bounces reach.
pub fn render_view_with(
    mesh: &Mesh,
    bvh: &Bvh,
    light: &PreparedLight,
    camera: &Camera,
    settings: &RenderSettings,
    materials: &dyn MaterialField,
) -> Image {
    let s = settings.supersample.max(1);
    let fine = camera.resized(camera.width * s, camera.height * s);
    let mut gbuf = GBuffer::trace(mesh, bvh, &fine);
    gbuf.apply_material_normals(materials);
    let scene = TraceScene { mesh, bvh, materials };
    let radiance = shade_with_params(&gbuf, &gbuf.material_params(materials), &scene, light, settings, 0, ray_epsilon(mesh));
    straight_rgba(&gbuf, &radiance, s)
}

/// The per-pixel `radiance` of a G-buffer traced at `supersample`× the view's resolution, box
/// filtered down to the view: linear RGBA with straight colour and coverage alpha.
pub fn straight_rgba(gbuf: &GBuffer, radiance: &[Vec3], supersample: usize) -> Image {
    let mut premultiplied = Image::new(gbuf.width, gbuf.height, 4);
    for (i, (c, surfel)) in radiance.iter().zip(&gbuf.surfels).enumerate() {
        if surfel.is_some() {
            premultiplied.data[4 * i..4 * i + 4].copy_from_slice(&[c.x, c.y, c.z, 1.0]);
        }
    }
    premultiplied.downsample_box(supersample.max(1)).unpremultiplied()
}


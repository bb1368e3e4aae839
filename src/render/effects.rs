//! Effects a scene switches on: shadows (shadow rays in Monte Carlo shading), specular reflection
//! and interreflection (light the object reflects onto itself, by extra path bounces). `auto`
//! inspects the scene and says why it chose what it chose; an effect that is off costs nothing (no
//! shadow rays traced, no specular lobe evaluated or sampled, no secondary surface shaded).

use std::fmt;

use glam::Vec3;
use serde::{Deserialize, Serialize};

use crate::color::luminance;
use crate::geometry::bvh::{Bvh, Hit};
use crate::geometry::Mesh;
use crate::material::MaterialField;
use crate::math::Frame;
use crate::render::gbuffer::{GBuffer, Surfel};
use crate::rng::Sampler;
use crate::scene::effect_switches::{EffectSwitches, Switch};
use crate::scene::View;

/// The effects actually simulated.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Effects {
    pub shadows: bool,
    pub specular: bool,
    /// Surface-to-surface bounces after the first (0: direct light only, NVDiffRecMC's model).
    /// Needs shadows: a blocked ray is what finds the surface that reflects light back.
    #[serde(default)]
    pub indirect_bounces: u32,
}

impl Effects {
    /// Direct light with shadows and specular: NVDiffRecMC's full model.
    pub const DIRECT: Effects = Effects { shadows: true, specular: true, indirect_bounces: 0 };

    /// [`Effects::DIRECT`] plus `bounces` indirect bounces.
    pub const fn with_bounces(bounces: u32) -> Effects {
        Effects { shadows: true, specular: true, indirect_bounces: bounces }
    }

    pub fn interreflection(&self) -> bool {
        self.indirect_bounces > 0
    }
}

/// Light trapped in concavities (between bun and sausage, under the sauce) needs more than one
/// bounce: relighting the hotdog's ground truth measured 22.2 / 28.6 / 30.8 / 31.4 / 31.7 dB with
/// 0 / 1 / 2 / 3 / 5 bounces (README); three keep all but the last 0.3 dB.
pub const DEFAULT_INDIRECT_BOUNCES: u32 = 3;

/// The decision and its reasons, for the log and the report.
#[derive(Clone, Debug, Serialize)]
pub struct EffectChoice {
    pub effects: Effects,
    pub reasons: Vec<String>,
}

impl fmt::Display for EffectChoice {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let on = |b: bool| if b { "on" } else { "off" };
        write!(f, "shadows {}, specular {}, interreflection ", on(self.effects.shadows), on(self.effects.specular))?;
        match self.effects.indirect_bounces {
            0 => write!(f, "off")?,
            1 => write!(f, "on (1 bounce)")?,
            b => write!(f, "on ({b} bounces)")?,
        }
        for r in &self.reasons {
            write!(f, "\n  - {r}")?;
        }
        Ok(())
    }
}

/// Shadows matter when at least this fraction of cosine-weighted hemisphere rays from the surface
/// hit the object itself (ambient occlusion); below it, cast shadows change few pixels by little.
pub const SHADOW_OCCLUSION_THRESHOLD: f32 = 0.03;
/// A part is glossy enough to need the specular lobe when its roughness is below this or it is
/// metallic; with F0 = 0.04 and roughness ≥ 0.9 the lobe is a faint, wide sheen.
pub const SPECULAR_ROUGHNESS_THRESHOLD: f32 = 0.9;
/// Interreflection matters when at least this share of the light arriving at the visible surface
/// is expected to come from the object itself (blocked hemisphere × the albedo it is blocked by).
pub const INTERREFLECTION_THRESHOLD: f32 = 0.03;

/// Cosine-distributed hemisphere rays cast from surface points the cameras see (around their
/// camera-facing geometric normals): for each, the object's surface it hits, if any.
pub fn visible_hemisphere_hits(bvh: &Bvh, views: &[GBuffer], rays: usize, seed: u64) -> Vec<Option<Hit>> {
    let surfels: Vec<&Surfel> = views.iter().flat_map(|g| g.surfels.iter().flatten()).collect();
    if surfels.is_empty() {
        return Vec::new();
    }
    let extent = surfels
        .iter()
        .fold((Vec3::splat(f32::MAX), Vec3::splat(f32::MIN)), |(lo, hi), s| (lo.min(s.position), hi.max(s.position)));
    let eps = 1e-4 * (extent.1 - extent.0).length().max(1e-6);
    let mut rng = Sampler::from_seed(seed);
    (0..rays)
        .map(|_| {
            let s = surfels[((rng.next_f32() * surfels.len() as f32) as usize).min(surfels.len() - 1)];
            let frame = Frame::from_normal(s.geo_normal);
            let (r1, r2) = rng.next_2d();
            let (sin, cos) = (2.0 * std::f32::consts::PI * r2).sin_cos();
            let rad = r1.sqrt();
            let d = frame.to_world(Vec3::new(rad * cos, rad * sin, (1.0 - r1).max(0.0).sqrt()));
            bvh.closest_hit(s.position + s.geo_normal * eps, d, eps, f32::INFINITY)
        })
        .collect()
}

/// Fraction of those rays the object itself blocks: its visible ambient occlusion.
pub fn visible_self_occlusion(bvh: &Bvh, views: &[GBuffer], rays: usize, seed: u64) -> f32 {
    occlusion_of(&visible_hemisphere_hits(bvh, views, rays, seed))
}

fn occlusion_of(hits: &[Option<Hit>]) -> f32 {
    hits.iter().filter(|h| h.is_some()).count() as f32 / hits.len().max(1) as f32
}

/// Expected share of the cosine-weighted light at the visible surface that arrives reflected by
/// the object (one bounce, a grey sky): the mean over hemisphere rays of the diffuse albedo
/// (luminance of kd(1−m)) of the surface they hit, 0 for rays that escape. With unknown materials
/// (`None`) every blocking surface counts as white: the share is bounded by the occlusion.
pub fn interreflection_share(mesh: &Mesh, bvh: &Bvh, materials: Option<&dyn MaterialField>, views: &[GBuffer], rays: usize, seed: u64) -> f32 {
    share_of(mesh, materials, &visible_hemisphere_hits(bvh, views, rays, seed))
}

fn share_of(mesh: &Mesh, materials: Option<&dyn MaterialField>, hits: &[Option<Hit>]) -> f32 {
    let albedo = |h: &Hit| -> f32 {
        let Some(m) = materials else { return 1.0 };
        let [i0, i1, i2] = mesh.triangles[h.triangle as usize].map(|i| i as usize);
        let uv = (1.0 - h.bary.x - h.bary.y) * mesh.uvs[i0] + h.bary.x * mesh.uvs[i1] + h.bary.y * mesh.uvs[i2];
        let p = m.at(h.triangle, uv);
        luminance(p.kd * (1.0 - p.metallic))
    };
    // fold from +0: an empty float sum is −0, which would print as "-0.0%".
    hits.iter().flatten().map(albedo).fold(0.0, |sum, a| sum + a) / hits.len().max(1) as f32
}

/// A switch the scene set explicitly: its value, with the reason recorded.
fn set_by_scene(effect: &str, switch: Switch, reasons: &mut Vec<String>) -> bool {
    let on = switch == Switch::On;
    reasons.push(format!("{effect} {}: set by the scene", if on { "on" } else { "off" }));
    on
}

/// How many training views `auto` looks at, and their side in pixels: a coarse look from a few
/// sides spread over the training set. `auto` only asks whether the seen surface shadows or
/// reflects onto itself noticeably, which a few small views answer. The render job and the
/// reconstruction both look at these views.
pub const PROBE_VIEWS: usize = 4;
pub const PROBE_VIEW_SIDE: usize = 64;

/// G-buffers of the views `auto` looks at: [`PROBE_VIEWS`] of the `train` views, evenly spaced
/// along the list, at [`PROBE_VIEW_SIDE`]² pixels.
pub fn probe_views(mesh: &Mesh, bvh: &Bvh, train: &[View]) -> Vec<GBuffer> {
    train
        .iter()
        .step_by((train.len() / PROBE_VIEWS).max(1))
        .take(PROBE_VIEWS)
        .map(|v| GBuffer::trace(mesh, bvh, &v.camera.resized(PROBE_VIEW_SIDE, PROBE_VIEW_SIDE)))
        .collect()
}

/// Resolve `auto` switches by inspecting the geometry and materials (ground truth when known).
/// With unknown materials (`materials_known` false) specular stays on and interreflection is
/// judged with white occluders: neither can be ruled out.
/// `views` are G-buffers of a few training cameras ([`probe_views`]): the surface that matters is
/// the surface seen.
pub fn choose(switches: EffectSwitches, mesh: &Mesh, bvh: &Bvh, views: &[GBuffer], materials_known: bool) -> EffectChoice {
    let mut reasons = Vec::new();
    // Occlusion and interreflection are judged from the same hemisphere rays: trace them once.
    let hits = std::cell::OnceCell::new();
    let hits = || hits.get_or_init(|| visible_hemisphere_hits(bvh, views, 4000, 1)).as_slice();
    let shadows = match switches.shadows {
        Switch::On | Switch::Off => set_by_scene("shadows", switches.shadows, &mut reasons),
        Switch::Auto => {
            let occ = occlusion_of(hits());
            let on = occ >= SHADOW_OCCLUSION_THRESHOLD;
            reasons.push(format!(
                "shadows {} (auto): the object blocks {:.1}% of the hemisphere above its visible surface (threshold {:.0}%)",
                if on { "on" } else { "off" },
                100.0 * occ,
                100.0 * SHADOW_OCCLUSION_THRESHOLD
            ));
            on
        }
    };
    let specular = match switches.specular {
        Switch::On | Switch::Off => set_by_scene("specular", switches.specular, &mut reasons),
        Switch::Auto if !materials_known => {
            reasons.push("specular on (auto): materials are unknown, so glossiness cannot be ruled out".into());
            true
        }
        Switch::Auto => {
            let glossy: Vec<String> = mesh
                .materials
                .iter()
                .filter(|m| m.roughness.range().0 < SPECULAR_ROUGHNESS_THRESHOLD || m.metallic.range().1 > 0.0)
                .map(|m| format!("{} (roughness {}, metallic {})", m.name, m.roughness, m.metallic))
                .collect();
            let on = !glossy.is_empty();
            if on {
                reasons.push(format!("specular on (auto): glossy parts: {}", glossy.join(", ")));
            } else {
                reasons.push(format!(
                    "specular off (auto): every part has roughness ≥ {SPECULAR_ROUGHNESS_THRESHOLD} and metallic 0"
                ));
            }
            on
        }
    };
    let interreflection = match switches.interreflection {
        Switch::On | Switch::Off => set_by_scene("interreflection", switches.interreflection, &mut reasons),
        Switch::Auto => {
            let known: Option<&dyn MaterialField> = if materials_known { Some(mesh) } else { None };
            let share = share_of(mesh, known, hits());
            let on = share >= INTERREFLECTION_THRESHOLD;
            reasons.push(format!(
                "interreflection {} (auto): up to {:.1}% of the light on the visible surface is reflected by the object itself ({}; threshold {:.0}%)",
                if on { "on" } else { "off" },
                100.0 * share,
                if materials_known { "blocked hemisphere × the albedo blocking it" } else { "blocked hemisphere, materials unknown so occluders count as white" },
                100.0 * INTERREFLECTION_THRESHOLD
            ));
            on
        }
    };
    let shadows = if interreflection && !shadows {
        reasons.push("shadows on: interreflection needs them (a blocked ray is what finds the reflecting surface)".into());
        true
    } else {
        shadows
    };
    let indirect_bounces = if interreflection { switches.bounces.unwrap_or(DEFAULT_INDIRECT_BOUNCES).max(1) } else { 0 };
    EffectChoice { effects: Effects { shadows, specular, indirect_bounces }, reasons }
}

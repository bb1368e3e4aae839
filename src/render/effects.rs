//! Effects a scene switches on: shadows (shadow rays in Monte Carlo shading) and specular
//! reflection. `auto` inspects the scene and says why it chose what it chose; an effect that is off
//! costs nothing (no shadow rays traced, no specular lobe evaluated or sampled).

use std::fmt;
use std::str::FromStr;

use glam::Vec3;
use serde::{Deserialize, Serialize};

use crate::geometry::bvh::Bvh;
use crate::geometry::Mesh;
use crate::math::Frame;
use crate::render::gbuffer::{GBuffer, Surfel};
use crate::rng::Sampler;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Switch {
    #[default]
    Auto,
    On,
    Off,
}

impl FromStr for Switch {
    type Err = anyhow::Error;
    fn from_str(s: &str) -> anyhow::Result<Self> {
        match s {
            "auto" => Ok(Switch::Auto),
            "on" => Ok(Switch::On),
            "off" => Ok(Switch::Off),
            _ => anyhow::bail!("expected auto, on or off, got '{s}'"),
        }
    }
}

/// What the scene asks for, per effect.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct EffectSwitches {
    #[serde(default)]
    pub shadows: Switch,
    #[serde(default)]
    pub specular: Switch,
}

/// The effects actually simulated.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Effects {
    pub shadows: bool,
    pub specular: bool,
}

impl Effects {
    pub const ALL: Effects = Effects { shadows: true, specular: true };
}

/// The decision and its reasons, for the log and the report.
#[derive(Clone, Debug, Serialize)]
pub struct EffectChoice {
    pub effects: Effects,
    pub reasons: Vec<String>,
}

impl fmt::Display for EffectChoice {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let on = |b: bool| if b { "on" } else { "off" };
        write!(f, "shadows {}, specular {}", on(self.effects.shadows), on(self.effects.specular))?;
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

/// Fraction of cosine-distributed hemisphere rays, cast from surface points the cameras see (around
/// their camera-facing normals), that the object itself blocks: its visible ambient occlusion.
pub fn visible_self_occlusion(bvh: &Bvh, views: &[GBuffer], rays: usize, seed: u64) -> f32 {
    let surfels: Vec<&Surfel> = views.iter().flat_map(|g| g.surfels.iter().flatten()).collect();
    if surfels.is_empty() || rays == 0 {
        return 0.0;
    }
    let extent = surfels
        .iter()
        .fold((Vec3::splat(f32::MAX), Vec3::splat(f32::MIN)), |(lo, hi), s| (lo.min(s.position), hi.max(s.position)));
    let eps = 1e-4 * (extent.1 - extent.0).length().max(1e-6);
    let mut rng = Sampler::from_seed(seed);
    let mut blocked = 0usize;
    for _ in 0..rays {
        let s = surfels[((rng.next_f32() * surfels.len() as f32) as usize).min(surfels.len() - 1)];
        let frame = Frame::from_normal(s.geo_normal);
        let (r1, r2) = rng.next_2d();
        let (sin, cos) = (2.0 * std::f32::consts::PI * r2).sin_cos();
        let rad = r1.sqrt();
        let d = frame.to_world(Vec3::new(rad * cos, rad * sin, (1.0 - r1).max(0.0).sqrt()));
        if bvh.any_hit(s.position + s.geo_normal * eps, d, eps, f32::INFINITY) {
            blocked += 1;
        }
    }
    blocked as f32 / rays as f32
}

/// Resolve `auto` switches by inspecting the geometry and materials (ground truth when known).
/// With unknown materials (`materials_known` false) specular stays on: we cannot rule it out.
/// `views` are G-buffers of a few training cameras: the surface that matters is the surface seen.
pub fn choose(switches: EffectSwitches, mesh: &Mesh, bvh: &Bvh, views: &[GBuffer], materials_known: bool) -> EffectChoice {
    let mut reasons = Vec::new();
    let shadows = match switches.shadows {
        Switch::On => {
            reasons.push("shadows on: set by the scene".into());
            true
        }
        Switch::Off => {
            reasons.push("shadows off: set by the scene".into());
            false
        }
        Switch::Auto => {
            let occ = visible_self_occlusion(bvh, views, 4000, 1);
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
        Switch::On => {
            reasons.push("specular on: set by the scene".into());
            true
        }
        Switch::Off => {
            reasons.push("specular off: set by the scene".into());
            false
        }
        Switch::Auto if !materials_known => {
            reasons.push("specular on (auto): materials are unknown, so glossiness cannot be ruled out".into());
            true
        }
        Switch::Auto => {
            let glossy: Vec<String> = mesh
                .materials
                .iter()
                .filter(|m| m.roughness < SPECULAR_ROUGHNESS_THRESHOLD || m.metallic > 0.0)
                .map(|m| format!("{} (roughness {:.2}, metallic {:.2})", m.name, m.roughness, m.metallic))
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
    EffectChoice { effects: Effects { shadows, specular }, reasons }
}

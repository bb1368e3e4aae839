//! The `[effects]` table of a scene spec: per effect (shadows, specular, interreflection) whether
//! the scene turns it on, off, or leaves it to `auto`, which `render::effects::choose` decides
//! from the scene itself. Kept here, with the spec that is parsed into it, so that the spec does
//! not depend on the renderer.

use std::str::FromStr;

use serde::{Deserialize, Serialize};

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
    #[serde(default)]
    pub interreflection: Switch,
    /// Indirect bounces simulated when interreflection is on (default `render::effects::DEFAULT_INDIRECT_BOUNCES`).
    #[serde(default)]
    pub bounces: Option<u32>,
}

//! Scene spec files (TOML): where a scene's data, light probes and ground truth are, and which
//! light-transport effects it calls for. The format is documented in docs/scene_files.md.
//!
//! Paths: `{shared}` expands to [`shared_dir`], `{crate}` to the crate root; other relative paths
//! are resolved against the folder of the spec file (the ground-truth folder against the data folder).

use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context, Result};
use serde::Deserialize;

use super::effect_switches::EffectSwitches;
use super::probe::Probe;

/// The NeRFactor relighting protocol's 8 test probes.
pub const NERFACTOR_TEST_PROBES: [&str; 8] =
    ["city", "courtyard", "forest", "interior", "night", "studio", "sunrise", "sunset"];

/// The crate's root folder (at compile time).
pub fn crate_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// Where generated data (the default scene) is cached: `$RECONSTRUCT_CACHE`, else `<crate>/.cache`.
pub fn cache_dir() -> PathBuf {
    match std::env::var_os("RECONSTRUCT_CACHE") {
        Some(d) if !d.is_empty() => PathBuf::from(d),
        _ => crate_dir().join(".cache"),
    }
}

/// The shared data folder: `$RECONSTRUCT_SHARED_DIR`, else `<crate>/../shared`.
pub fn shared_dir() -> PathBuf {
    match std::env::var_os("RECONSTRUCT_SHARED_DIR") {
        Some(d) if !d.is_empty() => PathBuf::from(d),
        _ => crate_dir().join("..").join("shared"),
    }
}

/// A probe file and its strength.
#[derive(Clone, Debug, PartialEq)]
pub struct ProbeFile {
    pub path: PathBuf,
    pub strength: f32,
}

/// The relighting probes: names looked up as `<folder>/<name>.hdr` (then `.exr`) in each folder in turn.
#[derive(Clone, Debug, PartialEq)]
pub struct TestProbes {
    pub names: Vec<String>,
    pub folders: Vec<PathBuf>,
    pub strength: f32,
}

/// A scene spec with every path resolved.
#[derive(Clone, Debug, PartialEq)]
pub struct SceneSpec {
    pub name: String,
    pub description: Option<String>,
    /// The spec file this came from (None when parsed from a string).
    pub source: Option<PathBuf>,
    /// The dataset folder (NeRFactor or NeRF-synthetic layout).
    pub data_dir: PathBuf,
    /// The probe the training images were lit by, when known.
    pub train_probe: Option<ProbeFile>,
    pub test_probes: TestProbes,
    /// Ground-truth folder as written: relative paths are inside the data folder.
    pub ground_truth: Option<PathBuf>,
    pub effects: EffectSwitches,
    /// Set when the project makes the data itself (`"default"`: the embedded default scene).
    pub generator: Option<String>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawSpec {
    name: Option<String>,
    description: Option<String>,
    data: String,
    train_probe: Option<RawProbeFile>,
    #[serde(default)]
    test_probes: RawTestProbes,
    ground_truth: Option<RawGroundTruth>,
    #[serde(default)]
    effects: EffectSwitches,
    generator: Option<String>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawProbeFile {
    file: String,
    #[serde(default = "one")]
    strength: f32,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawTestProbes {
    #[serde(default = "default_test_probe_names")]
    names: Vec<String>,
    #[serde(default = "default_test_probe_folders")]
    folders: Vec<String>,
    #[serde(default = "one")]
    strength: f32,
}

impl Default for RawTestProbes {
    fn default() -> Self {
        RawTestProbes { names: default_test_probe_names(), folders: default_test_probe_folders(), strength: 1.0 }
    }
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawGroundTruth {
    folder: String,
}

fn one() -> f32 {
    1.0
}

fn default_test_probe_names() -> Vec<String> {
    NERFACTOR_TEST_PROBES.iter().map(|s| s.to_string()).collect()
}

fn default_test_probe_folders() -> Vec<String> {
    vec!["{shared}/data/probes".into(), "{crate}/tests/fixtures/probes".into()]
}

/// Expand `{shared}` / `{crate}`; resolve what is still relative against `base`.
fn resolve(path: &str, base: &Path) -> PathBuf {
    let expanded = if let Some(rest) = path.strip_prefix("{cache}") {
        cache_dir().join(rest.trim_start_matches(['/', '\\']))
    } else if let Some(rest) = path.strip_prefix("{shared}") {
        shared_dir().join(rest.trim_start_matches(['/', '\\']))
    } else if let Some(rest) = path.strip_prefix("{crate}") {
        crate_dir().join(rest.trim_start_matches(['/', '\\']))
    } else {
        PathBuf::from(path)
    };
    if expanded.is_absolute() {
        expanded
    } else {
        base.join(expanded)
    }
}

fn check_strength(what: &str, s: f32) -> Result<f32> {
    if !s.is_finite() || s < 0.0 {
        bail!("{what} strength must be finite and ≥ 0, got {s}");
    }
    Ok(s)
}

impl SceneSpec {
    /// Read a spec file.
    pub fn load(path: &Path) -> Result<SceneSpec> {
        if !path.is_file() {
            bail!("scene spec file not found: {}", path.display());
        }
        let text = std::fs::read_to_string(path).with_context(|| format!("cannot read scene spec {}", path.display()))?;
        let base = path.parent().map(Path::to_path_buf).unwrap_or_default();
        let stem = path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
        let mut spec = Self::parse(&text, &base, &stem).with_context(|| format!("in scene spec {}", path.display()))?;
        spec.source = Some(path.to_path_buf());
        Ok(spec)
    }

    /// Parse spec text; relative paths resolve against `base`; `default_name` is used when the
    /// file has no `name`.
    pub fn parse(text: &str, base: &Path, default_name: &str) -> Result<SceneSpec> {
        let raw: RawSpec = toml::from_str(text).map_err(|e| anyhow!("invalid scene spec: {e}"))?;
        let train_probe = match raw.train_probe {
            Some(p) => Some(ProbeFile { path: resolve(&p.file, base), strength: check_strength("train_probe", p.strength)? }),
            None => None,
        };
        if raw.test_probes.folders.is_empty() && !raw.test_probes.names.is_empty() {
            bail!("test_probes.folders is empty but {} probe names are given", raw.test_probes.names.len());
        }
        Ok(SceneSpec {
            name: raw.name.unwrap_or_else(|| default_name.to_string()),
            description: raw.description,
            source: None,
            data_dir: resolve(&raw.data, base),
            train_probe,
            test_probes: TestProbes {
                names: raw.test_probes.names,
                folders: raw.test_probes.folders.iter().map(|f| resolve(f, base)).collect(),
                strength: check_strength("test_probes", raw.test_probes.strength)?,
            },
            ground_truth: raw.ground_truth.map(|g| PathBuf::from(g.folder)),
            effects: raw.effects,
            generator: raw.generator,
        })
    }

    /// A spec by file path, or by name from `<crate>/scenes/NAME.toml`.
    pub fn find(name_or_path: &str) -> Result<SceneSpec> {
        let as_path = Path::new(name_or_path);
        if as_path.is_file() {
            return Self::load(as_path);
        }
        let looks_like_path = name_or_path.ends_with(".toml") || name_or_path.contains(['/', '\\']);
        if looks_like_path {
            bail!("scene spec file not found: {name_or_path}");
        }
        let scenes = crate_dir().join("scenes");
        let candidate = scenes.join(format!("{name_or_path}.toml"));
        if candidate.is_file() {
            return Self::load(&candidate);
        }
        let mut known: Vec<String> = std::fs::read_dir(&scenes)
            .map(|rd| {
                rd.filter_map(|e| e.ok())
                    .filter_map(|e| e.file_name().to_string_lossy().strip_suffix(".toml").map(str::to_owned))
                    .collect()
            })
            .unwrap_or_default();
        known.sort();
        bail!(
            "unknown scene {name_or_path:?}: no file {} (known scenes: {})",
            candidate.display(),
            if known.is_empty() { "none".to_string() } else { known.join(", ") }
        )
    }

    /// The same scene with its data in another folder (e.g. from `--data DIR`).
    pub fn with_data_dir(mut self, dir: impl Into<PathBuf>) -> SceneSpec {
        self.data_dir = dir.into();
        self
    }

    /// The ground-truth folder, when the spec names one.
    pub fn gt_dir(&self) -> Option<PathBuf> {
        self.ground_truth.as_ref().map(|g| self.data_dir.join(g))
    }

    pub fn load_train_probe(&self) -> Result<Probe> {
        let p = self
            .train_probe
            .as_ref()
            .ok_or_else(|| anyhow!("scene {:?} names no training probe", self.name))?;
        Probe::load(&p.path, p.strength)
    }

    /// Where test probe `name` is: the first folder holding `<name>.hdr` or `<name>.exr`.
    pub fn test_probe_path(&self, name: &str) -> Result<PathBuf> {
        for folder in &self.test_probes.folders {
            for ext in ["hdr", "exr"] {
                let p = folder.join(format!("{name}.{ext}"));
                if p.is_file() {
                    return Ok(p);
                }
            }
        }
        let tried: Vec<String> = self.test_probes.folders.iter().map(|f| f.display().to_string()).collect();
        bail!("test probe {name:?} not found (looked for {name}.hdr / {name}.exr in {})", tried.join(", "))
    }

    /// All test probes at the spec's test strength, in the spec's order.
    pub fn load_test_probes(&self) -> Result<Vec<Probe>> {
        self.test_probes
            .names
            .iter()
            .map(|n| Probe::load(&self.test_probe_path(n)?, self.test_probes.strength))
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::effect_switches::Switch;

    #[test]
    fn minimal_spec_gets_the_nerfactor_defaults_and_resolves_against_its_folder() {
        let spec = SceneSpec::parse("data = \"my_data\"", Path::new("/specs"), "mine").expect("test setup");
        assert_eq!(spec.name, "mine");
        assert_eq!(spec.data_dir, PathBuf::from("/specs/my_data"));
        assert_eq!(spec.test_probes.names.len(), 8);
        assert_eq!(spec.test_probes.strength, 1.0);
        assert_eq!(spec.test_probes.folders[1], crate_dir().join("tests/fixtures/probes"));
        assert_eq!(spec.effects, EffectSwitches { shadows: Switch::Auto, specular: Switch::Auto, ..Default::default() });
        assert!(spec.train_probe.is_none() && spec.gt_dir().is_none());
    }

    #[test]
    fn placeholders_absolute_paths_and_overrides() {
        let text = r#"
            data = "{shared}/data/x"
            train_probe = { file = "/abs/probe.hdr", strength = 3 }
            ground_truth = { folder = "gt" }
            effects = { shadows = "on", specular = "off", interreflection = "on", bounces = 2 }
        "#;
        let spec = SceneSpec::parse(text, Path::new("/specs"), "x").expect("test setup");
        assert_eq!(spec.data_dir, shared_dir().join("data/x"));
        assert_eq!(spec.train_probe, Some(ProbeFile { path: "/abs/probe.hdr".into(), strength: 3.0 }));
        assert_eq!(spec.effects, EffectSwitches { shadows: Switch::On, specular: Switch::Off, interreflection: Switch::On, bounces: Some(2) });
        let moved = spec.with_data_dir("/elsewhere");
        assert_eq!(moved.gt_dir(), Some(PathBuf::from("/elsewhere/gt")));
    }

    #[test]
    fn typos_and_bad_values_are_reported() {
        let e = SceneSpec::parse("data = \"d\"\nefects = {}", Path::new("."), "x").unwrap_err();
        assert!(format!("{e:#}").contains("efects"), "{e:#}");
        let e = SceneSpec::parse("data = \"d\"\neffects = { shadows = \"maybe\" }", Path::new("."), "x").unwrap_err();
        assert!(format!("{e:#}").contains("maybe"), "{e:#}");
        let e = SceneSpec::parse("train_probe = { file = \"p.hdr\" }", Path::new("."), "x").unwrap_err();
        assert!(format!("{e:#}").contains("data"), "{e:#}");
        let e = SceneSpec::parse("data = \"d\"\ntest_probes = { strength = -1 }", Path::new("."), "x").unwrap_err();
        assert!(format!("{e:#}").contains("strength"), "{e:#}");
    }

    #[test]
    fn a_missing_data_folder_names_it_and_says_to_pass_data() {
        let spec = SceneSpec::parse("data = \"/nonexistent/ficus_2188\"", Path::new("."), "x").expect("test setup");
        let msg = format!("{:#}", spec.load_dataset().unwrap_err());
        assert!(msg.contains("/nonexistent/ficus_2188") && msg.contains("--data"), "{msg}");
    }

    #[test]
    fn unknown_scene_names_the_file_it_looked_for() {
        let msg = format!("{:#}", SceneSpec::find("no_such_scene").unwrap_err());
        assert!(msg.contains("no_such_scene.toml"), "{msg}");
        let msg = format!("{:#}", SceneSpec::find("/tmp/none/x.toml").unwrap_err());
        assert!(msg.contains("/tmp/none/x.toml"), "{msg}");
    }
}

//! The label job (`reconstruct label`): per-view labels of a scene's training views from a label
//! source (the IDArb network, or the oracle / idarb-sim for checks without weights) written as
//! files that `--prior labels:DIR` reads, so labels can be made where compute is (a GPU node)
//! and used anywhere. IDArb labels still go through the label cache with its key unchanged: the
//! same views labelled by `--prior idarb` on this machine reuse them.
//!
//! Output folder: `<view>_albedo.png`, `<view>_normal.png`, `<view>_metallic.png`,
//! `<view>_roughness.png` (16-bit, the label spaces of docs/prior_labels.md) and `labels.json`
//! (source, views, and for IDArb the cache settings with the key and the weight hashes).

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use serde::{Deserialize, Serialize};

use crate::fit::config::FitConfig;
use crate::image::io::write_png16;
use crate::prior::idarb::labels::IdarbOptions;
use crate::prior::idarb::labels_cache::SETTINGS_FILE;
use crate::prior::source::{make_prior, PriorContext, PriorSource};
use crate::scene::spec::cache_dir;
use crate::scene::SceneSpec;

use super::reconstruct::{labelled_views, prepare, prior_context, GeometrySource};

/// The file that marks a finished label folder.
pub const LABELS_FILE: &str = "labels.json";

/// Which training views to label.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ViewSelection {
    /// This many, evenly spread over the sequence (as `--labelled-views`).
    Count(usize),
    /// These view names (`train_003`).
    Names(Vec<String>),
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LabelOptions {
    pub scene: String,
    /// Data folder overriding the spec's.
    pub data: Option<PathBuf>,
    /// idarb, oracle or idarb-sim[:LEVEL].
    pub source: String,
    pub views: ViewSelection,
    pub out: PathBuf,
    /// IDArb weights folder (else `$IDARB_WEIGHTS`).
    pub idarb_weights: Option<PathBuf>,
    /// Seed of simulated labels (a run's `--seed`, so its `--prior idarb-sim` gets the same).
    pub seed: u64,
}

#[derive(Clone, Debug, Serialize)]
pub struct LabelReport {
    pub scene: String,
    pub source: String,
    /// The labelled views, by name.
    pub views: Vec<String>,
    pub seconds: f64,
    /// For IDArb: the cache's settings (options, input hashes, weight hashes).
    pub idarb_cache: Option<serde_json::Value>,
}

/// The dataset indices of `selection` among training views named `names`.
pub fn select_views(names: &[String], selection: &ViewSelection) -> Result<Vec<usize>> {
    match selection {
        ViewSelection::Count(n) => Ok(labelled_views(names.len(), *n)),
        ViewSelection::Names(wanted) => wanted
            .iter()
            .map(|w| names.iter().position(|n| n == w).with_context(|| format!("no training view named {w:?} (the views are {} to {})", names.first().map_or("", |s| s), names.last().map_or("", |s| s))))
            .collect(),
    }
}

/// Label the views and write the folder.
pub fn run(opts: &LabelOptions) -> Result<LabelReport> {
    let t = Instant::now();
    let source: PriorSource = opts.source.parse()?;
    if matches!(source, PriorSource::None | PriorSource::LabelsDir(_)) {
        bail!("reconstruct label --source {}: use idarb, oracle or idarb-sim[:LEVEL] (a source that makes labels)", opts.source);
    }
    let fit = FitConfig { seed: opts.seed, ..FitConfig::default() };
    let (spec, dataset, ctx) = if let PriorSource::IdarbSim(_) = source {
        // Simulated errors follow the surface: the same mesh a run uses, so the labels match.
        let p = prepare(&opts.scene, opts.data.as_ref(), GeometrySource::GroundTruth, &Default::default(), &fit, 1, false)?;
        let ctx = prior_context(opts.seed, opts.idarb_weights.clone());
        (p.spec, p.dataset, ctx)
    } else {
        let mut spec = SceneSpec::find(&opts.scene)?;
        if let Some(d) = &opts.data {
            spec = spec.with_data_dir(d);
        }
        let dataset = spec.load_dataset()?;
        let ctx = PriorContext { idarb_weights: opts.idarb_weights.clone(), cache_dir: cache_dir(), idarb: IdarbOptions::default(), seed: opts.seed };
        (spec, dataset, ctx)
    };
    let names: Vec<String> = dataset.train.iter().map(|v| v.name.clone()).collect();
    let which = select_views(&names, &opts.views).with_context(|| format!("scene {:?}", spec.name))?;
    let prior = make_prior(&source, &ctx)?;
    let labels = prior.labels(&dataset, &which).with_context(|| format!("labelling scene {:?} with {}", spec.name, source.tag()))?;
    std::fs::create_dir_all(&opts.out).with_context(|| format!("cannot create the label folder {}", opts.out.display()))?;
    let mut views = Vec::new();
    for (&i, l) in which.iter().zip(&labels) {
        let Some(l) = l else { continue };
        let name = &dataset.train[i].name;
        for (map, img) in [("albedo", &l.albedo), ("normal", &l.normal), ("metallic", &l.metallic), ("roughness", &l.roughness)] {
            write_png16(&opts.out.join(format!("{name}_{map}.png")), img)?;
        }
        views.push(name.clone());
    }
    let idarb_cache = if source == PriorSource::Idarb { read_json(&ctx.cache_dir.join("idarb").join(SETTINGS_FILE)).ok() } else { None };
    let report = LabelReport { scene: spec.name.clone(), source: prior.describe(), views, seconds: t.elapsed().as_secs_f64(), idarb_cache };
    let path = opts.out.join(LABELS_FILE);
    std::fs::write(&path, serde_json::to_string_pretty(&report)?).with_context(|| format!("cannot write {}", path.display()))?;
    Ok(report)
}

fn read_json(path: &Path) -> Result<serde_json::Value> {
    Ok(serde_json::from_str(&std::fs::read_to_string(path)?)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn selects_spread_views_or_names_and_names_a_missing_view() {
        let names: Vec<String> = (0..10).map(|i| format!("train_{i:03}")).collect();
        assert_eq!(select_views(&names, &ViewSelection::Count(4)).unwrap(), vec![0, 2, 5, 7]);
        assert_eq!(select_views(&names, &ViewSelection::Count(50)).unwrap().len(), 10);
        assert_eq!(select_views(&names, &ViewSelection::Names(vec!["train_007".into(), "train_001".into()])).unwrap(), vec![7, 1]);
        let err = select_views(&names, &ViewSelection::Names(vec!["r_7".into()])).unwrap_err().to_string();
        assert!(err.contains("r_7") && err.contains("train_000"), "{err}");
    }
}

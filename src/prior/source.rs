//! Where the prior's labels come from (`--prior`): nothing, the IDArb network (or its cached
//! labels), a folder of label files, the ground truth (oracle), or the ground truth degraded to
//! IDArb's published accuracy (idarb-sim). One [`Prior`] trait serves them all.

use std::path::PathBuf;
use std::str::FromStr;

use anyhow::{bail, Context, Result};

use crate::image::Image;
use crate::scene::dataset::Dataset;

use super::idarb::labels::{labels_for_named_views, IdarbOptions};
use super::view_labels::ViewLabels;
use super::idarb::preprocess::pose_from_camera_origin;
use super::idarb_sim::SimulatedIdarb;
use super::labels_dir::LabelsDir;
use super::oracle::Oracle;

#[derive(Clone, Debug, PartialEq)]
pub enum PriorSource {
    None,
    Idarb,
    LabelsDir(PathBuf),
    Oracle,
    /// Error scale: 1 = IDArb's published accuracy, 0 = the oracle.
    IdarbSim(f64),
}

impl FromStr for PriorSource {
    type Err = anyhow::Error;
    fn from_str(s: &str) -> Result<Self> {
        Ok(match s {
            "none" => PriorSource::None,
            "idarb" => PriorSource::Idarb,
            "oracle" => PriorSource::Oracle,
            "idarb-sim" => PriorSource::IdarbSim(1.0),
            _ => {
                if let Some(dir) = s.strip_prefix("labels:") {
                    if dir.is_empty() {
                        bail!("--prior labels:DIR needs a folder after `labels:`");
                    }
                    PriorSource::LabelsDir(PathBuf::from(dir))
                } else if let Some(level) = s.strip_prefix("idarb-sim:") {
                    let v: f64 = level.parse().with_context(|| format!("--prior {s}: the level after `idarb-sim:` must be a number"))?;
                    if !(v.is_finite() && v >= 0.0) {
                        bail!("--prior {s}: the level must be ≥ 0");
                    }
                    PriorSource::IdarbSim(v)
                } else {
                    bail!("unknown prior {s:?}: use none, idarb, labels:DIR, oracle, idarb-sim or idarb-sim:LEVEL")
                }
            }
        })
    }
}

impl PriorSource {
    /// Short name for file names and tables.
    pub fn tag(&self) -> String {
        match self {
            PriorSource::None => "none".into(),
            PriorSource::Idarb => "idarb".into(),
            PriorSource::LabelsDir(d) => format!("labels:{}", d.display()),
            PriorSource::Oracle => "oracle".into(),
            PriorSource::IdarbSim(l) => format!("idarb-sim:{l}"),
        }
    }
}

/// A source of per-view labels.
pub trait Prior {
    /// One line for reports, naming the source (a simulated result must never pass for a real one).
    fn describe(&self) -> String;
    /// Labels for the dataset's training views `views` (indices into `dataset.train`); `None` where
    /// a view has no label.
    fn labels(&self, dataset: &Dataset, views: &[usize]) -> Result<Vec<Option<ViewLabels>>>;
}

/// What label sources may need besides the dataset.
#[derive(Clone)]
pub struct PriorContext {
    pub idarb_weights: Option<PathBuf>,
    pub cache_dir: PathBuf,
    pub idarb: IdarbOptions,
    pub seed: u64,
}

struct NoPrior;

impl Prior for NoPrior {
    fn describe(&self) -> String {
        "none".into()
    }
    fn labels(&self, _: &Dataset, views: &[usize]) -> Result<Vec<Option<ViewLabels>>> {
        Ok(vec![None; views.len()])
    }
}

struct IdarbNetwork {
    ctx: PriorContext,
}

impl Prior for IdarbNetwork {
    fn describe(&self) -> String {
        format!("idarb (IDArb network, {} DDIM steps at {}², cached labels reused)", self.ctx.idarb.steps, self.ctx.idarb.target_size)
    }
    fn labels(&self, dataset: &Dataset, views: &[usize]) -> Result<Vec<Option<ViewLabels>>> {
        let images: Vec<Image> = views
            .iter()
            .map(|&i| dataset.train[i].load_rgba().map(|img| img.linear_to_srgb()))
            .collect::<Result<_>>()?;
        let poses: Vec<[f32; 4]> = views.iter().map(|&i| pose_from_camera_origin(dataset.train[i].camera.origin())).collect();
        // named after the views, so the cache folder is also a `--prior labels:DIR` folder
        let names: Vec<String> = views.iter().map(|&i| dataset.train[i].name.clone()).collect();
        let labels = labels_for_named_views(&images, &names, Some(&poses), &self.ctx.idarb, self.ctx.idarb_weights.as_deref(), &self.ctx.cache_dir.join("idarb"))?;
        Ok(labels.into_iter().map(Some).collect())
    }
}

pub fn make_prior(source: &PriorSource, ctx: &PriorContext) -> Result<Box<dyn Prior>> {
    Ok(match source {
        PriorSource::None => Box::new(NoPrior),
        PriorSource::Idarb => Box::new(IdarbNetwork { ctx: ctx.clone() }),
        PriorSource::LabelsDir(dir) => Box::new(LabelsDir::open(dir)?),
        PriorSource::Oracle => Box::new(Oracle),
        PriorSource::IdarbSim(level) => Box::new(SimulatedIdarb::new(*level, ctx.seed)),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_every_source_and_rejects_bad_ones() {
        assert_eq!("none".parse::<PriorSource>().unwrap(), PriorSource::None);
        assert_eq!("idarb".parse::<PriorSource>().unwrap(), PriorSource::Idarb);
        assert_eq!("oracle".parse::<PriorSource>().unwrap(), PriorSource::Oracle);
        assert_eq!("idarb-sim".parse::<PriorSource>().unwrap(), PriorSource::IdarbSim(1.0));
        assert_eq!("idarb-sim:0.5".parse::<PriorSource>().unwrap(), PriorSource::IdarbSim(0.5));
        assert_eq!("labels:out/x".parse::<PriorSource>().unwrap(), PriorSource::LabelsDir("out/x".into()));
        for bad in ["idarb-sim:-1", "idarb-sim:abc", "labels:", "nerf"] {
            assert!(bad.parse::<PriorSource>().is_err(), "{bad}");
        }
    }
}

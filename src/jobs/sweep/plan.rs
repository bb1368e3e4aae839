//! Planning a sweep: the ablation, the trade-off and labelling split into manifest lines, one per
//! run, with the same run folders and settings the one-process jobs use, so a gathered sweep and
//! a serial job give the same table. Each job takes `--plan FILE` ([`PlanArgs`]) to write its
//! lines instead of running them.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};

use crate::jobs::ablation::{all_sources, run_folder, AblationOptions};
use crate::jobs::label::LabelOptions;
use crate::jobs::reconstruct::ReconstructOptions;
use crate::jobs::tradeoff::{point_options, TradeoffPoint};
use crate::scene::SceneSpec;

use super::manifest::{self, Job, RunSpec, Study, SweepLine};

/// The `--plan` options every sweepable job shares.
#[derive(clap::Args, Clone, Debug, Default)]
pub struct PlanArgs {
    /// Write the runs to this manifest (JSON lines) instead of running them; run them with
    /// `reconstruct sweep run` on Slurm, GNU parallel or Kubernetes (docs/scale.md).
    #[arg(long)]
    pub plan: Option<PathBuf>,
    /// Add the runs to the manifest instead of replacing it.
    #[arg(long, requires = "plan")]
    pub append: bool,
}

/// One line per run of the ablation `opts` (its sources, then its sweep levels), in table order.
pub fn ablation(opts: &AblationOptions) -> Vec<SweepLine> {
    let study = Study::Ablation { out: opts.base.out.clone(), levels: opts.sweep.clone() };
    all_sources(opts)
        .into_iter()
        .map(|source| {
            let mut o = opts.base.clone();
            o.out = run_folder(&opts.base.out, &source);
            SweepLine { study: study.clone(), name: source.tag(), job: Job::Reconstruct(Box::new(RunSpec::new(&o, &source, 1))) }
        })
        .collect()
}

/// One line per point of a trade-off on `base` (run folders `base.out/<k>`).
pub fn tradeoff(base: &ReconstructOptions, points: &[TradeoffPoint]) -> Result<Vec<SweepLine>> {
    points
        .iter()
        .enumerate()
        .map(|(k, pt)| {
            let (o, source) = point_options(base, k, pt).with_context(|| format!("trade-off point {:?}", pt.name))?;
            let study = Study::Tradeoff { out: base.out.clone(), point: pt.clone() };
            Ok(SweepLine { study, name: pt.name.clone(), job: Job::Reconstruct(Box::new(RunSpec::new(&o, &source, pt.downscale))) })
        })
        .collect()
}

/// One line per labelling job.
pub fn labels(jobs: &[LabelOptions]) -> Vec<SweepLine> {
    jobs.iter().map(|l| SweepLine { study: Study::Labels, name: l.scene.clone(), job: Job::Label(l.clone()) }).collect()
}

/// Loads every scene the tasks name (a clear error now rather than on a cluster node later; a
/// generated scene such as `default` is rendered into the cache once, before tasks race for it).
pub fn check_scenes(lines: &[SweepLine]) -> Result<()> {
    let mut seen = BTreeSet::new();
    for l in lines {
        let (scene, data) = match &l.job {
            Job::Reconstruct(r) => (&r.scene, &r.data),
            Job::Label(j) => (&j.scene, &j.data),
        };
        if seen.insert((scene.clone(), data.clone())) {
            let mut spec = SceneSpec::find(scene)?;
            if let Some(d) = data {
                spec = spec.with_data_dir(d);
            }
            spec.load_dataset().with_context(|| format!("checking task {:?} of the sweep", l.name))?;
        }
    }
    Ok(())
}

/// Checks the scenes, writes `lines` to the manifest at `path` (after its lines when `append`),
/// and returns what was written with the commands that run it.
pub fn write_plan(path: &Path, lines: &[SweepLine], append: bool) -> Result<String> {
    check_scenes(lines)?;
    manifest::write(path, lines, append)?;
    let total = manifest::read(path)?.len();
    let (m, last) = (path.display(), total - 1);
    Ok(format!(
        "wrote {} tasks to {m} ({total} in all); run them with\n  \
         Slurm:         mkdir -p logs && sbatch --array=0-{last} tools/slurm/sweep.sbatch {m}\n  \
         GNU parallel:  RAYON_NUM_THREADS=1 parallel -j \"$(nproc)\" --joblog sweep.joblog target/release/reconstruct sweep run --manifest {m} --task {{}} ::: $(seq 0 {last})\n  \
         then:          target/release/reconstruct sweep gather --manifest {m}",
        lines.len()
    ))
}

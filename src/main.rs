//! The `reconstruct` command line: parses arguments, calls the library's jobs, prints.

use std::path::PathBuf;

use anyhow::Result;
use clap::{Parser, Subcommand, ValueEnum};
use reconstruct::fit::config::FitConfig;
use reconstruct::jobs::ablation;
use reconstruct::prior::source::PriorSource;
use reconstruct::jobs::reconstruct::{run as run_job, GeometrySource, ReconstructOptions};
use reconstruct::jobs::render::{run, RenderOptions};
use reconstruct::jobs::label::{self, LabelOptions, ViewSelection};
use reconstruct::jobs::sweep::{gather, manifest, plan, task};
use reconstruct::jobs::tradeoff;
use reconstruct::render::view::ShadingMode;

#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

#[derive(Parser)]
#[command(
    name = "reconstruct",
    version,
    about = "Shape, material and light from multi-view images (NVDiffRecMC-style), guided by IDArb labels",
    args_conflicts_with_subcommands = true
)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
    #[command(flatten)]
    reconstruct: ReconstructArgs,
}

#[derive(Clone, Copy, ValueEnum)]
enum Geometry {
    /// The scene's ground-truth mesh.
    Gt,
}

#[derive(Clone, Copy, ValueEnum)]
enum TrainMode {
    /// Monte Carlo when the scene's effects need visibility (shadows, interreflection), else split-sum.
    Auto,
    SplitSum,
    Mc,
}

impl TrainMode {
    /// The fixed mode, or None for auto.
    fn fixed(self) -> Option<ShadingMode> {
        match self {
            TrainMode::Auto => None,
            TrainMode::SplitSum => Some(ShadingMode::SplitSum),
            TrainMode::Mc => Some(ShadingMode::MonteCarlo),
        }
    }
}

/// Optimise materials and light of a scene (the default command).
#[derive(clap::Args)]
struct ReconstructArgs {
    /// Scene name (scenes/NAME.toml) or spec file path.
    #[arg(long, default_value = "default")]
    scene: String,
    /// Data folder overriding the spec's.
    #[arg(long)]
    data: Option<PathBuf>,
    /// Label source of the prior: none, idarb, labels:DIR, oracle, idarb-sim[:LEVEL].
    #[arg(long, default_value = "none")]
    prior: String,
    #[arg(long, value_enum, default_value = "gt")]
    geometry: Geometry,
    /// Shading during optimisation.
    #[arg(long, value_enum, default_value = "auto")]
    mode: TrainMode,
    /// Monte Carlo samples per pixel and strategy (training).
    #[arg(long)]
    spp: Option<u32>,
    /// Cross-bilateral denoiser on the Monte Carlo buffers.
    #[arg(long)]
    denoise: bool,
    #[arg(long)]
    iterations: Option<usize>,
    /// Views per iteration.
    #[arg(long)]
    batch: Option<usize>,
    #[arg(long)]
    texture_res: Option<usize>,
    #[arg(long)]
    light_res: Option<usize>,
    #[arg(long)]
    seed: Option<u64>,
    /// Adam learning rate of the kd/ks textures.
    #[arg(long)]
    lr_material: Option<f64>,
    /// Adam learning rate of the light.
    #[arg(long)]
    lr_light: Option<f64>,
    /// Weight of the light white-balance regulariser (NVDiffRec: 0.005).
    #[arg(long)]
    light_balance: Option<f64>,
    /// Monte Carlo samples per pixel of the evaluation renders.
    #[arg(long, default_value_t = 16)]
    eval_spp: u32,
    /// Run folder (default: runs/<scene>-<prior>-<mode>). A rerun resumes from its checkpoint.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Training views the prior labels (evenly spread; labelling with IDArb is expensive).
    #[arg(long, default_value_t = 100)]
    labelled_views: usize,
    /// Weight of every prior component (albedo, roughness, metallic).
    #[arg(long)]
    prior_weight: Option<f64>,
    /// Weight of the albedo component alone (overrides --prior-weight).
    #[arg(long)]
    prior_albedo: Option<f64>,
    /// Weight of the roughness component alone.
    #[arg(long)]
    prior_roughness: Option<f64>,
    /// Weight of the metallic component alone.
    #[arg(long)]
    prior_metallic: Option<f64>,
    /// IDArb weights folder for --prior idarb (else the IDARB_WEIGHTS variable).
    #[arg(long)]
    idarb_weights: Option<PathBuf>,
    /// Hide the progress bar.
    #[arg(long)]
    quiet: bool,
}

#[derive(Clone, Copy, ValueEnum)]
enum Mode {
    SplitSum,
    Mc,
    Both,
}

#[derive(Subcommand)]
enum Command {
    /// The prior ablation in one command: the same run with no prior, simulated IDArb labels and
    /// the ground truth as labels, side by side (a few minutes on the default scene).
    Ablation {
        #[arg(long, default_value = "default")]
        scene: String,
        #[arg(long, default_value_t = 300)]
        iterations: usize,
        /// Shading during optimisation.
        #[arg(long, value_enum, default_value = "auto")]
        mode: TrainMode,
        /// Monte Carlo samples per pixel and strategy (fewer than a full run's 16: a miniature).
        #[arg(long, default_value_t = 4)]
        spp: u32,
        /// idarb-sim levels of a prior-quality sweep (e.g. 0,0.5,1,2); none by default.
        #[arg(long, value_delimiter = ',')]
        sweep: Vec<f64>,
        #[arg(long, default_value_t = 8)]
        eval_spp: u32,
        /// Output folder (default: runs/ablation-<scene>).
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// Sweeps as manifests of independent tasks for Slurm job arrays, GNU parallel or Kubernetes
    /// Indexed Jobs: plan them, run one, gather the tables (docs/scale.md).
    Sweep {
        #[command(subcommand)]
        action: SweepAction,
    },
    /// Label training views (the IDArb network; oracle or idarb-sim need no weights) into a
    /// folder that `--prior labels:DIR` reads.
    Label {
        #[arg(long, default_value = "default")]
        scene: String,
        /// Data folder overriding the spec's.
        #[arg(long)]
        data: Option<PathBuf>,
        /// idarb, oracle or idarb-sim[:LEVEL].
        #[arg(long, default_value = "idarb")]
        source: String,
        /// How many training views, evenly spread (as --labelled-views).
        #[arg(long, default_value_t = 100)]
        views: usize,
        /// These views instead (e.g. train_003; repeatable).
        #[arg(long = "view")]
        names: Vec<String>,
        #[arg(long)]
        out: PathBuf,
        /// IDArb weights folder (else the IDARB_WEIGHTS variable).
        #[arg(long)]
        idarb_weights: Option<PathBuf>,
        /// Seed of simulated labels (the run's --seed).
        #[arg(long, default_value_t = 0)]
        seed: u64,
    },
    /// Render a scene's ground truth under probes and compare with the dataset's images.
    Render {
        /// Scene name (scenes/NAME.toml) or spec file path.
        #[arg(long, default_value = "default")]
        scene: String,
        /// Data folder overriding the spec's.
        #[arg(long)]
        data: Option<PathBuf>,
        /// View names (e.g. test_049); default: every test view.
        #[arg(long = "view")]
        views: Vec<String>,
        /// `train`, a test-probe name, or a .hdr/.exr path; default: the training probe and every test probe.
        #[arg(long = "probe")]
        probes: Vec<String>,
        #[arg(long, value_enum, default_value = "both")]
        mode: Mode,
        /// Monte Carlo samples per pixel (per strategy).
        #[arg(long, default_value_t = 32)]
        spp: u32,
        /// Primary rays per pixel side (box-filtered).
        #[arg(long, default_value_t = 2)]
        supersample: usize,
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Output folder (default: runs/render-<scene>).
        #[arg(long)]
        out: Option<PathBuf>,
    },
}

#[derive(clap::Args)]
struct ManifestOut {
    /// The manifest to write (JSON lines; task N is line N, from 0).
    #[arg(long, default_value = "sweep.jsonl")]
    manifest: PathBuf,
    /// Add the lines to an existing manifest instead of replacing it.
    #[arg(long)]
    append: bool,
}

#[derive(Subcommand)]
enum SweepAction {
    /// Write the manifest of a sweep (one line per run).
    Plan {
        #[command(subcommand)]
        study: PlanStudy,
    },
    /// Run one task of a manifest: --task N, else $SLURM_ARRAY_TASK_ID, else $JOB_COMPLETION_INDEX.
    Run {
        #[arg(long, default_value = "sweep.jsonl")]
        manifest: PathBuf,
        #[arg(long)]
        task: Option<usize>,
        /// Run it again even when it finished (an unfinished run resumes from its checkpoint anyway).
        #[arg(long)]
        force: bool,
    },
    /// Write the tables of the finished runs and name the missing or failed ones.
    Gather {
        #[arg(long, default_value = "sweep.jsonl")]
        manifest: PathBuf,
    },
}

#[derive(Subcommand)]
enum PlanStudy {
    /// The prior ablation (as `reconstruct ablation`), one study per scene in RUNS/ablation-<scene>.
    Ablation {
        #[arg(long, value_delimiter = ',', default_value = "default")]
        scenes: Vec<String>,
        /// Label sources of the table.
        #[arg(long, value_delimiter = ',', default_value = "none,idarb-sim,oracle")]
        sources: Vec<String>,
        #[arg(long, default_value_t = 300)]
        iterations: usize,
        #[arg(long, value_enum, default_value = "auto")]
        mode: TrainMode,
        #[arg(long, default_value_t = 4)]
        spp: u32,
        /// idarb-sim levels of a prior-quality sweep (e.g. 0,0.5,1,1.5,2).
        #[arg(long, value_delimiter = ',')]
        sweep: Vec<f64>,
        #[arg(long, default_value_t = 8)]
        eval_spp: u32,
        /// Relight at most this many test views (default: all).
        #[arg(long)]
        eval_test_views: Option<usize>,
        /// Training views the prior labels (default: all).
        #[arg(long)]
        labelled_views: Option<usize>,
        #[arg(long, default_value = "runs")]
        runs: PathBuf,
        #[command(flatten)]
        target: ManifestOut,
    },
    /// The time/accuracy trade-off (as `--example tradeoff`) in RUNS/tradeoff-<scene>.
    Tradeoff {
        #[arg(long, default_value = "default")]
        scene: String,
        /// Base iteration count (the sweep also runs a third and three times as many).
        #[arg(long, default_value_t = 200)]
        iterations: usize,
        /// Test views relit per point.
        #[arg(long, default_value_t = 2)]
        test_views: usize,
        #[arg(long, default_value_t = 8)]
        eval_spp: u32,
        #[arg(long, default_value = "runs")]
        runs: PathBuf,
        #[command(flatten)]
        target: ManifestOut,
    },
    /// Labelling jobs (`reconstruct label`), one per scene, into LABELS/<scene>.
    Labels {
        #[arg(long, value_delimiter = ',', default_value = "default")]
        scenes: Vec<String>,
        #[arg(long, default_value = "idarb")]
        source: String,
        #[arg(long, default_value_t = 100)]
        views: usize,
        #[arg(long, default_value = "labels")]
        labels: PathBuf,
        #[arg(long)]
        idarb_weights: Option<PathBuf>,
        #[command(flatten)]
        target: ManifestOut,
    },
}

fn sweep(action: SweepAction) -> Result<()> {
    match action {
        SweepAction::Plan { study } => {
            let (lines, target) = match study {
                PlanStudy::Ablation { scenes, sources, iterations, mode, spp, sweep, eval_spp, eval_test_views, labelled_views, runs, target } => {
                    let sources = sources.iter().map(|s| s.parse()).collect::<Result<Vec<PriorSource>>>()?;
                    let fixed_mode = mode.fixed();
                    let fit = FitConfig { mode: fixed_mode.unwrap_or(ShadingMode::SplitSum), iterations, spp, ..FitConfig::default() };
                    let mut lines = Vec::new();
                    for scene in &scenes {
                        let mut base = ReconstructOptions::new(scene, fit.clone(), eval_spp, runs.join(format!("ablation-{scene}")));
                        base.auto_mode = fixed_mode.is_none();
                        base.eval_test_views = eval_test_views;
                        base.labelled_views = labelled_views.unwrap_or(usize::MAX);
                        lines.extend(plan::ablation(&ablation::AblationOptions { base, sources: sources.clone(), sweep: sweep.clone() }));
                    }
                    (lines, target)
                }
                PlanStudy::Tradeoff { scene, iterations, test_views, eval_spp, runs, target } => {
                    let mut base = ReconstructOptions::new(&scene, FitConfig::default(), eval_spp, runs.join(format!("tradeoff-{scene}")));
                    base.eval_test_views = Some(test_views);
                    (plan::tradeoff(&base, &tradeoff::default_points(iterations))?, target)
                }
                PlanStudy::Labels { scenes, source, views, labels, idarb_weights, target } => {
                    let jobs: Vec<LabelOptions> = scenes
                        .iter()
                        .map(|scene| LabelOptions { scene: scene.clone(), data: None, source: source.clone(), views: ViewSelection::Count(views), out: labels.join(scene), idarb_weights: idarb_weights.clone(), seed: 0 })
                        .collect();
                    (plan::labels(&jobs), target)
                }
            };
            plan::check_scenes(&lines)?;
            manifest::write(&target.manifest, &lines, target.append)?;
            let total = manifest::read(&target.manifest)?.len();
            println!("wrote {} tasks to {} ({total} in all)", lines.len(), target.manifest.display());
            println!("Slurm:        mkdir -p logs && sbatch --array=0-{} tools/slurm/sweep.sbatch {}", total - 1, target.manifest.display());
            println!("one machine:  parallel -j 2 --joblog sweep.joblog target/release/reconstruct sweep run --manifest {} --task {{}} ::: $(seq 0 {})", target.manifest.display(), total - 1);
        }
        SweepAction::Run { manifest: path, task: explicit, force } => {
            let lines = manifest::read(&path)?;
            let n = manifest::task_index(explicit, |k| std::env::var(k).ok(), lines.len())?;
            let line = &lines[n];
            eprintln!("task {n} of {}: {} → {}", lines.len(), line.name, line.job.out().display());
            if !task::run(line, force)? {
                println!("task {n} ({}) already finished: {}", line.name, task::status(line));
            }
        }
        SweepAction::Gather { manifest: path } => {
            let lines = manifest::read(&path)?;
            let g = gather::gather(&lines)?;
            for (file, md) in &g.tables {
                println!("{md}\nwrote {}\n", file.display());
            }
            if g.labels > 0 {
                println!("{} label folders made", g.labels);
            }
            if !g.problems.is_empty() {
                for p in &g.problems {
                    eprintln!("{p}");
                }
                anyhow::bail!("{} of {} tasks of {} have no result (listed above)", g.problems.len(), lines.len(), path.display());
            }
        }
    }
    Ok(())
}

fn reconstruct(a: ReconstructArgs) -> Result<()> {
    let fixed_mode = a.mode.fixed();
    let mut fit = FitConfig { mode: fixed_mode.unwrap_or(ShadingMode::SplitSum), denoise: a.denoise, ..FitConfig::default() };
    if let Some(v) = a.spp { fit.spp = v; }
    if let Some(v) = a.iterations { fit.iterations = v; }
    if let Some(v) = a.batch { fit.batch = v; }
    if let Some(v) = a.texture_res { fit.texture_res = v; }
    if let Some(v) = a.light_res { fit.light_res = v; }
    if let Some(v) = a.seed { fit.seed = v; }
    if let Some(v) = a.lr_material { fit.lr_material = v; }
    if let Some(v) = a.lr_light { fit.lr_light = v; }
    if let Some(v) = a.light_balance { fit.regularizers.light_white_balance = v; }
    if let Some(v) = a.prior_weight { fit.prior.albedo = v; fit.prior.roughness = v; fit.prior.metallic = v; }
    if let Some(v) = a.prior_albedo { fit.prior.albedo = v; }
    if let Some(v) = a.prior_roughness { fit.prior.roughness = v; }
    if let Some(v) = a.prior_metallic { fit.prior.metallic = v; }
    let prior: PriorSource = a.prior.parse()?;
    let mode_tag = match fixed_mode { None => "auto", Some(ShadingMode::SplitSum) => "splitsum", Some(ShadingMode::MonteCarlo) => "mc" };
    let out = a.out.unwrap_or_else(|| PathBuf::from(format!("runs/{}-{}-{mode_tag}", a.scene, a.prior.replace([':', '/'], "_"))));
    let geometry = match a.geometry { Geometry::Gt => GeometrySource::GroundTruth };
    let opts = ReconstructOptions { scene: a.scene, data: a.data, geometry, fit, eval_spp: a.eval_spp, out: out.clone(), progress: !a.quiet, labelled_views: a.labelled_views, idarb_weights: a.idarb_weights, effects_override: None, eval_test_views: None, auto_mode: fixed_mode.is_none() };
    let report = run_job(&opts, &prior)?;
    println!("{}", report.summary());
    println!("wrote {}", out.display());
    Ok(())
}

fn main() -> Result<()> {
    let cli = Cli::parse();
    let Some(command) = cli.command else { return reconstruct(cli.reconstruct) };
    match command {
        Command::Ablation { scene, iterations, mode, spp, sweep, eval_spp, out } => {
            let out = out.unwrap_or_else(|| ablation::default_out(&scene));
            let fixed_mode = mode.fixed();
            let fit = FitConfig { mode: fixed_mode.unwrap_or(ShadingMode::SplitSum), iterations, spp, ..FitConfig::default() };
            let base = ReconstructOptions { auto_mode: fixed_mode.is_none(), ..ReconstructOptions::new(&scene, fit, eval_spp, out.clone()) };
            let sources = vec![PriorSource::None, PriorSource::IdarbSim(1.0), PriorSource::Oracle];
            let report = ablation::run(&ablation::AblationOptions { base, sources, sweep })?;
            println!("{}", report.markdown());
            println!("wrote {}", out.join("ablation.md").display());
        }
        Command::Sweep { action } => sweep(action)?,
        Command::Label { scene, data, source, views, names, out, idarb_weights, seed } => {
            let views = if names.is_empty() { ViewSelection::Count(views) } else { ViewSelection::Names(names) };
            let report = label::run(&LabelOptions { scene, data, source, views, out: out.clone(), idarb_weights, seed })?;
            println!("labelled {} views of {} with {} in {:.0} s; use --prior labels:{}", report.views.len(), report.scene, report.source, report.seconds, out.display());
        }
        Command::Render { scene, data, views, probes, mode, spp, supersample, seed, out } => {
            let modes = match mode {
                Mode::SplitSum => vec![ShadingMode::SplitSum],
                Mode::Mc => vec![ShadingMode::MonteCarlo],
                Mode::Both => vec![ShadingMode::SplitSum, ShadingMode::MonteCarlo],
            };
            let out = out.unwrap_or_else(|| PathBuf::from(format!("runs/render-{scene}")));
            let opts = RenderOptions { scene, data, views, probes, modes, spp, supersample, seed, out: out.clone() };
            let report = run(&opts)?;
            println!("| view | probe | mode | ms | PSNR vs dataset (dB) |\n|---|---|---|---:|---:|");
            for r in &report.renders {
                let score = r.psnr_db.map_or("-".to_string(), |p| format!("{p:.2}"));
                println!("| {} | {} | {:?} | {:.0} | {score} |", r.view, r.probe, r.mode, 1e3 * r.seconds);
            }
            for mode in &opts.modes {
                if let Some(mean) = report.mean_psnr(*mode) {
                    println!("mean PSNR {mode:?}: {mean:.2} dB");
                }
            }
            for (stage, s) in &report.stage_seconds {
                println!("{stage}: {s:.2} s");
            }
            println!("wrote {}", out.join("report.json").display());
        }
    }
    Ok(())
}

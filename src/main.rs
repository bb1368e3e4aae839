//! The `reconstruct` command line: parses arguments, calls the library's jobs, prints.

use std::path::PathBuf;

use anyhow::Result;
use clap::{Parser, Subcommand, ValueEnum};
use reconstruct::fit::config::FitConfig;
use reconstruct::jobs::overrides::{GeometryPassOverrides, SettingOverrides};
use reconstruct::jobs::run_folder::default_run_folder;
use reconstruct::jobs::ablation;
use reconstruct::prior::source::PriorSource;
use reconstruct::jobs::reconstruct::{run as run_job, GeometrySource, ReconstructOptions};
use reconstruct::jobs::render::{run, RenderOptions};
use reconstruct::jobs::label::{self, LabelOptions, ViewSelection};
use reconstruct::jobs::sweep::plan::{self as sweep_plan, PlanArgs};
use reconstruct::jobs::sweep::{gather, manifest, task};
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
    /// The scene's mesh when its data has one, else reconstructed from the images.
    Auto,
    /// The scene's ground-truth mesh.
    Gt,
    /// Reconstructed from the training images: visual hull of the masks, then the geometry pass.
    Reconstruct,
}

impl Geometry {
    fn source(self) -> GeometrySource {
        match self {
            Geometry::Auto => GeometrySource::Auto,
            Geometry::Gt => GeometrySource::GroundTruth,
            Geometry::Reconstruct => GeometrySource::Reconstruct,
        }
    }
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
    /// Where the mesh comes from.
    #[arg(long, value_enum, default_value = "auto")]
    geometry: Geometry,
    /// Shading during optimisation.
    #[arg(long, value_enum, default_value = "auto")]
    mode: TrainMode,
    #[command(flatten)]
    settings: SettingOverrides,
    /// Monte Carlo samples per pixel of the evaluation renders.
    #[arg(long, default_value_t = 16)]
    eval_spp: u32,
    /// Relight at most this many test views (default: all).
    #[arg(long)]
    eval_test_views: Option<usize>,
    /// Run folder (default: runs/<scene>-<geometry>-<prior>-<mode>-<digest of the settings>, docs/runs.md).
    /// A rerun with the same settings resumes from its checkpoint.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Training views the prior labels (evenly spread; labelling with IDArb is expensive).
    #[arg(long, default_value_t = 100)]
    labelled_views: usize,
    /// Train the materials on views N times smaller (box-filtered; N must divide the views' size).
    /// The geometry pass and the evaluation keep their resolutions.
    #[arg(long, default_value_t = 1)]
    downscale: usize,
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
        /// Where the mesh comes from (reconstructed: once per prior, whose normal labels the pass
        /// uses, and once without for the `none` row; known: one mesh for all rows).
        #[arg(long, value_enum, default_value = "reconstruct")]
        geometry: Geometry,
        #[command(flatten)]
        geometry_pass: GeometryPassOverrides,
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
        /// Move the vertices in the material pass too, through the shading normal (Monte Carlo
        /// training only; docs/geometry.md).
        #[arg(long)]
        refine_geometry: bool,
        /// Learn a tangent-space normal map with the textures, as NVDiffRecMC's second pass (Monte
        /// Carlo training only; docs/model.md, *Normal map*).
        #[arg(long)]
        normal_map: bool,
        #[command(flatten)]
        plan: PlanArgs,
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
        #[command(flatten)]
        plan: PlanArgs,
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

/// Run a sweep: plan, run one task, gather.
#[derive(Subcommand)]
enum SweepAction {
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

fn sweep(action: SweepAction) -> Result<()> {
    match action {
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
    let prior: PriorSource = a.prior.parse()?;
    let fixed_mode = a.mode.fixed();
    let mut opts = ReconstructOptions::new(&a.scene, a.settings.fit_config(fixed_mode), a.eval_spp, PathBuf::new());
    opts.data = a.data;
    opts.geometry = a.geometry.source();
    opts.geometry_pass = a.settings.geometry_pass();
    opts.progress = !a.quiet;
    opts.labelled_views = a.labelled_views;
    opts.downscale = a.downscale;
    opts.idarb_weights = a.idarb_weights;
    opts.auto_mode = fixed_mode.is_none();
    opts.eval_test_views = a.eval_test_views;
    opts.out = match a.out {
        Some(out) => out,
        None => default_run_folder(&opts, &prior)?,
    };
    let report = run_job(&opts, &prior)?;
    println!("{}", report.summary());
    println!("wrote {}", opts.out.display());
    Ok(())
}

fn main() -> Result<()> {
    reconstruct::allocator::keep_freed_pages();
    let cli = Cli::parse();
    let Some(command) = cli.command else { return reconstruct(cli.reconstruct) };
    match command {
        Command::Ablation { scene, iterations, geometry, geometry_pass, mode, spp, sweep, eval_spp, out, refine_geometry, normal_map, plan } => {
            let out = out.unwrap_or_else(|| ablation::default_out(&scene));
            let fixed_mode = mode.fixed();
            let fit = FitConfig { mode: fixed_mode.unwrap_or(ShadingMode::SplitSum), iterations, spp, refine_geometry, normal_map, ..FitConfig::default() };
            let geometry_pass = geometry_pass.geometry_pass();
            let base = ReconstructOptions { auto_mode: fixed_mode.is_none(), geometry: geometry.source(), geometry_pass, ..ReconstructOptions::new(&scene, fit, eval_spp, out.clone()) };
            let sources = ablation::default_sources();
            let opts = ablation::AblationOptions { base, sources, sweep };
            if let Some(path) = plan.plan {
                println!("{}", sweep_plan::write_plan(&path, &sweep_plan::ablation(&opts), plan.append)?);
                return Ok(());
            }
            let report = ablation::run(&opts)?;
            println!("{}", report.markdown());
            println!("wrote {}", out.join("ablation.md").display());
        }
        Command::Sweep { action } => sweep(action)?,
        Command::Label { scene, data, source, views, names, out, idarb_weights, seed, plan } => {
            let views = if names.is_empty() { ViewSelection::Count(views) } else { ViewSelection::Names(names) };
            let opts = LabelOptions { scene, data, source, views, out: out.clone(), idarb_weights, seed };
            if let Some(path) = plan.plan {
                println!("{}", sweep_plan::write_plan(&path, &sweep_plan::labels(&[opts]), plan.append)?);
                return Ok(());
            }
            let report = label::run(&opts)?;
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

//! Relight a finished run: render chosen views of its scene with the learned mesh and textures
//! under any light probes, to PNG (sRGB) and EXR (linear), plus a contact sheet.
//!
//! cargo run --release --example relight -- RUN_FOLDER PROBE.hdr [PROBE.exr ...]
//!     [--views test_024,test_049] [--strength 1] [--spp 32] [--supersample 2] [--out DIR]
//!
//! The views default to the scene's test views; the output folder to RUN_FOLDER/relight.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use clap::Parser;
use reconstruct::fit::export::write_render;
use reconstruct::geometry::bvh::Bvh;
use reconstruct::geometry::obj::load_obj;
use reconstruct::report::contact_sheet::contact_sheet;
use reconstruct::image::io::write_png;
use reconstruct::material::texture_maps::MaterialTextures;
use reconstruct::render::effects::Effects;
use reconstruct::render::view::{render_view_with, PreparedLight, RenderSettings, ShadingMode};
use reconstruct::scene::dataset::Dataset;
use reconstruct::scene::probe::Probe;

#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

#[derive(Parser)]
struct Args {
    /// A run folder written by `reconstruct` (has model/ and report.json).
    run: PathBuf,
    /// Light probes (.hdr or .exr lat-long, Blender orientation).
    #[arg(required = true)]
    probes: Vec<PathBuf>,
    /// Comma-separated view names; default: every test view of the run's scene.
    #[arg(long, value_delimiter = ',')]
    views: Vec<String>,
    #[arg(long, default_value_t = 1.0)]
    strength: f32,
    #[arg(long, default_value_t = 32)]
    spp: u32,
    #[arg(long, default_value_t = 2)]
    supersample: usize,
    #[arg(long)]
    out: Option<PathBuf>,
}

#[derive(serde::Deserialize)]
struct RunReport {
    data_dir: PathBuf,
    effects: EffectsField,
}

#[derive(serde::Deserialize)]
struct EffectsField {
    effects: Effects,
}

fn read_report(run: &Path) -> Result<RunReport> {
    let path = run.join("report.json");
    let text = std::fs::read_to_string(&path).with_context(|| format!("{} is not a finished run folder (no report.json)", run.display()))?;
    serde_json::from_str(&text).with_context(|| format!("{}: not a reconstruct report", path.display()))
}

fn main() -> Result<()> {
    reconstruct::allocator::keep_freed_pages();
    let args = Args::parse();
    let report = read_report(&args.run)?;
    let model = args.run.join("model");
    let mesh = load_obj(model.join("model.obj")).with_context(|| format!("loading the learned mesh of {}", args.run.display()))?;
    let textures = MaterialTextures::load_for(&model, &mesh)?;
    let dataset = Dataset::load(&report.data_dir).with_context(|| format!("loading the run's scene data {}", report.data_dir.display()))?;
    let views = if args.views.is_empty() {
        dataset.test.iter().collect::<Vec<_>>()
    } else {
        args.views.iter().map(|n| dataset.view(n)).collect::<Result<Vec<_>>>()?
    };
    if views.is_empty() {
        bail!("no views to render: the scene has no test views; pass --views");
    }
    let out = args.out.clone().unwrap_or_else(|| args.run.join("relight"));
    let bvh = Bvh::build(&mesh);
    let settings = RenderSettings { mode: ShadingMode::MonteCarlo, spp: args.spp, supersample: args.supersample, seed: 0, effects: report.effects.effects };
    let materials = &textures;
    let mut tiles = Vec::new();
    for path in &args.probes {
        let probe = Probe::load(path, args.strength)?;
        let light = PreparedLight::from_probe(&probe);
        for view in &views {
            let img = render_view_with(&mesh, &bvh, &light, &view.camera, &settings, materials);
            let stem = format!("{}_{}", view.name, probe.name);
            write_render(&out, &stem, &img)?;
            println!("wrote {}", out.join(format!("{stem}.png")).display());
            tiles.push((stem, img));
        }
    }
    let columns = views.len().min(8);
    let sheet = contact_sheet(&tiles, columns, 192);
    let sheet_path = out.join("contact_sheet.png");
    write_png(&sheet_path, &sheet)?;
    println!("wrote {}", sheet_path.display());
    Ok(())
}

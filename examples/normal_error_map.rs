//! Where a reconstructed mesh's shading normals are wrong. The evaluation's normal error (the
//! angle between the mesh's interpolated normal and the dataset's `normal.png`, on the test
//! views, over the pixels both cover) is one mean; this splits it by what the picture shows at
//! each pixel, to tell apart errors of different causes:
//! - how dark the pixel is for its albedo (target luminance over albedo luminance: shadowed
//!   pixels are where a shading model without visibility must bend the surface to match);
//! - how far it is from an outline or a depth step of the ground truth (in pixels);
//! - whether the reconstruction lies in front of the ground truth's depth there, on it, or behind
//!   it (a concavity the mesh fills, a surface in the right place, a part it lacks);
//! - the size of the error itself.
//!
//! Each table gives the pixels' share, their mean error, and their shares of the summed and of the
//! squared error. `--map DIR` writes one picture per test view: the error (blue 0° to orange 40°
//! and more) beside the view, three times enlarged.
//!
//!     cargo run --release --example normal_error_map -- MESH.obj [--scene nerfactor_hotdog] [--map DIR]
//!
//! MESH is a run's `model/model.obj` or what `bench_geometry --save` wrote. The scene's test views
//! need `normal.png`; the darkness and depth tables need `albedo.png` and `depth.exr`, and are left
//! out without them.

use anyhow::{bail, Result};
use clap::Parser;
use glam::Vec3;
use reconstruct::color::luminance;
use reconstruct::geometry::bvh::Bvh;
use reconstruct::geometry::obj::load_obj_geometry;
use reconstruct::image::io::write_png;
use reconstruct::image::Image;
use reconstruct::render::gbuffer::GBuffer;
use reconstruct::scene::SceneSpec;
use reconstruct::scene_data::ground_truth::ground_truth_mesh;

#[derive(Parser)]
struct Args {
    /// The reconstructed mesh (OBJ, in the dataset's frame).
    mesh: std::path::PathBuf,
    /// Scene name or spec file.
    #[arg(long, default_value = "nerfactor_hotdog")]
    scene: String,
    /// Write one error picture per test view into this folder.
    #[arg(long)]
    map: Option<std::path::PathBuf>,
}

/// Depth steps: neighbours whose planar depth differs by more than this share of their depth
/// (or where one is background). 2 % is well above the change between neighbours on a surface
/// seen at 60° from a 256-pixel view (under 1 %) and below the step at an occluding edge.
const DEPTH_STEP: f32 = 0.02;
/// In front of / behind: more than this share of the bounding-box diagonal, the geometry metrics'
/// threshold (docs/geometry.md, *Choices and their reasons*).
const DEPTH_TOLERANCE: f32 = 0.01;
/// The error picture's colour scale ends here.
const MAP_FULL_SCALE_DEG: f64 = 40.0;

/// Pixels falling into one bin of a table.
#[derive(Default, Clone, Copy)]
struct Bin {
    n: usize,
    sum: f64,
    sum2: f64,
}

/// A table: labels and the bin each pixel falls into.
struct Table {
    title: &'static str,
    labels: &'static [&'static str],
    bins: Vec<Bin>,
}

impl Table {
    fn new(title: &'static str, labels: &'static [&'static str]) -> Table {
        Table { title, labels, bins: vec![Bin::default(); labels.len()] }
    }

    fn add(&mut self, bin: usize, error: f64) {
        let b = &mut self.bins[bin];
        b.n += 1;
        b.sum += error;
        b.sum2 += error * error;
    }

    fn print(&self) {
        let n: usize = self.bins.iter().map(|b| b.n).sum();
        if n == 0 {
            return;
        }
        let sum: f64 = self.bins.iter().map(|b| b.sum).sum();
        let sum2: f64 = self.bins.iter().map(|b| b.sum2).sum();
        println!("\n{}\n\n| | pixels | share | mean error | share of the summed error | share of the squared error |\n|---|---:|---:|---:|---:|---:|", self.title);
        for (label, b) in self.labels.iter().zip(&self.bins) {
            let mean = b.sum / b.n.max(1) as f64;
            println!("| {label} | {} | {:.3} | {mean:.2}° | {:.3} | {:.3} |", b.n, b.n as f64 / n as f64, b.sum / sum, b.sum2 / sum2);
        }
    }
}

/// Per pixel, the chessboard distance in pixels to the nearest depth step of `depth`, up to `cap`.
fn distance_to_depth_steps(depth: &Image, cap: usize) -> Vec<usize> {
    let (w, h) = (depth.width, depth.height);
    let d = |x: usize, y: usize| depth.data[y * w + x];
    let is_step = |x: usize, y: usize| {
        let here = d(x, y);
        let neighbours = [(x.wrapping_sub(1), y), (x + 1, y), (x, y.wrapping_sub(1)), (x, y + 1)];
        neighbours.iter().filter(|&&(nx, ny)| nx < w && ny < h).any(|&(nx, ny)| {
            let there = d(nx, ny);
            (here > 0.0) != (there > 0.0) || (here > 0.0 && (here - there).abs() > DEPTH_STEP * here)
        })
    };
    let mut dist = vec![cap; w * h];
    for y in 0..h {
        for x in 0..w {
            if !is_step(x, y) {
                continue;
            }
            for yy in y.saturating_sub(cap)..(y + cap + 1).min(h) {
                for xx in x.saturating_sub(cap)..(x + cap + 1).min(w) {
                    let c = yy.abs_diff(y).max(xx.abs_diff(x));
                    dist[yy * w + xx] = dist[yy * w + xx].min(c);
                }
            }
        }
    }
    dist
}

/// The error picture (left) beside the view's colour (right), enlarged `zoom` times.
fn error_picture(errors: &[Option<f64>], colour: &Image, zoom: usize) -> Image {
    let (w, h) = (colour.width, colour.height);
    let mut out = Image::new(2 * w * zoom, h * zoom, 3);
    for y in 0..h * zoom {
        for x in 0..2 * w * zoom {
            let i = (y / zoom) * w + (x % (w * zoom)) / zoom;
            let rgb = if x < w * zoom {
                errors[i].map_or([0.0; 3], |e| {
                    let t = (e / MAP_FULL_SCALE_DEG).min(1.0) as f32;
                    [t, 0.3 * t, 1.0 - t]
                })
            } else {
                colour.rgb(i).max(Vec3::ZERO).powf(1.0 / 2.2).to_array()
            };
            out.pixel_mut(x, y).copy_from_slice(&rgb);
        }
    }
    out
}

fn main() -> Result<()> {
    let args = Args::parse();
    let spec = SceneSpec::find(&args.scene)?;
    let dataset = spec.load_dataset()?;
    let (mesh, _) = load_obj_geometry(&args.mesh)?;
    if mesh.triangles.is_empty() {
        bail!("{} has no triangles", args.mesh.display());
    }
    let bvh = Bvh::build(&mesh);
    let (diagonal, diagonal_of) = match ground_truth_mesh(&spec) {
        Ok(gt) => (gt.bounds().map_or(0.0, |(lo, hi)| (hi - lo).length()), "the ground truth's"),
        Err(_) => (mesh.bounds().map_or(0.0, |(lo, hi)| (hi - lo).length()), "the reconstruction's (no ground-truth mesh)"),
    };
    let mut darkness = Table::new("By darkness (target luminance / albedo luminance)", &["below 0.25", "0.25–0.5", "0.5–1", "1–2", "2 and above"]);
    let mut outline = Table::new("By distance to an outline or depth step of the ground truth", &["0–2 px", "3–5 px", "6 px and more"]);
    let mut placement = Table::new(
        "By depth against depth.exr (1 % of the bounding-box diagonal)",
        &["reconstruction in front of the ground truth", "on it", "behind it"],
    );
    let mut size = Table::new("By the error itself", &["below 5°", "5–10°", "10–20°", "20–40°", "40° and more"]);
    let mut all = Vec::new();
    for (k, view) in dataset.test.iter().enumerate() {
        if !view.has_normal() {
            bail!("test view {} has no normal.png ({}): nothing to score", view.name, view.dir.display());
        }
        let g = GBuffer::trace(&mesh, &bvh, &view.camera);
        let normal = view.load_normal()?;
        let colour = view.load_rgba()?;
        let albedo = view.has_albedo().then(|| view.load_albedo()).transpose()?;
        let depth = view.load_depth_if_present()?;
        let steps = depth.as_ref().map(|d| distance_to_depth_steps(d, 6));
        let mut errors = vec![None; g.surfels.len()];
        for (i, surfel) in g.surfels.iter().enumerate() {
            let (Some(s), true) = (surfel, normal.data[4 * i + 3] >= 0.5) else { continue };
            let truth = Vec3::from_slice(&normal.data[4 * i..4 * i + 3]);
            let e = (s.normal.normalize().dot(truth).clamp(-1.0, 1.0) as f64).acos().to_degrees();
            errors[i] = Some(e);
            all.push(e);
            if let Some(albedo) = &albedo {
                let ratio = luminance(colour.rgb(i)) / luminance(albedo.rgb(i)).max(1e-3);
                darkness.add([0.25, 0.5, 1.0, 2.0].iter().take_while(|&&t| ratio >= t).count(), e);
            }
            if let (Some(depth), Some(steps)) = (&depth, &steps) {
                outline.add(match steps[i] {
                    0..=2 => 0,
                    3..=5 => 1,
                    _ => 2,
                }, e);
                let ahead = depth.data[i] - s.depth;
                placement.add(if ahead > DEPTH_TOLERANCE * diagonal { 0 } else if ahead >= -DEPTH_TOLERANCE * diagonal { 1 } else { 2 }, e);
            }
            size.add([5.0, 10.0, 20.0, 40.0].iter().take_while(|&&t| e >= t).count(), e);
        }
        if let Some(dir) = &args.map {
            std::fs::create_dir_all(dir)?;
            write_png(&dir.join(format!("{}.png", view.name)), &error_picture(&errors, &colour, 3))?;
        }
        eprintln!("{} of {} test views scored", k + 1, dataset.test.len());
    }
    if all.is_empty() {
        bail!("{} covers no pixel of the test views' normal maps", args.mesh.display());
    }
    all.sort_by(f64::total_cmp);
    let mean = all.iter().sum::<f64>() / all.len() as f64;
    println!("{} pixels on {} test views: mean {mean:.2}°, median {:.2}°, 90th percentile {:.2}°", all.len(), dataset.test.len(), all[all.len() / 2], all[all.len() * 9 / 10]);
    println!("(depth tolerance: 1 % of {diagonal_of} bounding-box diagonal, {diagonal:.3})");
    for t in [&darkness, &outline, &placement, &size] {
        t.print();
    }
    Ok(())
}

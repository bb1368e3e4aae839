//! The library entry point: per-view IDArb labels, from the cache when present, else from the
//! network (views split into groups of at most `views_per_group`, each group denoised jointly).
use super::labels_cache;
use super::pipeline_idarbdiffusion::{IdarbPipeline, NUM_DOMAINS};
use super::preprocess::{default_pose, prepare_view, unframe, Framing};
use super::scheduling_ddim::DdimScheduler;
use super::unet_dr2d_condition::unet_forward_flops;
use super::weights::{floats_hash, resolve_weights_dir, WeightFiles, NO_WEIGHTS_MESSAGE};
use crate::image::Image;
use crate::prior::view_labels::ViewLabels;
use crate::rng::Sampler;
use anyhow::{bail, Context, Result};
use candle_core::{Device, Tensor};
use serde::Serialize;
use std::path::Path;
use std::time::Instant;

/// How the input RGBA values are encoded. IDArb consumes sRGB-encoded images (PNG values).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub enum InputEncoding {
    Srgb,
    /// Linear RGB; converted with the exact sRGB curve before the network.
    Linear,
}

#[derive(Debug, Clone, Serialize)]
pub struct IdarbOptions {
    /// Side of the square network input (official: 512). A multiple of 8.
    pub target_size: usize,
    /// DDIM steps (official: 50).
    pub steps: usize,
    /// DDIM η (official `main.py`: 1.0).
    pub eta: f32,
    /// Seed of the initial and per-step noise.
    pub seed: u64,
    /// Views denoised jointly (official default 4; memory grows with it).
    pub views_per_group: usize,
    pub input_encoding: InputEncoding,
    /// Show a progress bar and the time estimate.
    #[serde(skip)]
    pub progress: bool,
}

impl Default for IdarbOptions {
    fn default() -> Self {
        Self { target_size: 512, steps: 50, eta: 1.0, seed: 0, views_per_group: 4, input_encoding: InputEncoding::Srgb, progress: true }
    }
}

/// Labels for `views` (RGBA, encoded as `opts.input_encoding`). `poses` are CaPE angles per view
/// (see [`super::preprocess::pose_from_camera_origin`]); None uses the official no-camera pose.
/// Uses `cache_dir` when it holds labels made with the same settings and inputs; otherwise runs
/// the network with the weights in `weights_dir` (or `$IDARB_WEIGHTS`) and fills the cache, its
/// files named `view_0000_albedo.png`, … ([`labels_for_named_views`] names them after the views).
pub fn labels_for_views(views: &[Image], poses: Option<&[[f32; 4]]>, opts: &IdarbOptions, weights_dir: Option<&Path>, cache_dir: &Path) -> Result<Vec<ViewLabels>> {
    labels_for_named_views(views, &labels_cache::default_names(views.len()), poses, opts, weights_dir, cache_dir)
}

/// [`labels_for_views`] with the cache's files named after the views (`names[i]` for view i, e.g.
/// the dataset's `train_003` or image stem `r_3`): `<name>_albedo.png`, `_normal`, `_metallic`,
/// `_roughness` (and `_mask`), the layout `--prior labels:DIR` reads, so `cache_dir` can be
/// passed back as a labels folder.
pub fn labels_for_named_views(views: &[Image], names: &[String], poses: Option<&[[f32; 4]]>, opts: &IdarbOptions, weights_dir: Option<&Path>, cache_dir: &Path) -> Result<Vec<ViewLabels>> {
    if names.len() != views.len() {
        bail!("IDArb: {} names for {} views", names.len(), views.len());
    }
    let poses = resolve_poses(views.len(), poses)?;
    let key = cache_key(views, &poses, opts);
    if let Some(labels) = labels_cache::load(cache_dir, &key)? {
        if labels.len() == views.len() {
            // the same inputs under other names: write the files under these names too
            if let Some((stored, weights)) = labels_cache::names_and_weights(cache_dir)? {
                if stored != names {
                    labels_cache::store(cache_dir, &key, &weights, names, &labels)?;
                }
            }
            return Ok(labels);
        }
    }
    let Some(dir) = resolve_weights_dir(weights_dir) else { bail!("{NO_WEIGHTS_MESSAGE}") };
    let files = WeightFiles::locate(&dir)?;
    let hashes = files.hashes()?;
    let pipeline = files.load(&Device::Cpu)?;
    let labels = run_network(&pipeline, views, &poses, opts)?;
    labels_cache::store(cache_dir, &key, &hashes, names, &labels)?;
    Ok(labels)
}

fn resolve_poses(n: usize, poses: Option<&[[f32; 4]]>) -> Result<Vec<[f32; 4]>> {
    match poses {
        Some(p) if p.len() != n => bail!("IDArb: {} poses for {n} views", p.len()),
        Some(p) => Ok(p.to_vec()),
        None => Ok(vec![default_pose(); n]),
    }
}

fn cache_key(views: &[Image], poses: &[[f32; 4]], opts: &IdarbOptions) -> serde_json::Value {
    serde_json::json!({
        "format": 1,
        "options": opts,
        "views": views.iter().map(|v| format!("{}x{}x{}:{}", v.width, v.height, v.channels, floats_hash(&v.data))).collect::<Vec<_>>(),
        "poses": poses,
    })
}

/// Which views go together: view i joins group i mod G, so each group spans the whole sequence
/// of viewpoints rather than a run of neighbours.
pub fn view_groups(n: usize, per_group: usize) -> Vec<Vec<usize>> {
    let g = n.div_ceil(per_group.max(1)).max(1);
    (0..g).map(|k| (k..n).step_by(g).collect()).filter(|v: &Vec<usize>| !v.is_empty()).collect()
}

/// Standard normal noise of `shape` from a seeded stream (Box–Muller on the crate's sampler).
pub fn gaussian_noise(sampler: &mut Sampler, shape: (usize, usize, usize, usize)) -> Result<Tensor> {
    let n = shape.0 * shape.1 * shape.2 * shape.3;
    let mut v = Vec::with_capacity(n + 1);
    while v.len() < n {
        let (u1, u2) = sampler.next_2d();
        let r = (-2.0 * (1.0 - u1).max(1e-12).ln()).sqrt();
        let a = std::f32::consts::TAU * u2;
        v.push(r * a.cos());
        v.push(r * a.sin());
    }
    v.truncate(n);
    Ok(Tensor::from_vec(v, shape, &Device::Cpu)?)
}

/// Sustained f32 matmul throughput of this machine in FLOP/s (a short measurement).
fn measured_flops_per_second() -> Result<f64> {
    let n = 768;
    let a = Tensor::ones((n, n), candle_core::DType::F32, &Device::Cpu)?;
    a.matmul(&a)?; // warm-up
    let start = Instant::now();
    let reps = 4;
    for _ in 0..reps {
        a.matmul(&a)?;
    }
    Ok(2.0 * (n * n * n * reps) as f64 / start.elapsed().as_secs_f64().max(1e-9))
}

/// Run the network on `views` with the given poses (no cache).
pub fn run_network(pipeline: &IdarbPipeline, views: &[Image], poses: &[[f32; 4]], opts: &IdarbOptions) -> Result<Vec<ViewLabels>> {
    let t = opts.target_size;
    let prepared = views
        .iter()
        .enumerate()
        .map(|(i, v)| {
            let v = match opts.input_encoding {
                InputEncoding::Srgb => v.clone(),
                InputEncoding::Linear => v.map_channels(3, crate::color::linear_to_srgb),
            };
            prepare_view(&v, t).with_context(|| format!("IDArb input view {i}"))
        })
        .collect::<Result<Vec<_>>>()?;
    let scheduler = DdimScheduler::idarb(opts.steps);
    let groups = view_groups(views.len(), opts.views_per_group);
    let lat = t / 8;

    let progress = if opts.progress {
        let flops: f64 = groups.iter().map(|g| unet_forward_flops(&pipeline.unet.config, NUM_DOMAINS * g.len(), lat, lat, g.len())).sum::<f64>() * scheduler.timesteps.len() as f64;
        let rate = measured_flops_per_second()?;
        eprintln!(
            "IDArb: {} views in {} group(s), {} DDIM steps at {t}²: about {:.1} min (UNet {:.1} TFLOP at a measured {:.0} GFLOP/s; VAE extra)",
            views.len(), groups.len(), scheduler.timesteps.len(), flops / rate / 60.0, flops / 1e12, rate / 1e9
        );
        let bar = indicatif::ProgressBar::new((groups.len() * scheduler.timesteps.len()) as u64);
        bar.set_style(
            indicatif::ProgressStyle::with_template("IDArb {bar:40} {pos}/{len} UNet steps, {elapsed} elapsed, ETA {eta}")
                .map_err(|e| anyhow::anyhow!("progress template: {e}"))?,
        );
        Some(bar)
    } else {
        None
    };

    let mut out: Vec<Option<ViewLabels>> = vec![None; views.len()];
    for (gi, group) in groups.iter().enumerate() {
        let n = group.len();
        let rgb: Vec<f32> = group.iter().flat_map(|&i| prepared[i].rgb_planar.iter().copied()).collect();
        let rgb = Tensor::from_vec(rgb, (n, 3, t, t), &Device::Cpu)?;
        let pose: Vec<f32> = group.iter().flat_map(|&i| poses[i]).collect();
        let pose = Tensor::from_vec(pose, (1, n, 4), &Device::Cpu)?;
        let image_latents = pipeline.encode_images(&rgb)?;
        let mut sampler = Sampler::new(opts.seed, gi as u64);
        let shape = (NUM_DOMAINS * n, 4, lat, lat);
        let init = gaussian_noise(&mut sampler, shape)?;
        let latents = pipeline.denoise(
            &image_latents,
            &pose,
            &init,
            &scheduler,
            opts.eta,
            &mut |_| gaussian_noise(&mut sampler, shape).map_err(|e| candle_core::Error::Msg(e.to_string())),
            &mut |_| {
                if let Some(b) = &progress {
                    b.inc(1);
                }
                Ok(())
            },
        )?;
        let decoded = pipeline.decode(&latents)?; // [3n, 3, t, t]
        for (j, &vi) in group.iter().enumerate() {
            out[vi] = Some(split_labels(&decoded, j, &prepared[vi].mask, &prepared[vi].framing)?);
        }
    }
    if let Some(b) = progress {
        b.finish();
    }
    out.into_iter().enumerate().map(|(i, l)| l.with_context(|| format!("view {i} was not in any group"))).collect()
}

/// Labels of the j-th view of a decoded group [3N, 3, T, T], mapped back to the view's framing
/// (`main.py: reform_image`: metallic = R, roughness = G of the third map).
pub fn split_labels(decoded: &Tensor, j: usize, mask: &[f32], framing: &Framing) -> Result<ViewLabels> {
    let plane = |d: usize| -> Result<Vec<f32>> { Ok(decoded.get(NUM_DOMAINS * j + d)?.flatten_all()?.to_vec1::<f32>()?) };
    let (albedo, normal, mr) = (plane(0)?, plane(1)?, plane(2)?);
    let tt = framing.target * framing.target;
    Ok(ViewLabels {
        albedo: unframe(&albedo, 3, framing),
        normal: unframe(&normal, 3, framing),
        metallic: unframe(&mr[..tt], 1, framing),
        roughness: unframe(&mr[tt..2 * tt], 1, framing),
        mask: unframe(mask, 1, framing),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn groups_cover_every_view_once_and_respect_the_size() {
        for (n, k) in [(1, 4), (4, 4), (5, 4), (10, 3), (100, 4)] {
            let g = view_groups(n, k);
            let mut all: Vec<usize> = g.iter().flatten().copied().collect();
            all.sort();
            assert_eq!(all, (0..n).collect::<Vec<_>>());
            assert!(g.iter().all(|x| x.len() <= k && !x.is_empty()), "{n} {k}: {g:?}");
        }
        assert_eq!(view_groups(5, 4), vec![vec![0, 2, 4], vec![1, 3]]);
    }

    #[test]
    fn no_weights_and_no_cache_gives_the_instructions() {
        let dir = std::env::temp_dir().join(format!("idarb_nocache_{}", std::process::id()));
        let views = vec![Image::filled(8, 8, &[0.5, 0.5, 0.5, 1.0])];
        // an explicit missing folder must not fall back to anything else
        let err = labels_for_views(&views, None, &IdarbOptions::default(), Some(Path::new("/nonexistent/idarb")), &dir).unwrap_err();
        let msg = format!("{err:#}");
        assert!(msg.contains("--prior idarb-sim") && msg.contains("IDARB_WEIGHTS"), "{msg}");
    }

    #[test]
    fn gaussian_noise_has_unit_moments() -> Result<()> {
        let mut s = Sampler::new(7, 0);
        let v = gaussian_noise(&mut s, (1, 4, 64, 64))?.flatten_all()?.to_vec1::<f32>()?;
        let mean = v.iter().sum::<f32>() / v.len() as f32;
        let var = v.iter().map(|x| (x - mean) * (x - mean)).sum::<f32>() / v.len() as f32;
        assert!(mean.abs() < 0.03 && (var - 1.0).abs() < 0.05, "mean {mean} var {var}");
        Ok(())
    }
}

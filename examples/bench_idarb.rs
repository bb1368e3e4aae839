//! Full-size IDArb UNet forward time (random weights, f32, CPU) at 256², N = 1 and 2 views, and
//! in the same run PyTorch's time for diffusers' SD-2.1 UNet with 8 input channels
//! (`tools/idarb/bench_torch_unet.py`, skipped with a note when torch is not installed).
//!
//! Also prints the process's peak resident memory after the candle runs.
//!
//!     cargo run --release --example bench_idarb [-- --size 256 --views 1,2 --repeats 2 --no-torch]
//!     cargo run --release --example bench_idarb -- --size 512 --views 4 --repeats 1 --no-torch
use anyhow::{Context, Result};
use candle_core::{DType, Device, Tensor};
use candle_nn::{VarBuilder, VarMap};
use reconstruct::prior::idarb::unet_dr2d_condition::{unet_forward_flops, UNetDR2DConditionModel, UNetDR2DConfig};
use std::process::Command;
use std::time::Instant;

// The allocator of the `reconstruct` binary, which runs this network for `--prior idarb`.
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn arg<T: std::str::FromStr>(name: &str, default: T) -> T {
    let args: Vec<String> = std::env::args().collect();
    args.iter().position(|a| a == name).and_then(|i| args.get(i + 1)).and_then(|v| v.parse().ok()).unwrap_or(default)
}

/// Peak resident set size of this process in GiB (Linux `VmHWM`), if readable.
fn peak_rss_gib() -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let kib: f64 = status.lines().find(|l| l.starts_with("VmHWM:"))?.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / (1024.0 * 1024.0))
}

fn main() -> Result<()> {
    reconstruct::allocator::keep_freed_pages();
    let size: usize = arg("--size", 256);
    let repeats: usize = arg("--repeats", 2);
    let views: Vec<usize> = arg("--views", "1,2".to_string()).split(',').filter_map(|v| v.parse().ok()).collect();
    let dev = Device::Cpu;
    let config = UNetDR2DConfig::full();
    let t0 = Instant::now();
    let varmap = VarMap::new();
    let unet = UNetDR2DConditionModel::new(VarBuilder::from_varmap(&varmap, DType::F32, &dev), config.clone())?;
    println!("candle: built full-size UNet-DR2D with random weights in {:.1} s", t0.elapsed().as_secs_f64());
    let lat = size / 8;
    let mut candle_times = Vec::new();
    for &n in &views {
        let rows = 3 * n;
        let x = Tensor::randn(0f32, 1.0, (rows, 8, lat, lat), &dev)?;
        let ctx = Tensor::randn(0f32, 1.0, (rows, 77, 1024), &dev)?;
        let pose = Tensor::zeros((1, n, 4), DType::F32, &dev)?;
        unet.forward(&x, 999.0, &ctx, &pose, n)?; // warm-up
        let mut times = Vec::new();
        for _ in 0..repeats {
            let s = Instant::now();
            unet.forward(&x, 999.0, &ctx, &pose, n)?;
            times.push(s.elapsed().as_secs_f64());
        }
        times.sort_by(|a, b| a.total_cmp(b));
        let med = times[times.len() / 2];
        let flops = unet_forward_flops(&config, rows, lat, lat, n);
        println!("candle N={n} rows={rows} {size}² seconds={med:.3} ({:.0} GFLOP, {:.0} GFLOP/s)", flops / 1e9, flops / med / 1e9);
        candle_times.push((n, med));
    }
    if let Some(gib) = peak_rss_gib() {
        println!("candle: peak resident memory {gib:.2} GiB (weights {:.2} GiB)", varmap.all_vars().iter().map(|v| v.elem_count()).sum::<usize>() as f64 * 4.0 / (1u64 << 30) as f64);
    }
    drop(unet);
    drop(varmap);
    if std::env::args().any(|a| a == "--no-torch") {
        return Ok(());
    }

    let script = concat!(env!("CARGO_MANIFEST_DIR"), "/tools/idarb/bench_torch_unet.py");
    let views_arg: Vec<String> = views.iter().map(|v| v.to_string()).collect();
    let out = Command::new("python3")
        .arg(script)
        .args(["--size", &size.to_string(), "--repeats", &repeats.to_string(), "--views"])
        .args(&views_arg)
        .output()
        .context("running python3")?;
    if !out.status.success() {
        println!("torch: not measured ({})", String::from_utf8_lossy(&out.stderr).lines().last().unwrap_or("python failed"));
        return Ok(());
    }
    let text = String::from_utf8_lossy(&out.stdout);
    print!("{text}");
    for (n, c) in candle_times {
        let torch = text
            .lines()
            .find(|l| l.starts_with(&format!("torch N={n} ")))
            .and_then(|l| l.rsplit("seconds=").next())
            .and_then(|s| s.trim().parse::<f64>().ok());
        if let Some(t) = torch {
            println!("N={n}: candle {c:.3} s (UNet-DR2D, with cross-view attention) vs torch {t:.3} s (plain SD-2.1 UNet): candle/torch = {:.2}", c / t);
        }
    }
    Ok(())
}

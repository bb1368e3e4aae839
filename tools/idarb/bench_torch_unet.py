#!/usr/bin/env python3
"""Time PyTorch's forward of diffusers' SD-2.1-base UNet2DConditionModel with 8 input channels
(random weights, float32, CPU) for comparison with `cargo run --release --example bench_idarb`.

Usage: python3 tools/idarb/bench_torch_unet.py --size 256 --views 1 2 [--repeats 2]
Prints one line per view count: `torch N=<n> rows=<3n> seconds=<median>`.
Needs `pip install torch diffusers` (plain PyPI)."""
import argparse
import statistics
import time

import torch
from diffusers import UNet2DConditionModel

# SD-2.1-base UNet, with IDArb's 8 input channels (noisy latent + image latent).
SD21_BASE = dict(
    sample_size=32, in_channels=8, out_channels=4, layers_per_block=2,
    block_out_channels=(320, 640, 1280, 1280),
    down_block_types=("CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "CrossAttnDownBlock2D", "DownBlock2D"),
    up_block_types=("UpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D", "CrossAttnUpBlock2D"),
    attention_head_dim=(5, 10, 20, 20), cross_attention_dim=1024, use_linear_projection=True,
    norm_num_groups=32, flip_sin_to_cos=True, freq_shift=0,
)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=int, default=256, help="image side; the latent is size/8")
    ap.add_argument("--views", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--repeats", type=int, default=2)
    args = ap.parse_args()
    torch.manual_seed(0)
    unet = UNet2DConditionModel(**SD21_BASE).eval().float()
    lat = args.size // 8
    print(f"torch {torch.__version__} threads={torch.get_num_threads()} params={sum(p.numel() for p in unet.parameters())}")
    for n in args.views:
        rows = 3 * n  # three label domains per view, as IDArb batches them
        x = torch.randn(rows, 8, lat, lat)
        ctx = torch.randn(rows, 77, 1024)
        t = torch.tensor(999)
        with torch.inference_mode():
            unet(x, t, encoder_hidden_states=ctx)  # warm-up
            times = []
            for _ in range(args.repeats):
                start = time.perf_counter()
                unet(x, t, encoder_hidden_states=ctx)
                times.append(time.perf_counter() - start)
        print(f"torch N={n} rows={rows} seconds={statistics.median(times):.3f}", flush=True)


if __name__ == "__main__":
    main()

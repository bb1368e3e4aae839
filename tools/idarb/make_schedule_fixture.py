#!/usr/bin/env python3
"""Write the official DDIM schedule for many step counts (tests/fixtures/idarb/ddim_schedules.json).

diffusers' DDIMScheduler with IDArb's released scheduler config (v-prediction, zero-terminal-SNR
rescale, linear betas 0.00085..0.012 over 1000 steps, trailing spacing, set_alpha_to_one), asked
for S steps: the timesteps, the previous timestep `t - 1000 // S` that `step()` uses, and the
float32 ᾱ_t and ᾱ_prev it reads. Lets the Rust schedule be checked for every step count a case
may use, not only the fixture's.

Usage: python3 tools/idarb/make_schedule_fixture.py OUT.json
Needs: pip install torch diffusers"""
import json
import sys

import diffusers
import torch
from diffusers import DDIMScheduler

CONFIG = dict(num_train_timesteps=1000, beta_start=0.00085, beta_end=0.012, beta_schedule="linear",
              prediction_type="v_prediction", rescale_betas_zero_snr=True, timestep_spacing="trailing",
              set_alpha_to_one=True, clip_sample=False, steps_offset=1)
STEP_COUNTS = [1, 2, 3, 4, 5, 6, 7, 8, 10, 12, 16, 20, 25, 30, 40, 50, 64, 100, 250]


def main():
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    s = DDIMScheduler(**CONFIG)
    acp = s.alphas_cumprod  # float32
    out = {"diffusers": diffusers.__version__, "torch": torch.__version__, "config": CONFIG, "schedules": []}
    for n in STEP_COUNTS:
        s.set_timesteps(n)
        ts = [int(t) for t in s.timesteps]
        prev = [t - s.config.num_train_timesteps // n for t in ts]
        a_t = [float(acp[t]) for t in ts]
        a_prev = [float(acp[p]) if p >= 0 else float(s.final_alpha_cumprod) for p in prev]
        out["schedules"].append({"steps": n, "timesteps": ts, "prev_timesteps": prev,
                                 "alpha_prod_t": a_t, "alpha_prod_t_prev": a_prev})
    with open(sys.argv[1], "w") as f:
        json.dump(out, f)
        f.write("\n")
    print(f"wrote {sys.argv[1]}: {len(STEP_COUNTS)} step counts")


if __name__ == "__main__":
    main()

#!/usr/bin/env python3
"""Time one gradient step in Mitsuba 3 on the inputs `cargo run --release --example bench_step`
writes (the same mesh, textures, light and resolution as reconstruct's own step):

  INPUT_DIR/model.obj (+ kd.png sRGB base colour, roughness.png, metallic.png),
  INPUT_DIR/light_latlong.exr (Blender lat-long), INPUT_DIR/camera.json, INPUT_DIR/target.exr

One step = render (llvm_ad_rgb, `prb`; max_depth 2: direct light with shadows, like
reconstruct's Monte Carlo shader without interreflection; max_depth 5: 3 indirect bounces, like
its interreflection effect at the default depth) + L1 loss against the target + dr.backward + mi.ad.Adam step
(+ clamps) over the base-colour, roughness and metallic textures and the envmap. Mitsuba's
principled BSDF is not reconstruct's BRDF: irrelevant to timing. The first step (JIT compile)
is reported apart; then median and mean of the next --steps steps, per max_depth and spp.
Unlike reconstruct, Mitsuba differentiates the indirect light too (prb replays each path).

  DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1 \
      python3 tools/mitsuba/gradient_step.py INPUT_DIR [--spp 4 16] [--max-depth 2 5] [--steps 10] [--threads 2] [--json]
"""
import argparse
import json
import os
import statistics
import sys
import time

# Default to Debian's LLVM 19 as make_reference.py does (LLVM 15 crashes Dr.Jit); must precede
# the drjit import.
if "DRJIT_LIBLLVM_PATH" not in os.environ and os.path.exists("/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"):
    os.environ["DRJIT_LIBLLVM_PATH"] = "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"

EMITTER_TO_WORLD = [[0, 0, 1, 0], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]]  # Blender z-up, as make_reference.py


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("input_dir")
    ap.add_argument("--spp", type=int, nargs="+", default=[4, 16])
    ap.add_argument("--max-depth", type=int, nargs="+", default=[2, 5])
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--variant", default="llvm_ad_rgb")
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args()
    try:
        import drjit as dr
        import mitsuba as mi
        import numpy as np
    except ImportError as e:
        sys.exit(f"gradient_step.py: {e}; install with `pip install mitsuba numpy`")
    if a.variant.startswith("llvm") and not os.environ.get("DRJIT_LIBLLVM_PATH"):
        sys.exit("gradient_step.py: set DRJIT_LIBLLVM_PATH to libLLVM.so.19.1 (Debian libllvm19); LLVM 15 crashes Dr.Jit")
    try:
        mi.set_variant(a.variant)
    except Exception as e:  # noqa: BLE001 - report any variant failure plainly
        sys.exit(f"gradient_step.py: cannot use variant {a.variant}: {e}")
    dr.set_thread_count(a.threads)
    d = a.input_dir
    cam = json.load(open(os.path.join(d, "camera.json")))
    c2w = np.array(cam["c2w"], dtype=np.float64) @ np.diag([-1.0, 1.0, -1.0, 1.0])  # OpenGL -> Mitsuba camera
    tex = lambda name, raw: {"type": "bitmap", "filename": os.path.join(d, name), "raw": raw, "format": "variant"}
    target = mi.TensorXf(np.array(mi.Bitmap(os.path.join(d, "target.exr")), dtype=np.float32)[..., :3])
    result = {"mitsuba_version": mi.__version__, "variant": a.variant, "threads": a.threads, "max_depth": {}}
    for depth in a.max_depth:
        result["max_depth"][str(depth)] = time_steps(mi, dr, scene_dict(mi, np, d, cam, c2w, tex, depth, a.spp[0]), target, a.spp, a.steps)
    if a.json:
        print(json.dumps(result))
    else:
        print(f"Mitsuba {result['mitsuba_version']} {a.variant}, {a.threads} threads, {cam['width']}x{cam['height']}")
        print("| max_depth | spp | first step incl. JIT (s) | median step (s) | mean step (s) |")
        for depth, runs in result["max_depth"].items():
            for spp, r in runs.items():
                print(f"| {depth} | {spp} | {r['first_s']:.3f} | {r['median_s']:.3f} | {r['mean_s']:.3f} |")


def scene_dict(mi, np, d, cam, c2w, tex, depth, spp):
    """The step's scene with a `prb` integrator of `depth`."""
    return {
        "type": "scene",
        "integrator": {"type": "prb", "max_depth": depth, "hide_emitters": True},
        "sensor": {"type": "perspective", "fov": float(np.degrees(cam["fov_x"])), "fov_axis": "x",
                   "to_world": mi.ScalarTransform4f(c2w.tolist()),
                   "film": {"type": "hdrfilm", "width": cam["width"], "height": cam["height"], "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": spp}},
        "emitter": {"type": "envmap", "filename": os.path.join(d, "light_latlong.exr"),
                    "to_world": mi.ScalarTransform4f(EMITTER_TO_WORLD)},
        "object": {"type": "obj", "filename": os.path.join(d, "model.obj"),
                   "bsdf": {"type": "twosided", "bsdf": {"type": "principled",
                            "base_color": tex("kd.png", False),
                            "roughness": tex("roughness.png", True),
                            "metallic": tex("metallic.png", True)}}},
    }


def time_steps(mi, dr, scene_desc, target, spps, steps):
    """First-step and median/mean step times per spp for one scene description."""
    scene = mi.load_dict(scene_desc)
    params = mi.traverse(scene)
    keys = [k for k in params.keys() if k.endswith(".data") and ("base_color" in k or "roughness" in k or "metallic" in k or k.startswith("emitter"))]
    opt = mi.ad.Adam(lr=0.01)
    for k in keys:
        opt[k] = params[k]
    params.update(opt)
    out = {}
    for spp in spps:
        times = []
        for step in range(steps + 1):
            t = time.perf_counter()
            img = mi.render(scene, params, spp=spp, seed=step)
            loss = dr.mean(dr.abs(img - target))
            dr.backward(loss)
            opt.step()
            for k in keys:
                opt[k] = dr.clip(opt[k], 0.0, 1.0) if not k.startswith("emitter") else dr.maximum(opt[k], 0.0)
            params.update(opt)
            dr.eval(loss)
            dr.sync_thread()
            times.append(time.perf_counter() - t)
        out[str(spp)] = {"first_s": times[0], "median_s": statistics.median(times[1:]), "mean_s": statistics.mean(times[1:])}
    return out


if __name__ == "__main__":
    main()

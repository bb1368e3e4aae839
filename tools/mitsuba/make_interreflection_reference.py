#!/usr/bin/env python3
"""Mitsuba 3 references for `reconstruct`'s interreflection effect (Effects::indirect_bounces).

The scene (tests/fixtures/mitsuba/interreflection/, all generated here, CC0):
  an open corner -- a floor and two walls, each a closed thin box, light grey rough diffuse
  (albedo 0.8) -- with a strongly coloured (red) rough diffuse sphere near the corner and a
  glossy metal sphere in front of it, lit only by the CC0 `city` probe (sun ~50 deg above the
  horizon from +x/-y, i.e. into the open side of the corner: the spheres' shadows fall on the
  floor and walls of the corner, where light reflected by the other surfaces fills them in).

What it writes (under tests/fixtures/mitsuba/interreflection/):
  floor.obj, wall_x.obj, wall_y.obj, red_sphere.obj, metal_sphere.obj   meshes (Blender world, z up)
  scene.json            the scene for the Rust side, the schema of ../scene/scene.json
  ref_projectbrdf_d2_<view>.exr   project BRDF (tools/mitsuba/project_brdf.py), path max_depth 2:
                                  direct light only
  ref_projectbrdf_d5_<view>.exr   project BRDF, max_depth 5: direct + 3 indirect bounces
  ref_principled_d5_<view>.exr    Mitsuba's principled BSDF, max_depth 5 (context only)
All EXRs: linear RGBA float32, alpha = pixel coverage, RGB premultiplied by it.

Mitsuba's `path` integrator counts path *segments*: max_depth 1 = emitters seen directly,
2 = direct illumination (camera -> x0 -> emitter), and each further unit adds one surface
vertex that does next-event estimation. `reconstruct`'s indirect_bounces = b shades b
surfaces after the visible one (each with next-event estimation + one BSDF sample), i.e.
camera -> x0 -> x1 .. x_b -> emitter: b + 2 segments, so b = 3 <-> max_depth = 5. Russian
roulette is disabled (rr_depth > max_depth) so the reference has no extra noise from it.

Sampler: `independent`, not the `ldsampler` of ../scene. At max_depth 5, ldsampler renders
(65536 spp = 256 passes with consecutive seeds) had a structured error that does not average
out over the passes, so the two-halves noise estimate cannot see it: -1.5 % / +2.1 % of the
*indirect* light summed over the floor / wall_x of view `east` against Mitsuba's own
`independent` sampler (the sign flipped with another seed base, with the principled BSDF too),
while reconstruct's renderer agreed with `independent` to <= 0.3 % on every object (README).
At max_depth 2 the samplers agree to 0.02 %. `--sampler ldsampler` reproduces those renders.

Shared with tools/mitsuba/make_reference.py (imported, not copied): mesh writers, probe
conversion and envmap check, camera conversion and check, Mitsuba scene/sensor/BSDF dicts,
the project-BRDF self-check, the pass-averaging renderer and its noise estimate. The probe
for Mitsuba is ../scene/city_mitsuba.exr (checked here to equal a fresh conversion of the
shared probe); the Rust side reads ../city.hdr.

Rerun (llvm variant; about 25-35 min on 2 shared cores at the default spp):
  pip install mitsuba==3.9.1 numpy
  apt-get install -y libllvm19      # the llvm variant; LLVM 15 crashes it
  DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1 \\
      python3 tools/mitsuba/make_interreflection_reference.py [--spp-direct N] [--spp-indirect N]
          [--spp-principled N] [--sampler independent] [--no-principled] [--preview]
"""

import argparse
import json
import os
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
import make_reference as mr     # sets DRJIT_LIBLLVM_PATH before importing drjit/mitsuba

import numpy as np
import drjit as dr
import mitsuba as mi

OUT = os.path.join(mr.OUT, "interreflection")
RES = 64
# The probe scaled so the sun-lit albedo-0.8 walls stay below 1 (sRGB comparisons clip at 1).
PROBE_STRENGTH = 0.35

WALL = dict(base_color=[0.8, 0.8, 0.8], roughness=0.9, metallic=0.0)
# Closed thin boxes: the floor's top is z = 0; the walls stand on it along x = -1.2 and
# y = +1.2 and do not overlap each other (wall_y starts where wall_x ends).
FLOOR = dict(name="floor", mesh="floor.obj", centre=(0.0, 0.0, -0.05), half=(1.2, 1.2, 0.05), material=WALL)
WALL_X = dict(name="wall_x", mesh="wall_x.obj", centre=(-1.15, 0.0, 0.7), half=(0.05, 1.2, 0.7), material=WALL)
WALL_Y = dict(name="wall_y", mesh="wall_y.obj", centre=(0.05, 1.15, 0.7), half=(1.15, 0.05, 0.7), material=WALL)
RED = dict(name="red_sphere", mesh="red_sphere.obj", centre=(-0.55, 0.6, 0.405), radius=0.4,
           material=dict(base_color=[0.8, 0.06, 0.04], roughness=0.7, metallic=0.0))
METAL = dict(name="metal_sphere", mesh="metal_sphere.obj", centre=(0.3, -0.05, 0.305), radius=0.3,
             material=dict(base_color=[0.9, 0.9, 0.9], roughness=0.3, metallic=1.0))
OBJECTS = [FLOOR, WALL_X, WALL_Y, RED, METAL]
TARGET = (-0.35, 0.35, 0.45)
VIEWS = {"south": dict(azim=-95.0, elev=25.0, dist=4.2),
         "east": dict(azim=5.0, elev=35.0, dist=4.0)}
DEPTHS = {"direct": 2, "indirect": 5}       # path max_depth: direct only / 3 indirect bounces
BOUNCES = {2: 0, 5: 3}


def integrator(max_depth):
    return {"type": "path", "max_depth": max_depth, "rr_depth": 1000, "hide_emitters": True}


def srgb_covered_psnr(a, b, alpha):
    """The Rust test's metric: PSNR of sRGB-encoded, [0,1]-clipped RGB over pixels with alpha > 0.5."""
    m = alpha > 0.5
    d = mr.linear_to_srgb(a[..., :3]) - mr.linear_to_srgb(b[..., :3])
    return 10 * np.log10(1.0 / np.mean(d[m] ** 2))


def rel_l1(a, b, alpha):
    """The Rust test's relative L1: sum |a - b| / sum b of linear RGB (negatives clamped to 0)."""
    m = alpha > 0.5
    a, b = np.maximum(a[..., :3][m], 0), np.maximum(b[..., :3][m], 0)
    return float(np.abs(a - b).sum() / b.sum())


def write_exr(img, path):
    mi.Bitmap(img.astype(np.float32), pixel_format=mi.Bitmap.PixelFormat.RGBA).write(path)


def check_probe_file():
    """../scene/city_mitsuba.exr (what the envmap reads) is the conversion of the shared probe."""
    src = os.path.join(mr.SHARED, "data", "probes", mr.PROBE + ".hdr")
    if not os.path.exists(src):
        src = os.path.join(mr.OUT, mr.PROBE + ".hdr")     # the verbatim copy in the fixture
    with tempfile.TemporaryDirectory() as tmp:
        fresh = os.path.join(tmp, "probe.exr")
        probe = mr.convert_probe(src, fresh)
        a = np.array(mi.Bitmap(fresh))
        b = np.array(mi.Bitmap(os.path.join(mr.SCENE_DIR, mr.PROBE + "_mitsuba.exr")))
    assert a.shape == b.shape and np.array_equal(a, b), "scene/city_mitsuba.exr is not the converted probe"
    print("probe: scene/city_mitsuba.exr equals a fresh conversion of %s" % src)
    return probe


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--spp-direct", type=int, default=65536, help="spp of the max_depth 2 reference")
    ap.add_argument("--spp-indirect", type=int, default=131072, help="spp of the max_depth 5 project-BRDF reference")
    ap.add_argument("--spp-principled", type=int, default=65536, help="spp of the principled context render")
    ap.add_argument("--sampler", default="independent", help="Mitsuba sampler (see the docstring for ldsampler)")
    ap.add_argument("--variant", default="llvm_ad_rgb")
    ap.add_argument("--no-principled", action="store_true", help="skip the principled-BSDF context render")
    ap.add_argument("--preview", action="store_true", help="write PNG previews next to the EXRs (not committed)")
    args = ap.parse_args()
    mi.set_variant(args.variant)
    import project_brdf      # a mi.BSDF subclass: needs the variant set first
    project_brdf.register()
    os.makedirs(OUT, exist_ok=True)

    # 1. scene files
    mesh_stats = {}
    for o in OBJECTS:
        path = os.path.join(OUT, o["mesh"])
        mesh_stats[o["name"]] = (mr.write_uv_sphere(path, o["centre"], o["radius"]) if "radius" in o
                                 else mr.write_box(path, o["centre"], o["half"]))
    probe = check_probe_file()
    c2ws = {name: mr.look_at_c2w(mr.orbit(TARGET, v["dist"], v["azim"], v["elev"]), TARGET) for name, v in VIEWS.items()}
    scenes = {}

    def scene(model, depth):
        if (model, depth) not in scenes:
            scenes[(model, depth)] = mi.load_dict(mr.scene_dict(c2ws, integrator(depth), mr.PASS_SPP, model=model,
                                                                objects=OBJECTS, scene_dir=OUT, res=RES,
                                                                strength=PROBE_STRENGTH, sampler=args.sampler))
        return scenes[(model, depth)]

    # 2. checks
    env_err = mr.check_envmap(scene("project", 2), probe, PROBE_STRENGTH)
    brdf_err, brdf_sigma = mr.check_project_brdf(project_brdf, objects=OBJECTS)

    # 3. renders: (model, max_depth) -> per view
    jobs = [("project", 2, args.spp_direct), ("project", 5, args.spp_indirect)]
    if not args.no_principled:
        jobs.append(("principled", 5, args.spp_principled))
    images, info = {}, {}
    for model, depth, spp in jobs:
        for vi, name in enumerate(c2ws):
            t0 = time.perf_counter()
            # the same seeds for every job: the max_depth 2 and 5 renders share their camera rays
            img, spp_done, noise, halves = mr.render_view(scene(model, depth), vi, spp, seed_base=1000 * (vi + 1),
                                                          res=RES, halves=True)
            secs = time.perf_counter() - t0
            tag = "%s_d%d" % ("projectbrdf" if model == "project" else "principled", depth)
            fname = "ref_%s_%s.exr" % (tag, name)
            write_exr(img, os.path.join(OUT, fname))
            images[(model, depth, name)] = img
            noise_srgb = srgb_covered_psnr(halves[0], halves[1], img[..., 3]) + 10 * np.log10(4)
            info[(model, depth, name)] = {"file": fname, "spp": spp_done, "seconds": round(secs, 1),
                                          "estimated_psnr_db_vs_converged": round(noise, 1),
                                          "estimated_psnr_srgb_covered_db_vs_converged": round(noise_srgb, 1)}
            print("view %s, %s BSDF, max_depth %d: %d spp in %.1f s; coverage %.1f%%; estimated PSNR vs converged "
                  "%.1f dB (linear, all pixels), %.1f dB (sRGB, covered pixels)"
                  % (name, model, depth, spp_done, secs, 100 * img[..., 3].mean(), noise, noise_srgb))
            if args.preview:
                rgb = mr.linear_to_srgb(np.where(img[..., 3:] > 0, img[..., :3], 0.0))
                mi.Bitmap((rgb * 255 + 0.5).astype(np.uint8), pixel_format=mi.Bitmap.PixelFormat.RGB).write(
                    os.path.join(OUT, "preview_%s_%s.png" % (tag, name)))

    alphas = {name: images[("project", 2, name)][..., 3] for name in c2ws}
    cam_err = mr.check_camera(scene("project", 2), c2ws, alphas, res=RES, pts=[
        ("red_sphere centre", RED["centre"]), ("metal_sphere centre", METAL["centre"]),
        ("corner (floor top)", (-1.1, 1.1, 0.0)), ("wall_x top front", (-1.1, -1.2, 1.4))])

    # how much the indirect light matters, in the Rust test's metric
    effect = {}
    for name in c2ws:
        a = alphas[name]
        d2, d5 = images[("project", 2, name)], images[("project", 5, name)]
        effect[name] = {"psnr_srgb_covered_d2_vs_d5": round(srgb_covered_psnr(d2, d5, a), 2),
                        "rel_l1_d2_vs_d5": round(rel_l1(d2, d5, a), 4),
                        "d5_over_d2_total": round(float(d5[..., :3].sum() / d2[..., :3].sum()), 4),
                        "max_alpha_diff_d2_d5": float(np.abs(d2[..., 3] - d5[..., 3]).max())}
        if ("principled", 5, name) in images:
            pr = images[("principled", 5, name)]
            effect[name]["psnr_srgb_covered_principled_vs_project_d5"] = round(srgb_covered_psnr(pr, d5, a), 2)
            effect[name]["rel_l1_principled_vs_project_d5"] = round(rel_l1(pr, d5, a), 4)
        print("view %s: project BRDF max_depth 2 vs 5: %.2f dB (sRGB, covered), rel. L1 %.2f%%, total radiance x%.3f; %s"
              % (name, effect[name]["psnr_srgb_covered_d2_vs_d5"], 100 * effect[name]["rel_l1_d2_vs_d5"],
                 effect[name]["d5_over_d2_total"],
                 ("principled vs project BRDF at max_depth 5: %.2f dB, %.2f%%"
                  % (effect[name]["psnr_srgb_covered_principled_vs_project_d5"],
                     100 * effect[name]["rel_l1_principled_vs_project_d5"]))
                 if "psnr_srgb_covered_principled_vs_project_d5" in effect[name] else ""))

    # 4. scene.json (schema of ../scene/scene.json; paths relative to this folder)
    objs = []
    for o in OBJECTS:
        e = {"name": o["name"], "mesh": o["mesh"], "vertices": mesh_stats[o["name"]][0],
             "triangles": mesh_stats[o["name"]][1], "shading": "smooth (vn)" if "radius" in o else "flat (vn per face)",
             "centre": list(o["centre"]), "material": mr.material_json(o["material"])}
        if "radius" in o:
            e["radius"] = o["radius"]
        else:
            e["half_extents"] = list(o["half"])
        objs.append(e)
    cams = []
    for name, c2w in c2ws.items():
        c = {"name": name, "transform_matrix": c2w.tolist(), "camera_angle_x": mr.FOV_X,
             "width": RES, "height": RES,
             "reference": info.get(("principled", 5, name), {}).get("file"),
             "reference_project_brdf": info[("project", 5, name)]["file"],
             "reference_project_brdf_direct": info[("project", 2, name)]["file"],
             "renders": {"%s_max_depth_%d" % (m, d): info[(m, d, n)] for (m, d, n) in info if n == name},
             "effect_of_indirect_light": effect[name],
             "look_at": list(TARGET), "orbit_deg": {"azimuth": VIEWS[name]["azim"], "elevation": VIEWS[name]["elev"]},
             "distance": VIEWS[name]["dist"]}
        cams.append(c)
    doc = {
        "format": "reconstruct-mitsuba-reference v1",
        "paths": "relative to the folder holding this scene.json",
        "generator": {"script": "tools/mitsuba/make_interreflection_reference.py", "mitsuba": mi.__version__,
                      "drjit": dr.__version__, "variant": mi.variant(), "numpy": np.__version__,
                      "python": sys.version.split()[0]},
        "world": {"frame": "Blender, z up", "units": "arbitrary"},
        "objects": objs,
        "environment": {"file": "../%s.hdr" % mr.PROBE, "strength": PROBE_STRENGTH,
                        "convention": "Blender equirect: phi = 2pi(0.5-u), theta = v*pi, "
                                      "d = (sin th cos phi, sin th sin phi, cos th); texel centres; bilinear, periodic in u and v",
                        "mitsuba_file": "../scene/%s_mitsuba.exr" % mr.PROBE,
                        "mitsuba_to_world": mr.EMITTER_TO_WORLD.tolist(),
                        "check_max_rel_err": env_err},
        "cameras": cams,
        "camera_convention": "NeRF: camera-to-world, OpenGL camera (x right, y up, looks down -z); "
                             "camera_angle_x = horizontal FOV (rad); focal = 0.5*width/tan(0.5*camera_angle_x); "
                             "pixel (col,row) centre at (col+0.5,row+0.5), row 0 at the top",
        "integrator": {"type": "path", "max_depth": 5, "rr_depth": 1000, "hide_emitters": True,
                       "lighting": "direct + 3 indirect bounces: next-event estimation (one emitter sample, MIS with "
                                   "the BSDF sample, power heuristic) at the visible point and at 3 further path "
                                   "vertices, one BSDF sample per vertex; no Russian roulette. reconstruct: "
                                   "Effects::indirect_bounces = max_depth - 2",
                       "reference_project_brdf_direct": "the same with max_depth 2: direct light only"},
        "film": {"width": RES, "height": RES, "filter": "box (1 pixel)", "sampler": args.sampler,
                 "pixel_format": "RGBA float32, linear",
                 "alpha": "pixel coverage", "rgb": "premultiplied by coverage (background radiance counted as 0)"},
        "spp": min(v["spp"] for v in info.values()),
        "checks": {"camera_max_angle_err_rad": cam_err, "project_brdf_eval_max_rel_err": brdf_err,
                   "project_brdf_sampling_max_sigma": round(brdf_sigma, 2)},
        "project_brdf": {"module": "tools/mitsuba/project_brdf.py",
                         "model": "docs/model.md, BRDF: Lambert kd(1-m); GGX alpha = max(r,0.08)^2, height-correlated "
                                  "Smith, Schlick F with F0 = 0.04(1-m) + kd m; two-sided"},
    }
    with open(os.path.join(OUT, "scene.json"), "w") as f:
        json.dump(doc, f, indent=1)
    print("wrote", os.path.join(OUT, "scene.json"))


if __name__ == "__main__":
    main()

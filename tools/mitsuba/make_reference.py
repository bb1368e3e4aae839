#!/usr/bin/env python3
"""Independent Mitsuba 3 reference renders for `reconstruct`'s renderer.

What it makes (all under tests/fixtures/mitsuba/):
  scene/box.obj, scene/sphere.obj, scene/metal_sphere.obj   meshes, Blender world (z up)
  scene/sphere_base_color.png   64x64 sRGB-encoded procedural base-colour texture
  scene/city_mitsuba.exr        the probe converted for Mitsuba's envmap (33x32, see below)
  scene/scene.json              everything the Rust side needs to rebuild the scene
  city.hdr                      the CC0 test probe (copied verbatim from shared/data/probes)
  ref_above.exr, ref_side.exr   linear RGBA float32 renders (alpha = pixel coverage,
                                RGB premultiplied by coverage, i.e. background counts as 0)
  ref_projectbrdf_above.exr, ref_projectbrdf_side.exr
                                the same renders with reconstruct's own BRDF (docs/model.md,
                                tools/mitsuba/project_brdf.py) instead of Mitsuba's principled
  aov_above.exr                 optional ground truth for view "above": straight (coverage
                                normalised) base colour and world-space shading normal

The scene is a diffuse box used as a pedestal with two spheres resting on it (one glossy
and textured, one metallic), lit only by the `city` probe (sun about 50 deg above the
horizon, so shadows on the box top matter). Direct lighting only: Mitsuba `path`
integrator with max_depth = 2 (camera -> surface -> emitter; emitter sampling and BSDF
sampling combined with MIS; shadow rays included, no inter-reflection).

Conventions reproduced (see shared/data/nerfactor/hotdog_2163/README.md):
  * cameras are NeRF camera-to-world matrices (OpenGL camera: x right, y up, looking down
    -z); Mitsuba sensor to_world = c2w @ diag(-1, 1, -1, 1); fov_axis = x.
  * the probe is a Blender equirect lat-long; Mitsuba's envmap interpolates latitude with
    aligned corners, so the 16x32 probe is resampled to 33x32 rows (odd rows = original
    texel rows, even rows = midpoints; the two pole rows = mean of first and last row,
    i.e. Cycles' periodic vertical wrap). Emitter to_world maps Mitsuba's local frame
    (y up) onto Blender's z-up world so that u_mitsuba == u_blender.

Rerun (about 5-7 min on 2 cores with the llvm variant at the default 65536 spp):
  pip install mitsuba==3.9.1 numpy
  apt-get install -y libllvm19      # the llvm variant; LLVM 15 crashes it
  DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1 \
      python3 tools/mitsuba/make_reference.py [--spp 65536] [--variant llvm_ad_rgb] [--no-aov]
The shared data dir is $RECONSTRUCT_SHARED_DIR, else <repo>/../shared.

Checks printed (and asserted) on every run: envmap orientation vs the Blender formula,
camera conversion vs a NumPy NeRF projection, texture UV orientation, project BRDF vs a
NumPy transcription and its sampling weights. See tests/fixtures/mitsuba/README.md.

Versions used for the committed fixture: Mitsuba 3.9.1, Dr.Jit 1.5.0, variant llvm_ad_rgb,
Python 3.11, NumPy (see scene.json "generator").
"""

import argparse
import json
import os
import shutil
import sys
import time

if "DRJIT_LIBLLVM_PATH" not in os.environ and os.path.exists(
        "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"):
    os.environ["DRJIT_LIBLLVM_PATH"] = "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"

import numpy as np
import drjit as dr
import mitsuba as mi

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))
OUT = os.path.join(REPO, "tests", "fixtures", "mitsuba")
SCENE_DIR = os.path.join(OUT, "scene")
SHARED = os.environ.get("RECONSTRUCT_SHARED_DIR", os.path.join(REPO, "..", "shared"))

PROBE = "city"          # sun ~50 deg elevation: strong directional part -> clear shadows
PROBE_STRENGTH = 1.0
RES = 96
FOV_X = 0.6911112070083618   # same horizontal FOV as the NeRF synthetic cameras (rad)
PASS_SPP = 256               # ldsampler needs powers of 4; passes bound the llvm wavefront

# ---------------------------------------------------------------- sRGB (IEC 61966-2-1)

def srgb_to_linear(c):
    c = np.asarray(c, dtype=np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(c):
    c = np.clip(np.asarray(c, dtype=np.float64), 0.0, 1.0)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)

# ---------------------------------------------------------------- geometry

def write_uv_sphere(path, centre, radius, segments=40, rings=20):
    """UV sphere, smooth normals. vt: u = longitude / 2pi (seam duplicated),
    v = 0 at the south pole (-z) .. 1 at the north pole (+z): OBJ convention,
    v = 0 is the BOTTOM row of the texture image."""
    c = np.asarray(centre, dtype=np.float64)
    verts, uvs, normals = [], [], []
    for r in range(rings + 1):
        v = r / rings
        theta = np.pi * (1.0 - v)            # polar angle from +z
        for s in range(segments + 1):
            u = s / segments
            phi = 2.0 * np.pi * u
            n = np.array([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])
            verts.append(c + radius * n)
            normals.append(n)
            uvs.append((u, v))
    faces = []
    row = segments + 1
    for r in range(rings):
        for s in range(segments):
            a = r * row + s
            b = a + 1
            d = a + row
            e = d + 1
            # counter-clockwise seen from outside (normal outward)
            if r != 0:                       # skip degenerate triangle at the south pole
                faces.append((a, b, e))
            if r != rings - 1:               # ... and at the north pole
                faces.append((a, e, d))
    with open(path, "w") as f:
        f.write("# UV sphere, centre %s radius %g, %d segments x %d rings\n"
                % (" ".join("%g" % x for x in c), radius, segments, rings))
        f.write("# Blender world frame (z up); vt v = 0 is the bottom row of the texture\n")
        for p in verts:
            f.write("v %.7f %.7f %.7f\n" % tuple(p))
        for t in uvs:
            f.write("vt %.7f %.7f\n" % t)
        for n in normals:
            f.write("vn %.7f %.7f %.7f\n" % tuple(n))
        for tri in faces:
            f.write("f " + " ".join("%d/%d/%d" % (i + 1, i + 1, i + 1) for i in tri) + "\n")
    return len(verts), len(faces)


def write_box(path, centre, half):
    """Axis-aligned box, flat shaded: 6 faces x 4 vertices, per-face normals and UVs."""
    c = np.asarray(centre, dtype=np.float64)
    h = np.asarray(half, dtype=np.float64)
    verts, uvs, normals, faces = [], [], [], []
    for axis in range(3):
        for sign in (1.0, -1.0):
            n = np.zeros(3)
            n[axis] = sign
            t = np.zeros(3)
            t[(axis + 1) % 3] = 1.0
            b = np.cross(n, t)
            base = len(verts)
            for (su, sv) in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                verts.append(c + h * (n + su * t + sv * b))
                uvs.append(((su + 1) / 2, (sv + 1) / 2))
                normals.append(n)
            faces.append((base, base + 1, base + 2))
            faces.append((base, base + 2, base + 3))
    with open(path, "w") as f:
        f.write("# box, centre %s half extents %s, flat shaded (24 vertices)\n"
                % (" ".join("%g" % x for x in c), " ".join("%g" % x for x in h)))
        for p in verts:
            f.write("v %.7f %.7f %.7f\n" % tuple(p))
        for t in uvs:
            f.write("vt %.7f %.7f\n" % t)
        for n in normals:
            f.write("vn %.7f %.7f %.7f\n" % tuple(n))
        for tri in faces:
            f.write("f " + " ".join("%d/%d/%d" % (i + 1, i + 1, i + 1) for i in tri) + "\n")
    return len(verts), len(faces)


def make_texture(path, size=64):
    """8x8 checker modulating a hue gradient; stored sRGB-encoded 8-bit.
    Returns the linear values Mitsuba/the Rust side must see (sRGB-decoded bytes)."""
    j, i = np.meshgrid(np.arange(size), np.arange(size))   # i = row (top = 0), j = column
    x = (j + 0.5) / size
    y = (i + 0.5) / size
    lin = np.stack([0.15 + 0.7 * x, 0.15 + 0.6 * (1 - y), 0.6 - 0.45 * x], axis=-1)
    checker = ((i // 8 + j // 8) % 2).astype(np.float64)
    lin = lin * (0.35 + 0.65 * checker[..., None])
    # a marker in the top-left 8x8 block so orientation mistakes are visible
    lin[:8, :8] = (0.9, 0.9, 0.1)
    enc = np.round(linear_to_srgb(lin) * 255.0).astype(np.uint8)
    bmp = mi.Bitmap(enc, pixel_format=mi.Bitmap.PixelFormat.RGB)
    bmp.set_srgb_gamma(True)
    bmp.write(path)
    return srgb_to_linear(enc / 255.0)

# ---------------------------------------------------------------- probe

def convert_probe(src, dst):
    """Blender equirect (H x W, texel centred, periodic bilinear) -> Mitsuba envmap image
    with 2H+1 rows so Mitsuba's aligned-corners latitude interpolation is identical."""
    a = np.array(mi.Bitmap(src), dtype=np.float64)
    H, W, _ = a.shape
    out = np.zeros((2 * H + 1, W, 3))
    out[1::2] = a
    out[2:-1:2] = 0.5 * (a[:-1] + a[1:])
    out[0] = out[-1] = 0.5 * (a[0] + a[-1])      # Cycles wraps periodically in v too
    mi.Bitmap(out.astype(np.float32), pixel_format=mi.Bitmap.PixelFormat.RGB).write(dst)
    return a


EMITTER_TO_WORLD = np.array([[0, 0, 1, 0], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]], dtype=np.float64)


def blender_lookup(probe, d):
    """Blender/Cycles equirect lookup: phi = 2pi(0.5 - u), theta = v pi, bilinear, periodic."""
    H, W, _ = probe.shape
    d = np.asarray(d, dtype=np.float64)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    u = (0.5 - np.arctan2(d[..., 1], d[..., 0]) / (2 * np.pi)) % 1.0
    v = np.arccos(np.clip(d[..., 2], -1, 1)) / np.pi
    x = u * W - 0.5
    y = v * H - 0.5
    x0 = np.floor(x).astype(int)
    y0 = np.floor(y).astype(int)
    fx = (x - x0)[..., None]
    fy = (y - y0)[..., None]
    p = lambda yy, xx: probe[yy % H, xx % W]
    return ((1 - fy) * ((1 - fx) * p(y0, x0) + fx * p(y0, x0 + 1))
            + fy * ((1 - fx) * p(y0 + 1, x0) + fx * p(y0 + 1, x0 + 1)))


def blender_dir(u, v):
    phi = 2 * np.pi * (0.5 - u)
    th = v * np.pi
    return np.array([np.sin(th) * np.cos(phi), np.sin(th) * np.sin(phi), np.cos(th)])

# ---------------------------------------------------------------- cameras

def look_at_c2w(eye, target, up=(0, 0, 1)):
    """NeRF/OpenGL camera-to-world: columns x right, y up, z backwards (looks down -z)."""
    eye = np.asarray(eye, dtype=np.float64)
    f = np.asarray(target, dtype=np.float64) - eye
    f /= np.linalg.norm(f)
    right = np.cross(f, up)
    right /= np.linalg.norm(right)
    upv = np.cross(right, f)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, upv, -f, eye
    return m


def orbit(target, dist, azim_deg, elev_deg):
    a, e = np.radians(azim_deg), np.radians(elev_deg)
    t = np.asarray(target, dtype=np.float64)
    return t + dist * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])


def nerf_project(c2w, fov_x, w, h, p):
    """World point -> continuous pixel coords (x right, y DOWN; pixel (i,j) centre at +0.5)."""
    q = np.linalg.inv(c2w) @ np.append(p, 1.0)
    focal = 0.5 * w / np.tan(0.5 * fov_x)
    return np.array([0.5 * w + focal * q[0] / -q[2], 0.5 * h - focal * q[1] / -q[2]])

# ---------------------------------------------------------------- scene

BOX = dict(name="box", mesh="box.obj", centre=(0.0, 0.0, 0.0), half=(0.8, 0.6, 0.15),
           material=dict(base_color=[0.45, 0.40, 0.32], roughness=0.9, metallic=0.0))
SPHERE = dict(name="textured_sphere", mesh="sphere.obj", centre=(-0.3, 0.08, 0.15 + 0.38 + 0.005),
              radius=0.38, material=dict(base_color="sphere_base_color.png", roughness=0.25, metallic=0.0))
METAL = dict(name="metal_sphere", mesh="metal_sphere.obj", centre=(0.45, -0.22, 0.15 + 0.22 + 0.005),
             radius=0.22, material=dict(base_color=[0.95, 0.64, 0.54], roughness=0.3, metallic=1.0))
OBJECTS = [BOX, SPHERE, METAL]
TARGET = (0.0, 0.0, 0.3)
VIEWS = {"above": dict(azim=45.0, elev=55.0, dist=3.2),
         "side": dict(azim=-120.0, elev=14.0, dist=3.3)}


def bsdf_dict(mat, model="principled", scene_dir=SCENE_DIR):
    bc = mat["base_color"]
    if isinstance(bc, str):
        base = {"type": "bitmap", "filename": os.path.join(scene_dir, bc), "raw": False,
                "filter_type": "bilinear", "wrap_mode": "repeat"}
    else:
        base = {"type": "rgb", "value": list(bc)}
    if model == "project":      # reconstruct's own BRDF (project_brdf.py), two-sided itself
        return {"type": "project_brdf", "base_color": base, "roughness": mat["roughness"],
                "metallic": mat["metallic"]}
    return {"type": "twosided", "nested": {
        "type": "principled", "base_color": base, "roughness": mat["roughness"],
        "metallic": mat["metallic"], "specular": 0.5, "spec_tint": 0.0, "spec_trans": 0.0,
        "anisotropic": 0.0, "sheen": 0.0, "clearcoat": 0.0}}


def sensor_dict(c2w, spp, res=RES, sampler="ldsampler"):
    to_world = c2w @ np.diag([-1.0, 1.0, -1.0, 1.0])   # OpenGL camera -> Mitsuba camera
    return {"type": "perspective", "fov": float(np.degrees(FOV_X)), "fov_axis": "x",
            "near_clip": 0.01, "far_clip": 100.0, "to_world": mi.ScalarTransform4f(to_world.tolist()),
            "sampler": {"type": sampler, "sample_count": spp},
            "film": {"type": "hdrfilm", "width": res, "height": res, "pixel_format": "rgba",
                     "rfilter": {"type": "box"}}}


def scene_dict(c2ws, integrator, spp, model="principled", objects=None, scene_dir=SCENE_DIR, res=RES,
               strength=PROBE_STRENGTH, sampler="ldsampler"):
    """The Mitsuba scene: the converted probe (always scene/city_mitsuba.exr) scaled by `strength`,
    one sensor per view, `objects` (default this scene's OBJECTS) with meshes and textures under
    `scene_dir`."""
    d = {"type": "scene", "integrator": integrator,
         "emitter": {"type": "envmap", "filename": os.path.join(SCENE_DIR, PROBE + "_mitsuba.exr"),
                     "scale": strength, "to_world": mi.ScalarTransform4f(EMITTER_TO_WORLD.tolist())}}
    for name, c2w in c2ws.items():
        d["sensor_" + name] = sensor_dict(c2w, spp, res, sampler)
    for o in (OBJECTS if objects is None else objects):
        d[o["name"]] = {"type": "obj", "filename": os.path.join(scene_dir, o["mesh"]),
                        "face_normals": False, "bsdf": bsdf_dict(o["material"], model, scene_dir)}
    return d


def material_json(m):
    """A material as scene.json describes it (the Mitsuba principled parameters used)."""
    bc = m["base_color"]
    base = ({"texture": bc, "color_space": "srgb", "filter": "bilinear", "wrap": "repeat",
             "uv_convention": "OBJ: vt v = 0 is the bottom row of the image; texel (i,j) centre at ((j+0.5)/W, 1-(i+0.5)/H)"}
            if isinstance(bc, str) else {"constant_linear_rgb": list(bc)})
    return {"type": "mitsuba_principled", "two_sided": True, "base_color": base,
            "roughness": m["roughness"], "metallic": m["metallic"], "specular": 0.5,
            "f0_dielectric": 0.04, "ggx_alpha": "roughness^2"}


def psnr(a, b):
    mse = np.mean((np.clip(a, 0, 1) - np.clip(b, 0, 1)) ** 2)
    return 10 * np.log10(1.0 / mse)

# ---------------------------------------------------------------- checks

def check_envmap(scene, probe, strength=PROBE_STRENGTH):
    em = scene.emitters()[0]
    H, W, _ = probe.shape
    names, dirs = [], []
    for name, d in [("+x", (1, 0, 0)), ("+y", (0, 1, 0)), ("-x", (-1, 0, 0)), ("-y", (0, -1, 0)),
                    ("near +z", blender_dir(0.3, 0.004)), ("near -z", blender_dir(0.8, 0.996))]:
        names.append(name)
        dirs.append(np.asarray(d, dtype=np.float64))
    lum = probe @ np.array([0.2126, 0.7152, 0.0722])
    bi, bj = np.unravel_index(np.argmax(lum), lum.shape)
    for (i, j) in [(bi, bj), (2, 12), (10, 5), (13, 27), (0, 31), (15, 0)]:
        names.append("texel r%d c%d" % (i, j))
        dirs.append(blender_dir((j + 0.5) / W, (i + 0.5) / H))
    rng = np.random.default_rng(1)
    rnd = rng.normal(size=(2000, 3))
    rnd /= np.linalg.norm(rnd, axis=1, keepdims=True)
    dirs_all = np.concatenate([np.array(dirs), rnd])
    si = dr.zeros(mi.SurfaceInteraction3f, len(dirs_all))
    si.wi = mi.Vector3f(*(-dirs_all.T.astype(np.float32)))
    got = np.array(em.eval(si), dtype=np.float64)
    got = got.T if got.shape[0] == 3 else got
    want = blender_lookup(probe, dirs_all) * strength
    rel = np.abs(got - want).max(axis=1) / np.maximum(want.max(axis=1), 1e-6)
    print("envmap orientation check (Mitsuba emitter.eval vs Blender lookup formula):")
    for k, n in enumerate(names):
        print("  %-14s mitsuba %s  blender %s  max rel err %.1e"
              % (n, np.array2string(got[k], precision=5), np.array2string(want[k], precision=5), rel[k]))
    mirrored = blender_lookup(probe[:, ::-1], dirs_all[len(names):])
    print("  2000 random directions: max rel err %.2e (mean abs err %.2e; a mirrored probe would give %.2e)"
          % (rel[len(names):].max(), np.abs(got - want)[len(names):].mean(),
             np.abs(got[len(names):] - mirrored).mean()))
    assert rel.max() < 1e-3, "envmap orientation mismatch"
    return float(rel.max())


def check_camera(scene, c2ws, alphas, pts=None, res=RES):
    """`pts`: (label, world point) pairs to project (default: this scene's sphere centres and two
    box corners)."""
    print("camera check (NeRF projection in numpy vs Mitsuba sensor rays):")
    worst = 0.0
    if pts is None:
        pts = [("textured_sphere centre", SPHERE["centre"]), ("metal_sphere centre", METAL["centre"]),
               ("box corner (+x,-y,top)", (0.8, -0.6, 0.15)), ("box corner (-x,+y,top)", (-0.8, 0.6, 0.15))]
    for vi, (name, c2w) in enumerate(c2ws.items()):
        sensor = scene.sensors()[vi]
        for label, p in pts:
            px = nerf_project(c2w, FOV_X, res, res, np.asarray(p, dtype=np.float64))
            ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(float(px[0] / res), float(px[1] / res)), mi.Point2f(0.5, 0.5))
            o = np.array(ray.o).ravel()
            d = np.array(ray.d).ravel()
            to_p = np.asarray(p) - o
            ang = np.arctan2(np.linalg.norm(np.cross(d, to_p)), d @ to_p)   # stable for tiny angles
            worst = max(worst, ang)
            col, row = int(px[0]), int(px[1])
            a = alphas[name][row, col] if 0 <= row < res and 0 <= col < res else float("nan")
            print("  view %-5s %-24s -> pixel x=%.2f y=%.2f (col %d, row %d) alpha there %.3f; "
                  "Mitsuba ray through that film point misses the point by %.2e rad"
                  % (name, label, px[0], px[1], col, row, a, ang))
    assert worst < 1e-4, "camera conversion mismatch"
    return float(worst)


def check_texture_uv(scene, c2w, tex_lin):
    """Mitsuba's albedo at sphere hits == bilinear lookup of the decoded PNG at the OBJ vt
    with image row = (1 - vt) * H (OBJ convention)."""
    sensor = scene.sensors()[0]
    n = RES
    ys, xs = np.meshgrid((np.arange(n) + 0.5) / n, (np.arange(n) + 0.5) / n, indexing="ij")
    ray, _ = sensor.sample_ray(dr.zeros(mi.Float, n * n), 0.5,
                               mi.Point2f(xs.ravel().astype(np.float32), ys.ravel().astype(np.float32)),
                               dr.zeros(mi.Point2f, n * n))
    si = scene.ray_intersect(ray)
    albedo = np.array(si.bsdf().eval_diffuse_reflectance(si))
    albedo = albedo.T if albedo.shape[0] == 3 else albedo
    uv = np.array(si.uv)
    uv = uv.T if uv.shape[0] == 2 else uv
    p = np.array(si.p)
    p = p.T if p.shape[0] == 3 else p
    valid = np.array(si.is_valid())
    on_sphere = valid & (np.abs(np.linalg.norm(p - np.asarray(SPHERE["centre"]), axis=1) - SPHERE["radius"]) < 0.01)
    # Mitsuba's si.uv for an OBJ: find whether it equals vt or (u, 1 - vt) by comparing with
    # the analytic longitude/latitude of the hit (close to the interpolated vt).
    q = p[on_sphere] - np.asarray(SPHERE["centre"])
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    v_analytic = 1 - np.arccos(np.clip(q[:, 2], -1, 1)) / np.pi
    uvs = uv[on_sphere]
    flipped = np.abs((1 - uvs[:, 1]) - v_analytic).mean() < np.abs(uvs[:, 1] - v_analytic).mean()
    vt = np.stack([uvs[:, 0], 1 - uvs[:, 1] if flipped else uvs[:, 1]], axis=1)
    H, W, _ = tex_lin.shape
    x = vt[:, 0] * W - 0.5
    y = (1 - vt[:, 1]) * H - 0.5
    x0 = np.floor(x).astype(int)
    y0 = np.floor(y).astype(int)
    fx = (x - x0)[:, None]
    fy = (y - y0)[:, None]
    t = lambda yy, xx: tex_lin[yy % H, xx % W]
    look = ((1 - fy) * ((1 - fx) * t(y0, x0) + fx * t(y0, x0 + 1))
            + fy * ((1 - fx) * t(y0 + 1, x0) + fx * t(y0 + 1, x0 + 1)))
    err = np.abs(look - albedo[on_sphere]).max()
    y_noflip = vt[:, 1] * H - 0.5
    print("texture/UV check: %d sphere hits; Mitsuba si.uv.v = %s; max |albedo - lookup(row=(1-vt)H)| = %.2e"
          % (on_sphere.sum(), "1 - vt" if flipped else "vt", err))
    assert err < 2e-3, "texture orientation mismatch"
    return float(err)

def check_project_brdf(project_brdf, objects=None):
    """The Python BSDF vs an independent NumPy transcription of its formulas, and its sampling
    weights vs a cosine-sampled estimate of the same integral (unbiasedness of sample())."""
    rng = np.random.default_rng(3)
    ctx = mi.BSDFContext()
    worst_eval, worst_sample = 0.0, 0.0
    for o in (OBJECTS if objects is None else objects):
        m = o["material"]
        kd = [0.6, 0.3, 0.2] if isinstance(m["base_color"], str) else m["base_color"]
        b = mi.load_dict({"type": "project_brdf", "base_color": {"type": "rgb", "value": list(kd)},
                          "roughness": m["roughness"], "metallic": m["metallic"]})
        n = 200000
        wi = rng.normal(size=(n, 3))
        wi /= np.linalg.norm(wi, axis=1, keepdims=True)
        wi[:, 2] = np.abs(wi[:, 2])
        wo = rng.normal(size=(n, 3))
        wo /= np.linalg.norm(wo, axis=1, keepdims=True)
        wi, wo = wi.astype(np.float32), wo.astype(np.float32)
        si = dr.zeros(mi.SurfaceInteraction3f, n)
        si.wi = mi.Vector3f(*wi.T)
        si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
        got = np.array(b.eval(ctx, si, mi.Vector3f(*wo.T))).T
        want = project_brdf.reference_eval_numpy(kd, m["roughness"], m["metallic"], wi.astype(np.float64), wo.astype(np.float64))
        rel = np.abs(got - want) / np.maximum(np.abs(want), 1e-3)
        worst_eval = max(worst_eval, rel.max())
        v = np.array([np.sin(1.0), 0.0, np.cos(1.0)], dtype=np.float32)
        M = 2000000
        si = dr.zeros(mi.SurfaceInteraction3f, M)
        si.wi = mi.Vector3f(*[np.full(M, x, np.float32) for x in v])
        si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
        _, w = b.sample(ctx, si, mi.Float(rng.random(M).astype(np.float32)),
                        mi.Point2f(*rng.random((2, M)).astype(np.float32)))
        w = np.array(w)
        d = np.array(mi.warp.square_to_cosine_hemisphere(mi.Point2f(*rng.random((2, M)).astype(np.float32))))
        e = np.array(b.eval(ctx, si, mi.Vector3f(*d))) / np.maximum(d[2] / np.pi, 1e-12)
        a_s, a_c = w.mean(1), e.mean(1)
        # standard error of the difference of the two independent estimates
        sig = np.maximum(np.sqrt(e.var(1) / M + w.var(1) / M), 1e-6)
        worst_sample = max(worst_sample, float((np.abs(a_s - a_c) / sig).max()))
        print("project BRDF check %-15s eval vs NumPy max rel err %.1e; directional albedo at 57 deg: "
              "sample() %s, cosine-sampled %s (difference +-%.5f, i.e. %.1f sigma)"
              % (o["name"], rel.max(), np.round(a_s, 4), np.round(a_c, 4), sig.max(), (np.abs(a_s - a_c) / sig).max()))
    assert worst_eval < 1e-3 and worst_sample < 5, "project BRDF self-check failed"
    return float(worst_eval), worst_sample


# ---------------------------------------------------------------- main

def render_view(scene, idx, spp_total, seed_base, res=RES, halves=False):
    """Average of passes of PASS_SPP spp (seeds seed_base + k): (image, spp, estimated PSNR of the
    image vs the converged one), plus the two half averages (even / odd passes) if `halves`."""
    passes = max(2, spp_total // PASS_SPP)
    acc = [np.zeros((res, res, 4)), np.zeros((res, res, 4))]
    for k in range(passes):
        img = np.array(mi.render(scene, sensor=idx, seed=seed_base + k, spp=PASS_SPP), dtype=np.float64)
        acc[k % 2] += img
    half = [a / (passes // 2) for a in acc]
    full = (acc[0] + acc[1]) / passes
    # the error of the mean of all passes vs the converged image: MSE(A,B)/4 -> +6.02 dB
    noise_psnr = psnr(half[0][..., :3], half[1][..., :3]) + 10 * np.log10(4)
    if halves:
        return full, passes * PASS_SPP, noise_psnr, half
    return full, passes * PASS_SPP, noise_psnr


def render_aov(c2w, spp):
    """Base colour and shading normal (world) for one view: film averages over all camera
    samples (misses count 0), channels R G B A albedo.RGB nn.XYZ."""
    sc = mi.load_dict(scene_dict({"above": c2w}, {"type": "aov", "aovs": "albedo:albedo,nn:sh_normal",
        # inner integrator only to get alpha = coverage (max_depth 1: no lighting)
        "integrator": {"type": "path", "max_depth": 1, "hide_emitters": True}}, PASS_SPP))
    passes = max(1, spp // PASS_SPP)
    acc = 0.0
    for k in range(passes):
        mi.render(sc, seed=5000 + k, spp=PASS_SPP)
        bmp = sc.sensors()[0].film().bitmap()
        acc = acc + np.array(bmp, dtype=np.float64)
    st = bmp.struct_()
    names = [st[i].name for i in range(len(st))]
    pick = lambda ns: np.stack([acc[..., names.index(n)] for n in ns], axis=-1) / passes
    return pick(["A"]), pick(["albedo.R", "albedo.G", "albedo.B"]), pick(["nn.X", "nn.Y", "nn.Z"])


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--spp", type=int, default=65536)
    ap.add_argument("--variant", default="llvm_ad_rgb")
    ap.add_argument("--no-aov", action="store_true")
    args = ap.parse_args()
    mi.set_variant(args.variant)
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    import project_brdf      # defines a mi.BSDF subclass: needs the variant set first
    project_brdf.register()
    os.makedirs(SCENE_DIR, exist_ok=True)

    # 1. scene files
    mesh_stats = {}
    mesh_stats["box"] = write_box(os.path.join(SCENE_DIR, BOX["mesh"]), BOX["centre"], BOX["half"])
    mesh_stats["textured_sphere"] = write_uv_sphere(os.path.join(SCENE_DIR, SPHERE["mesh"]), SPHERE["centre"], SPHERE["radius"])
    mesh_stats["metal_sphere"] = write_uv_sphere(os.path.join(SCENE_DIR, METAL["mesh"]), METAL["centre"], METAL["radius"])
    tex_lin = make_texture(os.path.join(SCENE_DIR, SPHERE["material"]["base_color"]))
    src_probe = os.path.join(SHARED, "data", "probes", PROBE + ".hdr")
    if not os.path.exists(src_probe):
        sys.exit("probe not found: %s (set RECONSTRUCT_SHARED_DIR)" % src_probe)
    shutil.copyfile(src_probe, os.path.join(OUT, PROBE + ".hdr"))
    probe = convert_probe(src_probe, os.path.join(SCENE_DIR, PROBE + "_mitsuba.exr"))

    c2ws = {name: look_at_c2w(orbit(TARGET, v["dist"], v["azim"], v["elev"]), TARGET) for name, v in VIEWS.items()}
    integrator = {"type": "path", "max_depth": 2, "hide_emitters": True}
    scene = mi.load_dict(scene_dict(c2ws, integrator, PASS_SPP))

    # 2. checks that need no render
    env_err = check_envmap(scene, probe)
    uv_err = check_texture_uv(scene, c2ws["above"], tex_lin)

    # 3. renders
    times, noise, spp_done, alphas = {}, {}, {}, {}
    for vi, name in enumerate(c2ws):
        t0 = time.perf_counter()
        img, spp_done[name], noise[name] = render_view(scene, vi, args.spp, seed_base=1000 * (vi + 1))
        times[name] = time.perf_counter() - t0
        alphas[name] = img[..., 3]
        mi.Bitmap(img.astype(np.float32), pixel_format=mi.Bitmap.PixelFormat.RGBA).write(
            os.path.join(OUT, "ref_%s.exr" % name))
        print("view %s: %d spp in %.1f s; coverage %.1f%% of the image; estimated PSNR of the "
              "reference vs converged (linear RGB, clipped to [0,1]) %.1f dB"
              % (name, spp_done[name], times[name], 100 * img[..., 3].mean(), noise[name]))
    cam_err = check_camera(scene, c2ws, alphas)

    # same scene and light transport, but reconstruct's BRDF instead of Mitsuba's principled
    brdf_err, brdf_sigma = check_project_brdf(project_brdf)
    scene_p = mi.load_dict(scene_dict(c2ws, integrator, PASS_SPP, model="project"))
    times_p, noise_p, spp_p, psnr_vs_principled = {}, {}, {}, {}
    for vi, name in enumerate(c2ws):
        t0 = time.perf_counter()
        img, spp_p[name], noise_p[name] = render_view(scene_p, vi, args.spp, seed_base=1000 * (vi + 1))
        times_p[name] = time.perf_counter() - t0
        mi.Bitmap(img.astype(np.float32), pixel_format=mi.Bitmap.PixelFormat.RGBA).write(
            os.path.join(OUT, "ref_projectbrdf_%s.exr" % name))
        ref = np.array(mi.Bitmap(os.path.join(OUT, "ref_%s.exr" % name)), dtype=np.float64)
        psnr_vs_principled[name] = psnr(img[..., :3], ref[..., :3])
        print("view %s, project BRDF: %d spp in %.1f s; estimated PSNR vs converged %.1f dB; "
              "PSNR vs the principled render %.1f dB (linear, clipped), mean |diff| %.4f, max alpha diff %.1e"
              % (name, spp_p[name], times_p[name], noise_p[name], psnr(img[..., :3], ref[..., :3]),
                 np.abs(img[..., :3] - ref[..., :3]).mean(), np.abs(img[..., 3] - ref[..., 3]).max()))

    aov_info = None
    if not args.no_aov:
        t0 = time.perf_counter()
        a, albedo, normal = render_aov(c2ws["above"], 1024)
        # film values are averages over all camera samples (misses = 0): divide by coverage
        straight = np.where(a > 0, np.concatenate([albedo, normal], axis=-1) / np.maximum(a, 1e-8), 0.0)
        names = ["albedo.R", "albedo.G", "albedo.B", "normal.X", "normal.Y", "normal.Z", "A"]
        bmp = mi.Bitmap(mi.Bitmap.PixelFormat.MultiChannel, mi.Struct.Type.Float32, [RES, RES], len(names), names)
        np.array(bmp, copy=False)[:] = np.concatenate([straight, a], axis=-1).astype(np.float32)
        bmp.write(os.path.join(OUT, "aov_above.exr"))
        aov_info = {"file": "../aov_above.exr", "view": "above", "spp": 1024,
                    "channels": ["albedo.R", "albedo.G", "albedo.B", "normal.X", "normal.Y", "normal.Z", "A"],
                    "albedo": "linear base colour, coverage-normalised (straight)",
                    "normal": "world-space interpolated shading normal, not flipped (all meshes are closed and seen "
                              "from outside); coverage-normalised average, not renormalised at silhouettes",
                    "seconds": round(time.perf_counter() - t0, 1)}
        print("aov_above.exr written (%.1f s)" % aov_info["seconds"])

    # 4. scene.json
    objs = []
    for o in OBJECTS:
        e = {"name": o["name"], "mesh": o["mesh"], "vertices": mesh_stats[o["name"]][0],
             "triangles": mesh_stats[o["name"]][1], "shading": "smooth (vn)" if "radius" in o else "flat (vn per face)",
             "centre": list(o["centre"]), "material": material_json(o["material"])}
        if "radius" in o:
            e["radius"] = o["radius"]
        else:
            e["half_extents"] = list(o["half"])
        objs.append(e)
    cams = []
    for name, c2w in c2ws.items():
        cams.append({"name": name, "transform_matrix": c2w.tolist(), "camera_angle_x": FOV_X,
                     "width": RES, "height": RES, "reference": "../ref_%s.exr" % name,
                     "reference_project_brdf": "../ref_projectbrdf_%s.exr" % name,
                     "project_brdf_render_seconds": round(times_p[name], 1),
                     "project_brdf_estimated_psnr_db_vs_converged": round(noise_p[name], 1),
                     "spp": spp_done[name], "render_seconds": round(times[name], 1),
                     "estimated_psnr_db_vs_converged": round(noise[name], 1),
                     "look_at": list(TARGET), "orbit_deg": {"azimuth": VIEWS[name]["azim"], "elevation": VIEWS[name]["elev"]},
                     "distance": VIEWS[name]["dist"]})
    doc = {
        "format": "reconstruct-mitsuba-reference v1",
        "paths": "relative to the folder holding this scene.json",
        "generator": {"script": "tools/mitsuba/make_reference.py", "mitsuba": mi.__version__,
                      "drjit": dr.__version__, "variant": mi.variant(), "numpy": np.__version__,
                      "python": sys.version.split()[0]},
        "world": {"frame": "Blender, z up", "units": "arbitrary"},
        "objects": objs,
        "environment": {"file": "../%s.hdr" % PROBE, "strength": PROBE_STRENGTH,
                        "convention": "Blender equirect: phi = 2pi(0.5-u), theta = v*pi, "
                                      "d = (sin th cos phi, sin th sin phi, cos th); texel centres; bilinear, periodic in u and v",
                        "mitsuba_file": "%s_mitsuba.exr" % PROBE,
                        "mitsuba_to_world": EMITTER_TO_WORLD.tolist(),
                        "check_max_rel_err": env_err},
        "cameras": cams,
        "camera_convention": "NeRF: camera-to-world, OpenGL camera (x right, y up, looks down -z); "
                             "camera_angle_x = horizontal FOV (rad); focal = 0.5*width/tan(0.5*camera_angle_x); "
                             "pixel (col,row) centre at (col+0.5,row+0.5), row 0 at the top",
        "integrator": {"type": "path", "max_depth": 2, "hide_emitters": True,
                       "lighting": "direct only: one emitter sample + one BSDF sample per camera sample, MIS "
                                   "(power heuristic); shadow rays test every object; no inter-reflection"},
        "film": {"width": RES, "height": RES, "filter": "box (1 pixel)", "sampler": "ldsampler",
                 "pixel_format": "RGBA float32, linear",
                 "alpha": "pixel coverage", "rgb": "premultiplied by coverage (background radiance counted as 0)"},
        "spp": min(spp_done.values()),
        "checks": {"camera_max_angle_err_rad": cam_err, "texture_max_abs_err": uv_err,
                   "project_brdf_eval_max_rel_err": brdf_err,
                   "project_brdf_sampling_max_sigma": round(brdf_sigma, 2)},
        "project_brdf": {"module": "tools/mitsuba/project_brdf.py",
                         "model": "docs/model.md, BRDF: Lambert kd(1-m); GGX alpha = max(r,0.08)^2, height-correlated "
                                  "Smith, Schlick F with F0 = 0.04(1-m) + kd m; two-sided",
                         "references": {n: "../ref_projectbrdf_%s.exr" % n for n in c2ws},
                         "psnr_db_vs_principled": {n: round(v, 1) for n, v in psnr_vs_principled.items()}},
    }
    if aov_info:
        doc["aov"] = aov_info
    with open(os.path.join(SCENE_DIR, "scene.json"), "w") as f:
        json.dump(doc, f, indent=1)
    print("wrote", os.path.join(SCENE_DIR, "scene.json"))


if __name__ == "__main__":
    main()

#!/usr/bin/env python
"""Ground truth for the procedural benchmark: Open3D ray casting vs Mitsuba 3, measured.

For each benchmark scene (and the glossy scene's bend) one camera of the test orbit is rendered at
the ``default`` preset's resolution by

* ``RayCaster`` (``ne_jax.benchmark.scenes``) at ``ss`` = 2 and 3: time per image, bit-for-bit
  repeatability, and the difference to the same renderer at ``ss`` = 8 (its own converged image:
  what is left is edge aliasing, not noise);
* Mitsuba 3 (``scalar_rgb`` unless a usable LLVM >= 16 is present, see :func:`choose_variant`) with
  the same mesh: vertex colours from the albedo textures, ``principled`` for glossy materials
  (roughness from the Blinn-Phong exponent), ``diffuse`` otherwise, the same directional lights and
  an environment map of the ``sky()`` gradient scaled to the ambient level, ``path`` integrator.
  At 32 and 128 spp: time per image, noise as the PSNR between two seeds and against a high-spp
  reference (one view per scene), and repeatability for a fixed seed.

PSNR is taken as the benchmark scores images: display values in [0, 1] composited over white, over
the whole image (``psnr``) and over the pixels the reference covers (``psnr_object``, stricter:
the empty background is noise-free in every renderer).

Outputs: ``experiments/results/compare_renderers.{json,md,png}``.  Run from the repository root::

    .venv/bin/python -m experiments.compare_renderers

``--quick`` renders tiny images at low spp to check the script in seconds.
"""

from __future__ import annotations

import argparse
import ctypes.util
import glob
import json
import math
import os
import platform
import re
import sys
import time
from pathlib import Path

import numpy as np

from ne_jax.benchmark import meshes as M
from ne_jax.benchmark import raycaster
from ne_jax.benchmark import scenes as S
from ne_jax.benchmark.generate import get_preset
from ne_jax.data import cameras

CPU_SECONDS: list[float] = []  # process CPU time of each Mitsuba render, in call order
RESULTS = Path(__file__).resolve().parent / "results"
INSTALL_HINT = "pip install 'ne_jax[mitsuba]'"

# ------------------------------------------------------------------------- Mitsuba variant choice

LLVM_GLOBS = (
    "/usr/lib/x86_64-linux-gnu/libLLVM*.so*",
    "/usr/lib/aarch64-linux-gnu/libLLVM*.so*",
    "/usr/lib/llvm-*/lib/libLLVM*.so*",
    "/usr/lib64/libLLVM*.so*",
    "/usr/local/lib/libLLVM*.so*",
    "/opt/homebrew/opt/llvm/lib/libLLVM*.dylib",
)


def llvm_major(path: str) -> int | None:
    """LLVM major version from a library path (``libLLVM-15.so.1``, ``libLLVM.so.19.1``,
    ``libLLVM-14.0.6.so.1``, ``/usr/lib/llvm-16/lib/libLLVM.so``), following symlinks; None if
    it cannot be told."""
    for candidate in (path, os.path.realpath(path)):
        name = os.path.basename(candidate)
        m = re.search(r"libLLVM(?:-|\.so\.)(\d+)", name) or re.search(r"llvm-(\d+)", candidate)
        if m:
            return int(m.group(1))
    return None


def find_llvm_libraries() -> dict[str, int | None]:
    """Every libLLVM this machine has (file path -> major version), found by looking at files only:
    loading a too-old LLVM into Dr.Jit aborts the process, so nothing here is tried."""
    found: dict[str, int | None] = {}
    for pattern in LLVM_GLOBS:
        for path in sorted(glob.glob(pattern)):
            found[path] = llvm_major(path)
    env = os.environ.get("DRJIT_LIBLLVM_PATH")
    if env and os.path.exists(env):
        found[env] = llvm_major(env)
    soname = ctypes.util.find_library("LLVM")  # a name such as 'libLLVM-15.so.1', not a path
    if soname and not any(os.path.basename(p) == soname for p in found):
        found[soname] = llvm_major(soname)
    return found


def choose_variant(requested: str, available: list[str], llvm_libs: dict[str, int | None]):
    """``(variant, reason, llvm_path)``; ``llvm_path`` is what DRJIT_LIBLLVM_PATH must name for an
    LLVM variant. Raises ``RuntimeError`` when ``llvm_ad_rgb`` is asked for but cannot run here."""
    usable = {p: v for p, v in llvm_libs.items() if v is not None and v >= 16 and os.path.exists(p)}
    env = os.environ.get("DRJIT_LIBLLVM_PATH")
    if env and env not in usable:
        # Dr.Jit would load exactly this file; if it is not a usable LLVM, no LLVM variant may run.
        usable = {}
    by_version: dict = {}
    for p, v in sorted(llvm_libs.items()):
        by_version.setdefault(v, []).append(p)
    summary = "; ".join(
        f"LLVM {'?' if v is None else v} ({', '.join(sorted({os.path.basename(os.path.realpath(p)) for p in ps}))})"
        for v, ps in sorted(by_version.items(), key=lambda kv: -1 if kv[0] is None else kv[0])
    ) or "no libLLVM at all"
    if requested == "scalar_rgb":
        return "scalar_rgb", "requested on the command line", None
    if "llvm_ad_rgb" not in available:
        reason = f"this Mitsuba build has no llvm_ad_rgb variant (variants: {', '.join(available)})"
        if requested == "llvm_ad_rgb":
            raise RuntimeError(reason)
        return "scalar_rgb", reason, None
    if not usable:
        reason = (
            f"llvm_ad_rgb needs libLLVM >= 16 and this machine has: {summary}"
            + (f" (DRJIT_LIBLLVM_PATH={env} is not one)" if env else "")
            + "; with an older LLVM Dr.Jit aborts the process uncatchably, so llvm_ad_rgb is not attempted"
        )
        if requested == "llvm_ad_rgb":
            raise RuntimeError(reason)
        return "scalar_rgb", reason, None
    path = max(usable, key=lambda p: usable[p])
    if env:
        path = env
    return "llvm_ad_rgb", f"found {path} (LLVM {usable[path]} >= 16); llvm_ad_rgb is 2-3x faster than scalar_rgb", path


# ------------------------------------------------------------------------------- image helpers


def to_display_white(rgba: np.ndarray) -> np.ndarray:
    """Straight-alpha display RGBA -> RGB over a white background (how the benchmark scores)."""
    a = rgba[..., 3:4]
    return rgba[..., :3] * a + (1.0 - a)


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    err = (a - b) ** 2
    if mask is not None:
        if not mask.any():
            return float("nan")
        err = err[mask]
    mse = float(np.mean(err))
    return float("inf") if mse == 0.0 else 10.0 * math.log10(1.0 / mse)


def fmt_db(x: float) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "-"
    return "inf (identical)" if math.isinf(x) else f"{x:.1f}"


def jsonable(x):
    if isinstance(x, dict):
        return {k: jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, (float, np.floating)):
        x = float(x)
        return None if math.isnan(x) else ("inf" if math.isinf(x) else round(x, 4))
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


# ------------------------------------------------------------------------------ Mitsuba scenes


def sky_envmap(width: int = 256) -> np.ndarray:
    """Lat-long bitmap ``[width/2, width, 3]`` of ``raycaster.sky()`` without its sun lobe (the sun is the
    first directional light), scaled so its mean radiance equals ``raycaster.AMBIENT`` (the ray caster's
    ambient term). Pixel (u, v) holds the radiance from Mitsuba's envmap direction
    ``(sin(pi v) sin(2 pi u), cos(pi v), -sin(pi v) cos(2 pi u))`` (envmap ``to_world`` identity)."""
    h = width // 2
    u = (np.arange(width) + 0.5) / width
    v = (np.arange(h) + 0.5) / h
    uu, vv = np.meshgrid(u, v)
    st = np.sin(np.pi * vv)
    d = np.stack([st * np.sin(2 * np.pi * uu), np.cos(np.pi * vv), -st * np.cos(2 * np.pi * uu)], -1).reshape(-1, 3)
    t = np.clip(0.5 + 0.5 * d[:, 2], 0.0, 1.0)[:, None]
    base = (1 - t) * np.array([0.12, 0.10, 0.08]) + t * np.array([0.45, 0.6, 0.9])
    # The same gradient as raycaster.sky() (check_envmap compares them); the sun lobe is left out here.
    weights = st.reshape(-1)  # solid angle of each pixel, up to a constant
    mean_lum = float(np.sum(weights * (base @ np.array([0.2126, 0.7152, 0.0722]))) / np.sum(weights))
    return (base * (raycaster.AMBIENT / mean_lum)).reshape(h, width, 3).astype(np.float32), d.reshape(h, width, 3)


def check_envmap(mi) -> None:
    """Evaluate Mitsuba's envmap emitter in a few world directions and check it returns
    ``raycaster.sky()`` (less its sun lobe) times one constant: catches a slip in the direction convention."""
    import drjit as dr

    env, _ = sky_envmap()
    emitter = mi.load_dict({"type": "envmap", "bitmap": mi.Bitmap(env)})
    dirs = np.random.default_rng(0).normal(size=(24, 3))
    dirs = np.concatenate([[[0, 0, 1.0], [0, 0, -1.0], [1.0, 0, 0]], dirs])
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    sun = np.asarray(raycaster.LIGHTS[0].direction, float)
    sun /= np.linalg.norm(sun)
    want = raycaster.sky(dirs) - 2.0 * np.clip(dirs @ sun, 0.0, 1.0)[:, None] ** 200
    got = []
    for d in dirs:
        si = dr.zeros(mi.SurfaceInteraction3f)
        si.wi = mi.Vector3f(*(-d))  # the emitter is seen looking along d
        got.append(np.array(emitter.eval(si), dtype=np.float64).reshape(-1)[:3])
    ratio = np.array(got) / want
    if not np.allclose(ratio, np.median(ratio), rtol=0.03):
        raise AssertionError("Mitsuba envmap does not reproduce raycaster.sky(): "
                             f"ratios {ratio.min():.3f}..{ratio.max():.3f}")


def mitsuba_bsdf(material: S.Material) -> dict:
    color = {"type": "mesh_attribute", "name": "vertex_color"}
    if material.ks <= 0.0 and material.reflect <= 0.0:
        inner = {"type": "diffuse", "reflectance": color}
    else:
        # Blinn-Phong exponent n <-> Beckmann/GGX alpha = sqrt(2 / (n + 2)); principled uses the
        # Disney parametrisation alpha = roughness^2. `specular` sets F0 = 0.08 * specular: with
        # specular = ks the highlight peak comes out near the ray caster's ks * intensity.
        alpha = math.sqrt(2.0 / (material.shininess + 2.0))
        inner = {
            "type": "principled",
            "base_color": color,
            "roughness": float(math.sqrt(alpha)),
            "specular": float(min(1.0, material.ks)),
            "metallic": 0.0,
        }
    return {"type": "twosided", "bsdf": inner}


def mitsuba_scene(mi, edited: S.EditedMesh, materials, c2w: np.ndarray, res: int, spp: int) -> object:
    """A Mitsuba scene of the (edited) mesh, split by material, seen by ``c2w``."""
    normals = M.vertex_normals(edited.vertices, edited.faces)
    parts = {}
    for i, material in enumerate(materials):
        faces = edited.faces[edited.material == i]
        if len(faces) == 0:
            continue
        used = np.unique(faces)
        remap = np.full(len(edited.vertices), -1, np.int64)
        remap[used] = np.arange(len(used))
        # Albedo from the texture at rest positions (textures follow the surface), linearised the
        # same way the ray caster does it (gamma 2.2), one colour per vertex.
        albedo = np.clip(material.albedo(edited.rest[used]), 0.0, 1.0) ** raycaster.GAMMA
        props = mi.Properties()
        props["bsdf"] = mi.load_dict(mitsuba_bsdf(material))
        mesh = mi.Mesh(f"part{i}", len(used), len(faces), props=props, has_vertex_normals=True)
        params = mi.traverse(mesh)
        for key, arr in (
            ("vertex_positions", edited.vertices[used].astype(np.float32).ravel()),
            ("faces", remap[faces].astype(np.uint32).ravel()),
            ("vertex_normals", normals[used].astype(np.float32).ravel()),
        ):
            params[key] = type(params[key])(arr)
        params.update()
        mesh.add_attribute("vertex_color", 3, type(params["vertex_positions"])(albedo.astype(np.float32).ravel()))
        parts[f"part{i}"] = mesh
    env, _ = sky_envmap()
    scene = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 8, "hide_emitters": True},
        "sensor": {
            "type": "perspective",
            "fov": float(np.degrees(cameras.CAMERA_ANGLE_X)),
            "fov_axis": "x",
            # NeRF/Blender c2w looks along -z with +x right; Mitsuba's camera looks along +z with
            # +x to the left.
            "to_world": mi.ScalarTransform4f((c2w @ np.diag([-1.0, 1.0, -1.0, 1.0])).tolist()),
            "film": {"type": "hdrfilm", "width": res, "height": res, "pixel_format": "rgba",
                     "rfilter": {"type": "box"}},
            "sampler": {"type": "independent", "sample_count": spp},
        },
        "sky": {"type": "envmap", "bitmap": mi.Bitmap(env)},
        **parts,
    }
    for k, light in enumerate(raycaster.LIGHTS):
        d = np.asarray(light.direction, float)
        d /= np.linalg.norm(d)
        # The ray caster adds intensity * albedo * cos; a diffuse BSDF gives albedo / pi * E * cos.
        scene[f"sun{k}"] = {"type": "directional", "direction": (-d).tolist(),
                            "irradiance": {"type": "rgb", "value": [math.pi * light.intensity] * 3}}
        # (Mitsuba has no unshadowed light; LIGHTS[2], the dim fill light, casts shadows here.)
    return mi.load_dict(scene)


def mitsuba_render(mi, scene, spp: int, seed: int) -> tuple[np.ndarray, float, int]:
    """Straight-alpha display RGBA (gamma 2.2 like the ray caster), seconds, NaN pixel count."""
    t0, c0 = time.perf_counter(), time.process_time()
    img = np.array(mi.render(scene, spp=spp, seed=seed), dtype=np.float64)
    seconds = time.perf_counter() - t0
    CPU_SECONDS.append(time.process_time() - c0)
    bad = ~np.isfinite(img).all(-1)
    img[bad] = 0.0
    rgb, a = img[..., :3], np.clip(img[..., 3:4], 0.0, 1.0)
    lin = np.where(a > 0, rgb / np.maximum(a, 1e-8), 0.0)  # Mitsuba's film is premultiplied
    display = np.clip(lin, 0.0, 1.0) ** (1.0 / raycaster.GAMMA)
    return np.concatenate([display, a], -1), seconds, int(bad.sum())


# ------------------------------------------------------------------------------------ main


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=RESULTS, help="output folder (default: experiments/results)")
    p.add_argument("--variant", choices=("auto", "scalar_rgb", "llvm_ad_rgb"), default="auto",
                   help="Mitsuba variant; auto = llvm_ad_rgb only where libLLVM >= 16 is found, else scalar_rgb")
    p.add_argument("--res", type=int, default=None, help="image size (default: the 'default' preset's)")
    p.add_argument("--ss", type=int, nargs="+", default=[2, 3], help="ray-caster supersampling settings")
    p.add_argument("--ref-ss", type=int, default=8, help="ray-caster 'converged' supersampling")
    p.add_argument("--spp", type=int, nargs="+", default=[32, 128], help="Mitsuba sample counts")
    p.add_argument("--ref-spp", type=int, default=1024, help="Mitsuba reference sample count (one view)")
    p.add_argument("--view", type=int, default=3, help="which of the 'default' preset's test-orbit cameras")
    p.add_argument("--quick", action="store_true", help="64x64, ss 2/3 vs 4, 8/16 vs 64 spp: a smoke test")
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    try:
        import mitsuba as mi
    except ImportError as e:
        print(f"compare_renderers: Mitsuba 3 is not installed ({e}).\n"
              f"Install the optional extra with:  {INSTALL_HINT}\n"
              "(the ray caster alone needs no Mitsuba: the benchmark itself does not use it)", file=sys.stderr)
        return 2

    preset = get_preset("default")
    res = args.res or preset.resolution
    ss_list, ref_ss, spp_list, ref_spp = args.ss, args.ref_ss, args.spp, args.ref_spp
    if args.quick:
        res, ss_list, ref_ss, spp_list, ref_spp = 64, [2, 3], 4, [8, 16], 64

    llvm_libs = find_llvm_libraries()
    try:
        variant, reason, llvm_path = choose_variant(args.variant, list(mi.variants()), llvm_libs)
    except RuntimeError as e:
        print(f"compare_renderers: cannot use llvm_ad_rgb: {e}", file=sys.stderr)
        return 3
    if llvm_path and not os.environ.get("DRJIT_LIBLLVM_PATH"):
        os.environ["DRJIT_LIBLLVM_PATH"] = llvm_path  # read by Dr.Jit when the LLVM backend starts
    print(f"libLLVM found: {llvm_libs or 'none'}")
    print(f"Mitsuba {mi.__version__}: using variant {variant} -- {reason}")
    mi.set_variant(variant)

    check_envmap(mi)

    configs = [(name, None) for name in S.SCENES] + [("glossy", "bend")]
    c2w = cameras.orbit_cameras(preset.test_views)[args.view]
    results = []
    images = {}
    t_all = time.perf_counter()
    load_before = os.getloadavg()
    for scene_name, edit_name in configs:
        label = scene_name + (f"/{edit_name}" if edit_name else "")
        scene = S.get_scene(scene_name, preset.detail)
        edited = S.apply_to_mesh(scene.mesh, scene.edits[edit_name] if edit_name else None)
        row = {"scene": scene_name, "edit": edit_name, "faces": len(edited.faces)}

        # --- ray caster
        t0 = time.perf_counter()
        caster = raycaster.RayCaster(edited, scene.materials)
        row["raycaster_build_s"] = time.perf_counter() - t0
        ref_rc = caster.render(c2w, res, res, cameras.CAMERA_ANGLE_X, ref_ss)
        rc = {}
        for ss in ss_list:
            times, cpu, renders = [], [], []
            for _ in range(3):
                t0, c0 = time.perf_counter(), time.process_time()
                renders.append(caster.render(c2w, res, res, cameras.CAMERA_ANGLE_X, ss))
                times.append(time.perf_counter() - t0)
                cpu.append(time.process_time() - c0)
            img = renders[0]
            mask = ref_rc[..., 3] > 0
            rc[ss] = {
                "seconds": times,
                "cpu_seconds": cpu,
                "ms_per_image": 1000 * min(times),
                "cpu_ms_per_image": 1000 * min(cpu),
                "deterministic": all(np.array_equal(renders[0], r) for r in renders[1:]),
                "psnr_vs_converged": psnr(to_display_white(img), to_display_white(ref_rc)),
                "psnr_object_vs_converged": psnr(to_display_white(img), to_display_white(ref_rc), mask),
            }
            images[(label, f"rc{ss}")] = img
        row["raycaster"] = rc
        images[(label, "rc_ref")] = ref_rc

        # --- Mitsuba
        t0 = time.perf_counter()
        ms_scene = mitsuba_scene(mi, edited, scene.materials, c2w, res, max(spp_list))
        row["mitsuba_build_s"] = time.perf_counter() - t0
        ref, t_ref, nan_ref = mitsuba_render(mi, ms_scene, ref_spp, seed=1_000_003)
        row["mitsuba_reference"] = {"spp": ref_spp, "seconds": t_ref, "nan_pixels": nan_ref}
        images[(label, "mi_ref")] = ref
        ref_w, mask = to_display_white(ref), ref[..., 3] > 0
        mt = {}
        for spp in spp_list:
            a, ta, na = mitsuba_render(mi, ms_scene, spp, seed=0)
            b, tb, nb = mitsuba_render(mi, ms_scene, spp, seed=1)
            a2, tc, _ = mitsuba_render(mi, ms_scene, spp, seed=0)
            cpu = CPU_SECONDS[-3:]
            aw, bw = to_display_white(a), to_display_white(b)
            mt[spp] = {
                "seconds": [ta, tb, tc],
                "cpu_seconds": cpu,
                "ms_per_image": 1000 * min(ta, tb, tc),
                "cpu_ms_per_image": 1000 * min(cpu),
                "deterministic_same_seed": bool(np.array_equal(a, a2)),
                "psnr_seed_vs_seed": psnr(aw, bw),
                "psnr_object_seed_vs_seed": psnr(aw, bw, mask),
                "psnr_vs_reference": psnr(aw, ref_w),
                "psnr_object_vs_reference": psnr(aw, ref_w, mask),
                "nan_pixels": na + nb,
            }
            images[(label, f"mi{spp}")] = a
        row["mitsuba"] = mt
        # How far apart the two renderers' pictures are (different shading models) and whether the
        # silhouettes agree (catches camera-convention slips: IoU should be ~1).
        rc_best = images[(label, f"rc{max(ss_list)}")]
        a_rc, a_mi = rc_best[..., 3] > 0.5, ref[..., 3] > 0.5
        row["cross"] = {
            "alpha_iou": float((a_rc & a_mi).sum() / max(1, (a_rc | a_mi).sum())),
            "psnr_raycaster_vs_mitsuba_reference": psnr(to_display_white(rc_best), ref_w),
        }
        results.append(row)
        print(f"{label:12s} faces {row['faces']:6d} | "
              + " ".join(f"ss{ss} {rc[ss]['ms_per_image']:6.0f} ms" for ss in ss_list) + " | "
              + " ".join(f"{spp}spp {mt[spp]['ms_per_image']:6.0f} ms {fmt_db(mt[spp]['psnr_object_vs_reference'])} dB"
                         for spp in spp_list)
              + f" | ref {ref_spp}spp {t_ref:.1f} s | IoU {row['cross']['alpha_iou']:.3f}", flush=True)

    # ---------------------------------------------------------------------------- summary
    n_scenes = len(S.SCENES)
    n_edits = len(S.get_scene("glossy", 0.25).edits)
    originals = preset.train_views + preset.val_views + preset.test_views
    edited_views = preset.train_views + preset.test_views
    total_images = n_scenes * (originals + n_edits * edited_views)
    test_images = n_scenes * (1 + n_edits) * preset.test_views
    n_variants = n_scenes * (1 + n_edits)

    def mean(xs):
        xs = [x for x in xs if x is not None and not math.isnan(x)]
        return float(np.mean(xs)) if xs else float("nan")

    def mean_db(xs):  # average the MSEs, not the dB values
        xs = [x for x in xs if not math.isnan(x)]
        if any(math.isinf(x) for x in xs):
            return float("inf") if all(math.isinf(x) for x in xs) else mean_db([x for x in xs if not math.isinf(x)])
        return -10 * math.log10(np.mean([10 ** (-x / 10) for x in xs])) if xs else float("nan")

    summary = []
    rc_build = mean([r["raycaster_build_s"] for r in results])
    mi_build = mean([r["mitsuba_build_s"] for r in results])
    for ss in ss_list:
        ms = mean([r["raycaster"][ss]["ms_per_image"] for r in results])
        summary.append({
            "renderer": "Open3D RayCaster", "setting": f"ss={ss} ({ss * ss} rays/px)", "ms_per_image": ms,
            "cpu_ms_per_image": mean([r["raycaster"][ss]["cpu_ms_per_image"] for r in results]),
            "psnr_vs_converged": mean_db([r["raycaster"][ss]["psnr_vs_converged"] for r in results]),
            "psnr_object_vs_converged": mean_db([r["raycaster"][ss]["psnr_object_vs_converged"] for r in results]),
            "psnr_seed_vs_seed": float("inf"),
            "deterministic": all(r["raycaster"][ss]["deterministic"] for r in results),
            "converged_means": f"same renderer at ss={ref_ss} (aliasing only)",
            "preset_minutes": (ms / 1000 * total_images + rc_build * n_variants) / 60,
        })
    for spp in spp_list:
        ms = mean([r["mitsuba"][spp]["ms_per_image"] for r in results])
        summary.append({
            "renderer": f"Mitsuba 3 {variant}", "setting": f"{spp} spp", "ms_per_image": ms,
            "cpu_ms_per_image": mean([r["mitsuba"][spp]["cpu_ms_per_image"] for r in results]),
            "psnr_vs_converged": mean_db([r["mitsuba"][spp]["psnr_vs_reference"] for r in results]),
            "psnr_object_vs_converged": mean_db([r["mitsuba"][spp]["psnr_object_vs_reference"] for r in results]),
            "psnr_seed_vs_seed": mean_db([r["mitsuba"][spp]["psnr_seed_vs_seed"] for r in results]),
            "psnr_object_seed_vs_seed": mean_db([r["mitsuba"][spp]["psnr_object_seed_vs_seed"] for r in results]),
            "deterministic": all(r["mitsuba"][spp]["deterministic_same_seed"] for r in results),
            "converged_means": f"same renderer at {ref_spp} spp",
            "preset_minutes": (ms / 1000 * total_images + mi_build * n_variants) / 60,
        })
    ref_ms = 1000 * mean([r["mitsuba_reference"]["seconds"] for r in results])
    if len(spp_list) >= 2:
        lo, hi = min(spp_list), max(spp_list)
        ms_lo = mean([r["mitsuba"][lo]["ms_per_image"] for r in results])
        ms_hi = mean([r["mitsuba"][hi]["ms_per_image"] for r in results])
        mixed = ((total_images - test_images) * ms_lo + test_images * ms_hi) / 1000 / 60 + mi_build * n_variants / 60
        summary.append({
            "renderer": f"Mitsuba 3 {variant}", "setting": f"{lo} spp train/val + {hi} spp test",
            "ms_per_image": ((total_images - test_images) * ms_lo + test_images * ms_hi) / total_images,
            "cpu_ms_per_image": float("nan"),
            "psnr_vs_converged": float("nan"), "psnr_object_vs_converged": float("nan"),
            "psnr_seed_vs_seed": float("nan"),
            "deterministic": all(s["deterministic"] for s in summary if s["renderer"].startswith("Mitsuba")),
            "converged_means": "see the two rows above", "preset_minutes": mixed,
        })

    cross = {
        "alpha_iou_min": min(r["cross"]["alpha_iou"] for r in results),
        "psnr_raycaster_vs_mitsuba_reference": mean_db([r["cross"]["psnr_raycaster_vs_mitsuba_reference"]
                                                        for r in results]),
    }
    wall = time.perf_counter() - t_all
    load_after = os.getloadavg()

    # ------------------------------------------------------------------------------ outputs
    args.out.mkdir(parents=True, exist_ok=True)
    header = ("| renderer | setting | ms/image | CPU ms/image | noise PSNR vs converged, dB (whole image / object) | "
              "seed-to-seed PSNR, dB (whole / object) | deterministic | `default` preset, min |")
    lines = [header, "|---|---|---:|---:|---|---|---|---:|"]
    for s in summary:
        vs = ("-" if math.isnan(s["psnr_vs_converged"])
              else f"{fmt_db(s['psnr_vs_converged'])} / {fmt_db(s['psnr_object_vs_converged'])}")
        if s["renderer"].startswith("Open3D"):
            seed = "n/a (no randomness)"
            vs += f" (vs ss={ref_ss}: aliasing, no noise)"
        elif math.isnan(s["psnr_seed_vs_seed"]):
            seed = "-"
        else:
            seed = f"{fmt_db(s['psnr_seed_vs_seed'])} / {fmt_db(s['psnr_object_seed_vs_seed'])}"
        det = "yes (bit-identical)" if s["deterministic"] else "no"
        if s["renderer"].startswith("Mitsuba") and s["deterministic"]:
            det = "yes for a fixed seed"
        cpu_ms = "-" if math.isnan(s["cpu_ms_per_image"]) else f"{s['cpu_ms_per_image']:.0f}"
        lines.append(f"| {s['renderer']} | {s['setting']} | {s['ms_per_image']:.0f} | {cpu_ms} | {vs} | {seed} | "
                     f"{det} | {s['preset_minutes']:.1f} |")
    per_scene = ["", "| scene | faces | " + " | ".join(f"RC ss={ss} ms" for ss in ss_list) + " | "
                 + " | ".join(f"MI {spp} spp ms (object PSNR vs ref)" for spp in spp_list)
                 + f" | MI {ref_spp} spp s | silhouette IoU |",
                 "|---|---:|" + "---:|" * len(ss_list) + "---|" * len(spp_list) + "---:|---:|"]
    for r in results:
        label = r["scene"] + (f"/{r['edit']}" if r["edit"] else "")
        mits = [f"{r['mitsuba'][spp]['ms_per_image']:.0f} ({fmt_db(r['mitsuba'][spp]['psnr_object_vs_reference'])})"
                for spp in spp_list]
        per_scene.append(f"| {label} | {r['faces']} | "
                         + " | ".join(f"{r['raycaster'][ss]['ms_per_image']:.0f}" for ss in ss_list)
                         + " | " + " | ".join(mits)
                         + f" | {r['mitsuba_reference']['seconds']:.1f} | {r['cross']['alpha_iou']:.3f} |")
    md = "\n".join([
        f"# Ground-truth renderers compared ({res}x{res}, {os.cpu_count()} CPU cores, "
        f"Mitsuba {mi.__version__} `{variant}`)",
        "",
        f"Variant: `{variant}` -- {reason}.",
        "",
        *lines,
        "",
        (f"`default` preset: {total_images} images ({n_scenes} scenes x (original {originals} + {n_edits} edits x "
        f"{edited_views})), "
        f"{n_variants} meshes; the projection adds the per-mesh set-up time "
        f"(ray caster {rc_build:.2f} s, Mitsuba {mi_build:.2f} s). Mitsuba reference ({ref_spp} spp): "
        f"{ref_ms / 1000:.1f} s per image."),
        "",
        ("Cross-renderer (different shading models, for information): silhouette IoU >= "
        f"{cross['alpha_iou_min']:.3f}, "
        f"PSNR ray caster ss={max(ss_list)} vs Mitsuba reference "
        f"{cross['psnr_raycaster_vs_mitsuba_reference']:.1f} dB."),
        *per_scene,
        "",
        (f"Whole run: {wall:.0f} s; load average {load_before[0]:.1f} before, {load_after[0]:.1f} after "
        f"(on {os.cpu_count()} cores: above that, other processes shared the CPU and wall times are inflated). "
        "ms/image is the fastest of 3 renders (wall clock), CPU ms/image the least process CPU time of "
        "the same renders (all threads; less sensitive to other load)."),
        "",
        ("Mitsuba's noise against the true converged image is about the seed-to-seed PSNR + 3 dB (two independent "
        "noises); the PSNR against the reference is a little lower than that because the reference is noisy too."),
        "",
    ])
    (args.out / "compare_renderers.md").write_text(md)
    print("\n" + md)

    report = {
        "resolution": res, "camera": {"preset_test_orbit_view": args.view, "c2w": c2w.tolist()},
        "machine": {"cpu_count": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version(),
                    "loadavg_before": load_before, "loadavg_after": load_after},
        "timing": "ms_per_image = the fastest of 3 renders (wall clock); cpu_seconds = process CPU time of each",
        "mitsuba": {"version": mi.__version__, "variant": variant, "reason": reason,
                    "llvm_libraries": {p: v for p, v in llvm_libs.items()}, "reference_spp": ref_spp},
        "psnr_convention": "display values in [0,1] over white; 'object' = pixels the reference covers",
        "preset": {"name": preset.name, "images": total_images, "test_images": test_images, "meshes": n_variants},
        "summary": summary, "cross_renderer": cross, "per_scene": results, "wall_seconds": wall,
    }
    (args.out / "compare_renderers.json").write_text(json.dumps(jsonable(report), indent=1) + "\n")

    # Side-by-side: our render | Mitsuba lowest spp | Mitsuba reference, for two scenes.
    from PIL import Image, ImageDraw

    rows = [lab for lab in ("glossy/bend", "blocks") if (lab, "mi_ref") in images]
    cols = [(f"rc{max(ss_list)}", f"ray caster ss={max(ss_list)}"),
            (f"mi{min(spp_list)}", f"Mitsuba {min(spp_list)} spp"),
            ("mi_ref", f"Mitsuba {ref_spp} spp")]
    pad, top = 4, 14
    sheet = Image.new("RGB", (len(cols) * (res + pad) + pad, len(rows) * (res + top + pad) + pad), "white")
    draw = ImageDraw.Draw(sheet)
    for i, lab in enumerate(rows):
        for j, (key, title) in enumerate(cols):
            tile = np.round(np.clip(to_display_white(images[(lab, key)]), 0, 1) * 255).astype(np.uint8)
            x, y = pad + j * (res + pad), pad + i * (res + top + pad)
            sheet.paste(Image.fromarray(tile), (x, y + top))
            draw.text((x + 2, y), f"{lab} | {title}", fill=(0, 0, 0))
    sheet.save(args.out / "compare_renderers.png")
    print(f"wrote {args.out / 'compare_renderers.json'}, .md and .png ({wall:.0f} s)")
    return 0


if __name__ == "__main__":
    import ne_jax

    ne_jax.setup(huge_pages=True)  # as `ne-jax` does: a host device per core, huge pages (restarts)
    sys.exit(main())

"""Rendering throughput per preset, and what each declared effect costs.

    python -m experiments.bench_render            # all presets and effects (several minutes on CPU)
    python -m experiments.bench_render --quick    # small cloud, tiny + default only

A random model (``common.bench_cloud``), 100 x 100 images (docs/studies/rendering.md); merged into
``experiments/results/bench_render.json`` under the backend's name (``cpu``, ``gpu``).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from experiments.common import bench_cloud, best_of, entry, machine
from ne_jax.data import cameras
from ne_jax.data.rays import Camera
from ne_jax.render.driver import render_image
from ne_jax.render.renderer import PointScene, RenderConfig
from ne_jax.render.shading import init_color_model, num_params
from ne_jax.train.run import get_run_preset

RESULTS = Path(__file__).resolve().parent / "results" / "bench_render.json"
RES = 100


def time_render(cfg: RenderConfig, scene: PointScene, repeats: int) -> dict:
    params = init_color_model(cfg.shading, jax.random.key(1))
    cams = [Camera.from_fov(c, RES, RES, cameras.CAMERA_ANGLE_X) for c in cameras.orbit_cameras(4)]
    bg = jnp.ones(3)
    first = best_of(lambda: render_image(cfg, params, scene, cams[0], bg, cameras.NEAR, cameras.FAR), 1)
    for cam in cams[1:]:  # settle any capacity growth (compiles once per grown budget)
        jax.block_until_ready(render_image(cfg, params, scene, cam, bg, cameras.NEAR, cameras.FAR))
    best, best_cpu = np.inf, np.inf
    for i in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        out = jax.block_until_ready(render_image(cfg, params, scene, cams[i % 4], bg, cameras.NEAR, cameras.FAR))
        best = min(best, time.perf_counter() - t0)
        best_cpu = min(best_cpu, time.process_time() - c0)
    return {"ms_per_image": round(1000 * best, 1), "cpu_ms_per_image": round(1000 * best_cpu, 1),
            "rays_per_s": round(RES * RES / best), "first_call_s": round(first, 2),
            "segments_per_ray": round(float(jnp.mean(out.num_segments)), 2),
            "lost_segments": int(jnp.sum(out.lost.count)), "params": num_params(params)}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)

    backend = jax.default_backend()
    n_points = {"tiny": 20_000, "default": 100_000, "paper": 2**21}
    n_points = {"tiny": 5_000, "default": 20_000} if args.quick else n_points
    rows, clouds = [], {}
    for preset, n in n_points.items():
        run = get_run_preset(preset)
        cfg = run.render
        if n not in clouds:
            clouds[n] = bench_cloud(n, 32, spread=0.5)
        t0 = time.perf_counter()
        scene = PointScene.build(clouds[n], cfg, run.capacities)
        build = time.perf_counter() - t0
        r = time_render(cfg, scene, args.repeats)
        rows.append({"setting": f"preset {preset}", "points": n, "depth": scene.tree.depth,
                     "build_s": round(build, 2), **r})
        print(rows[-1], flush=True)
        if preset == "default":
            unpacked = scene.replace(capacities=scene.capacities.replace(segments_per_ray=None))
            variants = {  # (render config, scene)
                "specular off (diffuse only)": (cfg.with_effects(specular=False), scene),
                "IST on": (cfg.with_effects(ist=True), scene),
                "background sphere on": (cfg.with_effects(background_model="sphere"), scene),
                "predicted normals (no point normals)": (cfg.with_effects(point_normals=False), scene),
                "traditional colour head": (cfg.with_effects(specular=False, color_head="traditional"), scene),
                # Unpacked, every one of the M slots per ray is sampled and shaded: at the default
                # 4096-ray chunk that needs ~31 GB, so this row uses 512-ray chunks.
                "no segment packing (512-ray chunks)": (cfg.replace(chunk=512), unpacked),
            }
            for name, (vcfg, vscene) in variants.items():
                rows.append({"setting": f"default, {name}", "points": n, "depth": scene.tree.depth,
                             "build_s": None, **time_render(vcfg, vscene, args.repeats)})
                print(rows[-1], flush=True)

    device = str(jax.devices()[0])
    report = {"command": "python -m experiments.bench_render" + (" --quick" if args.quick else ""), "device": device,
              "jax": jax.__version__, "machine": machine(), "image": f"{RES}x{RES}", "rows": rows}
    results = {**(json.loads(args.out.read_text()) if args.out.exists() else {}), backend: report}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2) + "\n")

    print(f"\n{device}, jax {jax.__version__}, {RES}x{RES} images\n")
    base_cpu = next(r["cpu_ms_per_image"] for r in rows if r["setting"] == "preset default")
    print("| setting | points | ms / image | rays / s | CPU ms / image | vs default (CPU) | first call s "
          "| segments / ray |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r['setting']} | {r['points']:,} | {r['ms_per_image']:.0f} | {r['rays_per_s']:,} | "
              f"{r['cpu_ms_per_image']:.0f} | {r['cpu_ms_per_image'] / base_cpu:.2f}x | {r['first_call_s']:.1f} | "
              f"{r['segments_per_ray']:.2f} |")
    print(f"\nsaved to {args.out} under '{backend}'")


if __name__ == "__main__":
    entry(main)

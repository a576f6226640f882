#!/usr/bin/env python
"""The noise floor of the path-traced benchmark: the PSNR between two seeds of the same view.

For each scene of each path-traced preset (``tiny_pt``, ``default_pt``), one camera of the test orbit
is rendered by :class:`ne_jax.benchmark.pathtracer.PathTracer` at the preset's resolution, twice per
sample count (two seeds), and the two images are compared as the benchmark scores a model: display
values composited over white, PSNR over the whole image (``psnr``) and over the pixels the object
covers (``psnr_object``, stricter: the empty background is noise-free). Two independent renders differ
by twice the variance of one, so one render's PSNR against the converged image is about 3 dB higher
than the seed-to-seed figure (``psnr_vs_converged`` = ``psnr + 3.01``). Also: the time per image
(wall clock and process CPU time) and the projected time of the whole preset (images x the mean time
per image; on an idle machine: the CPU time spread over every core).

Outputs ``experiments/results/pathtraced_noise.{json,md}``. Run from the repository root::

    .venv/bin/python -m experiments.pathtraced_noise                       # tiny_pt and default_pt at 64, 256 spp
    .venv/bin/python -m experiments.pathtraced_noise --presets tiny_pt --spp 16 --scenes cup   # seconds
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

from ne_jax.benchmark import pathtracer as P
from ne_jax.benchmark import scenes as S
from ne_jax.benchmark.generate import PRESETS, get_preset
from ne_jax.data import cameras
from ne_jax.provenance import commit, modified

RESULTS = Path(__file__).resolve().parent / "results"


def over_white(rgba: np.ndarray) -> np.ndarray:
    """Straight-alpha RGBA ``[H, W, 4]`` -> RGB over white ``[H, W, 3]`` (how the benchmark scores)."""
    return rgba[..., :3] * rgba[..., 3:4] + (1.0 - rgba[..., 3:4])


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    err = (a - b) ** 2 if mask is None else ((a - b) ** 2)[mask]
    mse = float(np.mean(err))
    return float("inf") if mse == 0.0 else -10.0 * math.log10(mse)


def mean_db(values: list[float]) -> float:
    """The PSNR of the mean MSE (not the mean of the dB values)."""
    return -10.0 * math.log10(float(np.mean([10 ** (-v / 10) for v in values])))


def preset_images(preset) -> int:
    """Images a preset writes: every scene's original (train, val, test) and its edits (train, test)."""
    return sum(preset.train_views + preset.val_views + preset.test_views
               + len(S.get_scene(n, 0.25).edits) * (preset.train_views + preset.test_views) for n in S.SCENES)


def measure(preset, scene_name: str, spp: int, view: int, seeds=(1, 2)) -> dict:
    scene = S.get_scene(scene_name, preset.detail)
    res, angle = preset.resolution, cameras.CAMERA_ANGLE_X
    t0 = time.perf_counter()
    surfaces = P.scene_surfaces(scene_name, scene.materials)
    tracer = P.PathTracer(S.truth_mesh(scene.mesh, None), scene.materials, surfaces,
                          max_edge=P.pixel_footprint(res, angle), spp=spp)
    build = time.perf_counter() - t0
    c2w = cameras.orbit_cameras(preset.test_views)[view]
    images, seconds, cpu = [], [], []
    for seed in seeds:
        t0, c0 = time.perf_counter(), time.process_time()
        images.append(tracer.render(c2w, res, res, angle, seed=seed))
        seconds.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    again = tracer.render(c2w, res, res, angle, seed=seeds[0])
    a, b = (over_white(x) for x in images)
    mask = (images[0][..., 3] > 0) | (images[1][..., 3] > 0)
    return {"scene": scene_name, "spp": spp, "faces": tracer.faces, "build_seconds": round(build, 3),
            "seconds_per_image": [round(s, 3) for s in seconds], "cpu_seconds_per_image": [round(s, 3) for s in cpu],
            "psnr": round(psnr(a, b), 2),
            "psnr_vs_converged": round(psnr(a, b) + 10 * math.log10(2), 2),
            "psnr_object": round(psnr(a, b, mask), 2), "object_fraction": round(float(mask.mean()), 3),
            "same_seed_identical": bool(np.array_equal(images[0], again))}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    pt = sorted(n for n, p in PRESETS.items() if p.renderer == "pathtrace")
    parser.add_argument("--presets", nargs="+", default=pt, choices=pt)
    parser.add_argument("--spp", type=int, nargs="+", default=None,
                        help="sample counts to measure (default: 64 and each preset's own)")
    parser.add_argument("--scenes", nargs="+", default=list(S.SCENES), choices=list(S.SCENES))
    parser.add_argument("--view", type=int, default=1, help="index of the test-orbit camera (default: 1)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)

    mi = P.import_mitsuba()
    load_before = os.getloadavg()
    t_all = time.perf_counter()
    command = "python -m experiments.pathtraced_noise " + " ".join(sys.argv[1:] if argv is None else argv)
    report = {"commit": commit(), "modified": modified("ne_jax", "experiments/pathtraced_noise.py"),
              "command": command.strip(),
              "mitsuba": {"version": mi.__version__, "variant": P.VARIANT, "sampler": P.SAMPLER,
                          "max_depth": P.MAX_DEPTH},
              "config": {"view": args.view, "scenes": args.scenes, "seeds": [1, 2],
                         "psnr": "display values over white; psnr_object: pixels either render covers"},
              "presets": {}}
    for name in args.presets:
        preset = get_preset(name)
        spps = sorted(set(args.spp or [64, preset.spp]))
        rows = []
        for spp in spps:
            for scene_name in args.scenes:
                row = measure(preset, scene_name, spp, args.view)
                rows.append(row)
                print(f"{name} {scene_name:7s} {spp:4d} spp: {row['psnr']:5.1f} dB (object {row['psnr_object']:5.1f}), "
                      f"{min(row['seconds_per_image']):.2f} s/image", flush=True)
        images = preset_images(preset)
        summary = {}
        for spp in spps:
            sel = [r for r in rows if r["spp"] == spp]
            per_image = float(np.mean([min(r["seconds_per_image"]) for r in sel]))
            cpu = float(np.mean([min(r["cpu_seconds_per_image"]) for r in sel]))
            summary[str(spp)] = {
                "worst_scene_psnr": min(r["psnr"] for r in sel),
                "mean_psnr": round(mean_db([r["psnr"] for r in sel]), 2),
                "worst_scene_psnr_object": min(r["psnr_object"] for r in sel),
                "seconds_per_image": round(per_image, 3),
                "cpu_seconds_per_image": round(cpu, 3),
                "projected_preset_minutes": round(images * per_image / 60, 1) if len(sel) == len(S.SCENES) else None,
                # on this machine's cores with nothing else running: CPU time spread over every core
                "projected_idle_minutes": (round(images * cpu / os.cpu_count() / 60, 1)
                                           if len(sel) == len(S.SCENES) else None),
            }
        report["presets"][name] = {"preset": preset.record(), "images": images, "rows": rows, "summary": summary}
    report["wall_seconds"] = round(time.perf_counter() - t_all, 1)
    report["machine"] = {"cpus": os.cpu_count(), "platform": platform.platform(),
                         "python": platform.python_version(), "loadavg_before": load_before,
                         "loadavg_after": os.getloadavg()}

    lines = [f"# Path-traced benchmark: noise floor (commit {report['commit'][:12]})", "",
             f"Command: `{report['command'].strip()}`; Mitsuba {mi.__version__} `{P.VARIANT}`, sampler "
             f"`{P.SAMPLER}`, max depth {P.MAX_DEPTH}; test-orbit view {args.view}; seeds 1 and 2.", "",
             "Seed-to-seed PSNR (dB) of the same view, over white, whole image (object pixels in brackets). One "
             "render's PSNR against the converged image is ~3 dB higher (two independent noises differ by twice the "
             "variance of one).", ""]
    for name, block in report["presets"].items():
        p = block["preset"]
        lines += [f"## `{name}` ({p['resolution']} px, {block['images']} images)", "",
                  "| spp | " + " | ".join(args.scenes) + " | worst | s / image (CPU s) | whole preset, projected "
                  "(idle machine) |",
                  "|---:|" + "---:|" * len(args.scenes) + "---:|---:|---:|"]
        for spp, s in block["summary"].items():
            cells = [f"{r['psnr']:.1f} ({r['psnr_object']:.1f})" for r in block["rows"] if r["spp"] == int(spp)]
            minutes = ("-" if s["projected_preset_minutes"] is None else
                       f"{s['projected_preset_minutes']:.0f} min ({s['projected_idle_minutes']:.0f} min)")
            lines.append(f"| {spp} | " + " | ".join(cells) + f" | {s['worst_scene_psnr']:.1f} | "
                         f"{s['seconds_per_image']:.2f} ({s['cpu_seconds_per_image']:.2f}) | {minutes} |")
        lines.append("")
    lines.append(f"Machine: {os.cpu_count()} CPUs, load average {load_before[0]:.1f} before and "
                 f"{report['machine']['loadavg_after'][0]:.1f} after (above {os.cpu_count()}, other jobs shared "
                 f"the CPUs: times are upper bounds); whole run {report['wall_seconds']:.0f} s. Each time is the "
                 "faster of the two renders (CPU s: process CPU time, all threads); the projection multiplies it by "
                 "the preset's images, the idle projection spreads the CPU time over every core.")
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "pathtraced_noise.json").write_text(json.dumps(report, indent=1) + "\n")
    (args.out / "pathtraced_noise.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    import ne_jax

    ne_jax.setup(huge_pages=True)  # as `ne-jax` does: a host device per core, huge pages (restarts)
    sys.exit(main())

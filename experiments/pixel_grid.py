"""What one ray per pixel costs: the ground truth's own floor, and trained models rendered with a
grid of rays per pixel.

The benchmark's ground truth is area-averaged (the ray caster shoots a 2 x 2 or 3 x 3 grid per pixel,
the path tracer random positions), while a model rendered with ``RenderConfig.pixel_samples = 1``
shoots one ray through each pixel's centre. For each ``--run`` this study

1. on a ray-cast scene, renders the ground truth again with one ray per pixel centre (the same ray
   caster, mesh and materials) and scores it against the stored ground truth: the error a perfect
   model with sharp edges would make at one ray per pixel (``floor``);
2. renders the trained model's test views with ``n x n`` rays per pixel for each ``n`` of
   ``--samples`` (zero-shot where ``n`` differs from the model's own): PSNR, the silhouette's share
   of the squared error (:mod:`ne_jax.eval.regions`) and seconds per image.

    python -m experiments.pixel_grid --run NAME RUN_DIR SCENE_DIR [--run ...] [--samples 1 2 3]
        [--views 0 1 2] --out NAME

Writes ``experiments/results/pixel_grid_<NAME>.{json,md}``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from experiments.common import RESULTS, command, commit, write_results


def ground_truth_floor(scene_dir: Path, split, views: list[int], background) -> dict | None:
    """Step 1 of the module docstring; ``None`` for a scene the ray caster did not make (path-traced)
    or an edited one."""
    from ne_jax.benchmark import raycaster
    from ne_jax.benchmark import scenes as S
    from ne_jax.data.nerf_synthetic import composite
    from ne_jax.eval.metrics import psnr

    meta = json.loads((Path(scene_dir) / "scene.json").read_text())
    if meta.get("edit") is not None or not str(meta.get("renderer", "")).startswith("open3d"):
        return None
    scene = S.get_scene(meta["scene"], meta["preset"]["detail"])
    caster = raycaster.RayCaster(S.truth_mesh(scene.mesh, None), scene.materials)
    scores = []
    for v in views:
        one = caster.render(np.asarray(split.c2w[v]), split.width, split.height, split.camera_angle_x, ss=1)
        truth = composite(split.images[v:v + 1], background)[0]
        scores.append(float(psnr(composite(one[None], background)[0].astype(np.float32), truth.astype(np.float32))))
    return {"psnr": round(float(np.mean(scores)), 2), "ground_truth_rays_per_pixel": meta["preset"]["supersample"] ** 2}


def grid_row(model, split, views: list[int], n: int) -> dict:
    """Step 2 of the module docstring at ``n x n`` rays per pixel."""
    from ne_jax.data.nerf_synthetic import composite, parse_background
    from ne_jax.eval.metrics import psnr
    from ne_jax.eval.regions import label_regions, region_errors

    render = dataclasses.replace(model.run.render, pixel_samples=n)
    model = model.replace(run=dataclasses.replace(model.run, render=render))
    bg = np.asarray(parse_background(model.background), np.float32)
    scores, seconds, labels, preds, truths = [], [], [], [], []
    for v in views:
        truth = composite(split.images[v:v + 1], bg)[0].astype(np.float32)
        t0 = time.perf_counter()
        out = model.render_image(split.camera(v))
        pred = np.asarray(out.rgb, np.float32)
        seconds.append(time.perf_counter() - t0)
        labels.append(label_regions(truth, np.asarray(split.images[v][..., 3]), pred, bg,
                                    depth=np.asarray(out.depth, np.float32)))
        scores.append(float(psnr(pred, truth)))
        preds.append(pred)
        truths.append(truth)
    errors = region_errors(np.stack(labels), np.stack(preds), np.stack(truths))
    return {"pixel_samples": n, "psnr": round(float(np.mean(scores)), 2),
            "psnr_per_view": [round(p, 2) for p in scores],
            "silhouette_error_share": round(errors["silhouette"]["error"], 4),
            # the first view compiles the renderer
            "seconds_per_image": round(float(np.median(seconds[1:] if len(seconds) > 1 else seconds)), 2)}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", nargs=3, action="append", required=True, metavar=("NAME", "RUN_DIR", "SCENE_DIR"),
                        help="a label, a trained model's run directory and the scene folder of its test views")
    parser.add_argument("--samples", type=int, nargs="+", default=[1, 2, 3], help="rays per pixel side to render")
    parser.add_argument("--views", type=int, nargs="+", default=[0, 1, 2], help="test views to render")
    parser.add_argument("--out", required=True, help="results file stem: pixel_grid_<out>")
    args = parser.parse_args(argv)
    if min(args.samples) < 1:
        raise SystemExit(f"--samples: expected rays per pixel side >= 1, found {args.samples}")

    from ne_jax.config_json import config_key
    from ne_jax.data.nerf_synthetic import load_split, parse_background
    from ne_jax.train.model import load_trained

    t0 = time.perf_counter()
    runs = []
    for name, run_dir, scene_dir in args.run:
        model = load_trained(run_dir)
        split = load_split(scene_dir, "test")
        bad = [v for v in args.views if not 0 <= v < split.num_views]
        if bad:
            raise SystemExit(f"--views: expected test views 0..{split.num_views - 1} of {scene_dir}, found {bad}")
        floor = ground_truth_floor(scene_dir, split, args.views, parse_background(model.background))
        rows = [grid_row(model, split, args.views, n) for n in args.samples]
        runs.append({"name": name, "run": run_dir, "scene_dir": scene_dir, "config_key": config_key(model.run),
                     "trained_pixel_samples": model.run.render.pixel_samples, "floor": floor, "rows": rows})
        print(f"{name}: floor {floor}; " + "; ".join(f"n={r['pixel_samples']}: {r['psnr']:.2f} dB, "
                                                    f"{r['seconds_per_image']:.2f} s" for r in rows), flush=True)
    res = {"what": "one ray per pixel against a grid: the ground truth's floor and trained models zero-shot",
           "command": command("pixel_grid", argv), "commit": commit(), "views": args.views, "runs": runs,
           "seconds": round(time.perf_counter() - t0, 1)}
    md = (f"Test views {args.views}; commit {res['commit']}; `{res['command']}`. *Floor*: the ray-cast ground "
          "truth rendered again with one ray per pixel centre, against the stored ground truth. Rows: the model "
          "rendered with n x n rays per pixel (its own n in bold).\n\n"
          "| model | config key | floor PSNR (1 ray) | rays per pixel | PSNR | silhouette share of the squared error "
          "| s / image |\n|---|---|---:|---:|---:|---:|---:|\n")
    for run in runs:
        floor = "-" if run["floor"] is None else f"{run['floor']['psnr']:.2f}"
        for r in run["rows"]:
            n = f"{r['pixel_samples'] ** 2}"
            n = f"**{n}**" if r["pixel_samples"] == run["trained_pixel_samples"] else n
            md += (f"| {run['name']} | {run['config_key']} | {floor} | {n} | {r['psnr']:.2f} | "
                   f"{100 * r['silhouette_error_share']:.0f}% | {r['seconds_per_image']:.2f} |\n")
    write_results(RESULTS, f"pixel_grid_{args.out}", res, md)


if __name__ == "__main__":
    import ne_jax

    ne_jax.setup(huge_pages=True)  # as `ne-jax` does: a host device per core, huge pages (restarts)
    main()

"""Initial point clouds by visual-hull carving on the benchmark scenes: accuracy and time.

    python -m experiments.initial_cloud                 # generate the tiny benchmark in a temp dir
    python -m experiments.initial_cloud --root DIR      # use an existing benchmark preset directory

For each scene: carve the training views' masks (with and without snapping onto the hull, and
with 5 photo-consistency sweeps),
estimate normals with Open3D, and compare with the scene's ground-truth surface samples
(``points.ply``, used here only as the reference): Chamfer distance (mean/median, both directions),
normal agreement (mean |cos|, mean signed cos, fraction oriented), and every orientation rule of
:mod:`ne_jax.pointcloud.normals` on the carved cloud and on the ground-truth positions. Writes
``experiments/results/initial_cloud.json`` and prints a Markdown table.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

from ne_jax.benchmark.generate import generate_benchmark, get_preset
from ne_jax.benchmark.scenes import SCENES
from ne_jax.data.nerf_synthetic import load_split
from ne_jax.pointcloud.init import CarveConfig, Views, carve_visual_hull, ground_truth_cloud
from ne_jax.pointcloud.metrics import chamfer, normal_agreement
from ne_jax.pointcloud.normals import ORIENTATIONS, NormalConfig, estimate_normals

RESULTS = Path(__file__).resolve().parent / "results"
PHOTO_ITERS = 5
"""Photo-consistency sweeps of the ``carve_photo`` variant (the main ``carve`` has none)."""


def _round(d: dict, n: int = 4) -> dict:
    return {k: round(v, n) if isinstance(v, float) else v for k, v in d.items()}


def run_scene(scene_dir: Path, carve_cfg: CarveConfig, normal_cfg: NormalConfig) -> dict:
    split = load_split(scene_dir, "train")
    views = Views.from_split(split)
    gt = ground_truth_cloud(scene_dir)
    out = {"views": views.num_views, "image_size": [split.width, split.height], "gt_points": len(gt)}
    unsnapped = carve_visual_hull(dataclasses.replace(carve_cfg, snap_steps=0), views)
    out["carve_no_snap"] = {
        "seconds": round(unsnapped.info["seconds"], 2),
        "chamfer": _round(chamfer(unsnapped.xyz, gt.xyz).as_dict()),
    }
    photo = carve_visual_hull(dataclasses.replace(carve_cfg, photo_iters=PHOTO_ITERS), views)
    out["carve_photo"] = {
        "photo_iters": PHOTO_ITERS,
        "removed_per_sweep": photo.info["photo_removed_per_sweep"],
        "seconds": round(photo.info["seconds"], 2),
        "chamfer": _round(chamfer(photo.xyz, gt.xyz).as_dict()),
    }
    cloud = carve_visual_hull(carve_cfg, views)
    t0 = time.perf_counter()
    normals = estimate_normals(normal_cfg, cloud.xyz, views)
    normal_seconds = time.perf_counter() - t0
    out["carve"] = {
        "source": cloud.source,
        "points": len(cloud),
        "info": _round(cloud.info),
        "seconds": round(cloud.info["seconds"], 2),
        "chamfer": _round(chamfer(cloud.xyz, gt.xyz).as_dict()),
        "normals_seconds": round(normal_seconds, 2),
        "normals": _round(normal_agreement(cloud.xyz, normals, gt.xyz, gt.normals).as_dict()),
    }
    orientation = {}
    for name, xyz in (("carved", cloud.xyz), ("gt_positions", gt.xyz)):
        orientation[name] = {}
        for orient in ORIENTATIONS:
            t0 = time.perf_counter()
            n = estimate_normals(dataclasses.replace(normal_cfg, orient=orient), xyz, views)
            seconds = time.perf_counter() - t0
            agreement = normal_agreement(xyz, n, gt.xyz, gt.normals).as_dict()
            orientation[name][orient] = _round({**agreement, "seconds": seconds})
    out["orientation"] = orientation
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--root", default=None, help="existing benchmark preset directory (default: generate)")
    parser.add_argument("--preset", default="tiny")
    parser.add_argument("--resolution", type=int, default=128)
    parser.add_argument("--points", type=int, default=20_000)
    args = parser.parse_args(argv)

    carve_cfg = CarveConfig(resolution=args.resolution, bounds=((-1.1,) * 3, (1.1,) * 3), num_points=args.points)
    normal_cfg = NormalConfig()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(args.root) if args.root else Path(tmp) / args.preset
        generate_seconds = None
        if args.root is None:
            t0 = time.perf_counter()
            generate_benchmark(root, get_preset(args.preset))
            generate_seconds = round(time.perf_counter() - t0, 1)
        scenes = {name: run_scene(root / name, carve_cfg, normal_cfg) for name in SCENES}

    orient_means = {}
    for cloud in ("carved", "gt_positions"):
        orient_means[cloud] = {
            o: round(float(np.mean([s["orientation"][cloud][o]["oriented"] for s in scenes.values()])), 3)
            for o in ORIENTATIONS
        }
    report = {
        "what": "visual-hull carving of the training masks vs the benchmark's ground-truth surface samples",
        "preset": args.preset,
        "generate_seconds": generate_seconds,
        "carve_config": dataclasses.asdict(carve_cfg),
        "normal_config": dataclasses.asdict(normal_cfg),
        "scenes": scenes,
        "orientation_mean_oriented_fraction": orient_means,
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version()},
        "notes": "distances in world units (scenes in [-1, 1]^3); Chamfer 'mean' = (accuracy_mean + "
                 "completeness_mean) / 2; 'oriented' = fraction of normals with cos > 0 to the nearest "
                 "ground-truth normal; carve_photo: the same with 5 photo-consistency sweeps",
    }
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "initial_cloud.json").write_text(json.dumps(report, indent=2) + "\n")

    voxel = (carve_cfg.bounds[1][0] - carve_cfg.bounds[0][0]) / carve_cfg.resolution
    print(f"preset {args.preset}, {carve_cfg.resolution}^3 voxels of {voxel:.4f}, {args.points} points\n")
    print("| scene | carve s | normals s | Chamfer mean (no snap; photo) | acc. median | compl. median | "
          "normal abs cos | oriented |")
    print("|---|---|---|---|---|---|---|---|")
    for name, s in scenes.items():
        c = s["carve"]
        print(f"| {name} | {c['seconds']} | {c['normals_seconds']} | {c['chamfer']['mean']:.4f} "
              f"({s['carve_no_snap']['chamfer']['mean']:.4f}; {s['carve_photo']['chamfer']['mean']:.4f}) | "
              f"{c['chamfer']['accuracy_median']:.4f} | "
              f"{c['chamfer']['completeness_median']:.4f} | {c['normals']['abs_cos']:.3f} | "
              f"{c['normals']['oriented']:.3f} |")
    print("\norientation rules, mean fraction oriented over the scenes:")
    for cloud, row in orient_means.items():
        print(f"  {cloud}: " + ", ".join(f"{o} {v}" for o, v in row.items()))


if __name__ == "__main__":
    import ne_jax

    ne_jax.setup(huge_pages=True)  # as `ne-jax` does: a host device per core, huge pages (restarts)
    main()

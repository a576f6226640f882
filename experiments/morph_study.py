"""Scene morphing between two trained benchmark scenes, ours vs the PointNeRF-like variant, with the
smoothness figures of :func:`ne_jax.morph.render.smoothness` (the paper judged morphs by eye only).

    python -m experiments.morph_study --runs runs/deform --a glossy --b stool

Models are the deformation benchmark's (``<runs>/<scene>/models/<name>``: trained here if missing, with
the preset's run config, or reused). Both variants morph along the same kind of path (straight lines
along the K-D matching of their own clouds) from the same camera. Writes
``experiments/results/morph_<a>_<b>.{json,md,png}`` (the PNG: one strip of frames per variant, top ours)
and the frames and videos under ``<runs>/morph/<a>_<b>/<variant>``.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import numpy as np

from experiments.common import cached_run
from ne_jax.atomic import atomic_write_json, atomic_write_text
from ne_jax.benchmark.generate import generate_benchmark, get_preset
from ne_jax.benchmark.scenes import SCENES
from ne_jax.benchmark.variants import get_variant, variant_run
from ne_jax.data.nerf_synthetic import load_split
from ne_jax.data.png import write_image
from ne_jax.morph import MorphSettings, morph_models, strip
from ne_jax.train.model import TrainedModel, load_trained
from ne_jax.train.run import get_run_preset

RESULTS = Path(__file__).resolve().parent / "results"
VARIANTS = ("full", "pointnerf_like")


def model_for(runs: Path, root: Path, scene: str, run) -> TrainedModel:
    run_dir = runs / scene / "models" / run.name
    cached_run(run, root / scene, run_dir)
    return load_trained(run_dir)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", required=True, help="the deformation benchmark's runs folder (models reused)")
    parser.add_argument("--root", default=None,
                        help="benchmark folder (default: <runs>/benchmark, generated if missing)")
    parser.add_argument("--preset", default="tiny", choices=["tiny", "default"])
    parser.add_argument("--a", default="glossy", choices=list(SCENES))
    parser.add_argument("--b", default="stool", choices=list(SCENES))
    parser.add_argument("--steps", type=int, default=24)
    parser.add_argument("--view", type=int, default=0, help="test view of scene A to render from")
    args = parser.parse_args(argv)
    runs = Path(args.runs)
    root = Path(args.root) if args.root else runs / "benchmark"
    if not (root / args.a / "scene.json").is_file() or not (root / args.b / "scene.json").is_file():
        generate_benchmark(root, get_preset(args.preset), [args.a, args.b])
    camera = load_split(root / args.a, "test").camera(args.view)
    full = get_run_preset(args.preset)
    name = f"morph_{args.a}_{args.b}"
    results, strips = {}, []
    for v in VARIANTS:
        run = variant_run(full, get_variant(v))
        t0 = time.perf_counter()
        a, b = model_for(runs, root, args.a, run), model_for(runs, root, args.b, run)
        report, frames = morph_models(a, b, runs / "morph" / f"{args.a}_{args.b}" / v, camera,
                                      MorphSettings(steps=args.steps), labels=(args.a, args.b), progress=False)
        report.pop("per_frame")
        results[v] = {**report, "label": get_variant(v).label, "seconds_total": round(time.perf_counter() - t0, 1)}
        strips.append(strip(frames, count=8))
        sm = report["smoothness"]
        print(f"{v:>15}: frame-to-frame change mean {sm['mean']:.4f} max {sm['max']:.4f}, "
              f"path ratio {sm['path_ratio']:.2f} ({report['seconds']:.0f} s)", flush=True)

    command = (f"python -m experiments.morph_study --runs DIR --a {args.a} --b {args.b} --steps {args.steps} "
               f"--view {args.view}")
    RESULTS.mkdir(exist_ok=True)
    atomic_write_json(RESULTS / f"{name}.json", {
        "what": "morph of two trained benchmark scenes, ours vs PointNeRF-like: frame-to-frame image change",
        "preset": args.preset, "a": args.a, "b": args.b, "steps": args.steps, "view": args.view,
        "variants": results, "command": command,
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version()}})
    lines = [f"Morph `{args.a}` -> `{args.b}` ({args.steps} frames, preset `{args.preset}`, test view {args.view} of "
             f"`{args.a}`; straight-line path along the K-D matching). Re-run: `{command}`.", "",
             "| variant | mean frame change | max frame change | path ratio | end change | matched points | seconds |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for r in results.values():
        sm = r["smoothness"]
        lines.append(f"| {r['label']} | {sm['mean']:.4f} | {sm['max']:.4f} | {sm['path_ratio']:.2f} | "
                     f"{sm['end_change']:.4f} | {r['points']['matched']} | {r['seconds']:.0f} |")
    atomic_write_text(RESULTS / f"{name}.md", "\n".join(lines) + "\n")
    pad = 2
    grid = np.ones((len(strips) * (strips[0].shape[0] + pad) - pad, strips[0].shape[1], 3), np.float32)
    for i, s in enumerate(strips):
        grid[i * (s.shape[0] + pad):i * (s.shape[0] + pad) + s.shape[0]] = s
    write_image(RESULTS / f"{name}.png", grid)
    print("\n".join(lines))


if __name__ == "__main__":
    import ne_jax

    ne_jax.setup(huge_pages=True)  # as `ne-jax` does: a host device per core, huge pages (restarts)
    main()

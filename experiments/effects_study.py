"""What declaring a scene's effects buys: each benchmark scene trained with the effects its
``scene.json`` declares and with every effect on (``--effects all``), in one run: training time,
time per test image, parameters and test PSNR.

    python -m experiments.effects_study --root BENCH/tiny --preset tiny --runs RUNS --out effects_study_tiny

Writes ``experiments/results/<out>.{json,md}``. Runs are cached in ``--runs`` (a finished run is
read back, its recorded training time kept).
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import jax
import numpy as np

from ne_jax import provenance
from ne_jax.atomic import atomic_write_json, atomic_write_text
from ne_jax.config_json import config_key
from ne_jax.data.nerf_synthetic import load_split
from ne_jax.eval import evaluate_model
from ne_jax.train.effects import declare_effects
from ne_jax.train.loop import train
from ne_jax.train.run import get_run_preset

RESULTS = Path(__file__).resolve().parent / "results"
SCENES = ("glossy", "cup", "stool", "blocks")


def _commit() -> str:
    return provenance.commit(short=True)


def measure(preset: str, scene_dir: Path, spec: str, run_dir: Path) -> dict:
    base = get_run_preset(preset)
    render, record = declare_effects(base.render, spec, scene_dir)
    run = base.replace(render=render)
    model = train(run, scene_dir, run_dir, progress=False, log=lambda s: None, notes={"effects": record})
    split = load_split(scene_dir, "test")
    evaluate_model(model, split, progress=False, lpips_net=None)  # compiles
    t0 = time.perf_counter()
    report, _ = evaluate_model(model, split, progress=False, lpips_net=None)
    per_image = (time.perf_counter() - t0) / split.num_views
    params = sum(int(np.size(x)) for x in jax.tree_util.tree_leaves(model.state.params))
    return {"spec": spec, "effects": record["effects"], "source": record["source"], "config_key": config_key(run),
            "train_seconds": round(model.recorded_seconds, 1), "seconds_per_image": round(per_image, 3),
            "parameters": params, "psnr": round(report["psnr"], 2), "ssim": round(report["ssim"], 4)}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--root", type=Path, required=True, help="a generated benchmark preset folder")
    parser.add_argument("--preset", default="tiny", choices=["tiny", "default"])
    parser.add_argument("--scenes", nargs="+", default=list(SCENES))
    parser.add_argument("--runs", type=Path, required=True)
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    out = args.out or f"effects_study_{args.preset}"
    rows = []
    for scene in args.scenes:
        for spec in ("scene", "all"):
            rec = measure(args.preset, args.root / scene, spec, args.runs / scene / spec)
            rec["scene"] = scene
            rows.append(rec)
            print(f"{scene} {spec}: {rec}", flush=True)
    command = (f"python -m experiments.effects_study --root {args.root} --preset {args.preset} --scenes "
               f"{' '.join(args.scenes)} --runs RUNS --out {out}")
    report = {"what": "declared effects against every effect on, per scene", "commit": _commit(), "command": command,
              "machine": {"cpus": jax.device_count(), "platform": platform.platform()}, "rows": rows}
    atomic_write_json(RESULTS / f"{out}.json", report)
    lines = [f"Declared effects (`scene.json`) against every effect on (`all`), preset `{args.preset}`, commit "
             f"{report['commit']}: `{command}`.", "",
             "| scene | effects | specular | background | train s | s / image | parameters | test PSNR |",
             "|---|---|---|---|---:|---:|---:|---:|"]
    for r in rows:
        e = r["effects"]
        lines.append(f"| {r['scene']} | {r['spec']} | {e['specular']} | {e['background']} | {r['train_seconds']:.0f} | "
                     f"{r['seconds_per_image']:.2f} | {r['parameters']:,} | {r['psnr']:.2f} |")
    atomic_write_text(RESULTS / f"{out}.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()

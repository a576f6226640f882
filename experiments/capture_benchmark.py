"""The capture benchmark: train, evaluate and edit on the benchmark's capture variant, as a user
would on their own captures (no masks, a start from SfM points, a learned background).

    python -m experiments.make_benchmark --preset tiny_capture --out BENCH
    python -m experiments.capture_benchmark --preset tiny --root BENCH/tiny_capture --runs RUNS
    python -m experiments.capture_benchmark --preset tiny --root BENCH/tiny_capture --runs RUNS --layouts colmap

Every scene in each layout (``colmap``: the scene folder; ``nerfstudio``: its ``<scene>_ns`` copy), as
docs/benchmark.md describes. Writes ``experiments/results/capture_benchmark_<preset>.{json,md}``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from experiments import common
from experiments.common import RESULTS, commit, entry
from ne_jax.benchmark.edits import benchmark_edit
from ne_jax.benchmark.scenes import SCENES, get_scene
from ne_jax.config_json import config_key, config_set
from ne_jax.data.scene import load_split, scene_points
from ne_jax.edit.model import edit_model, finetune, model_edit_context
from ne_jax.eval import evaluate_model
from ne_jax.train.effects import declare_effects
from ne_jax.train.loop import train
from ne_jax.train.model import load_trained
from ne_jax.train.run import get_run_preset

LAYOUTS = {"colmap": "{scene}", "nerfstudio": "{scene}_ns"}


def _score(model, scene_dir: Path) -> dict:
    split = load_split(scene_dir, "test", model.run.downscale)
    t0 = time.perf_counter()
    report, _ = evaluate_model(model, split, progress=False)
    return {"psnr": round(report["psnr"], 2), "ssim": round(report["ssim"], 4),
            "views": list(split.file_paths), "eval_seconds": round(time.perf_counter() - t0, 1)}


def run_layout(preset: str, scene_dir: Path, run_dir: Path, resume: bool, sets=()) -> tuple[object, dict]:
    """Train the preset, with ``sets`` (``FIELD.PATH=VALUE`` changes), on a capture as ``ne-jax train``
    does, and score it."""
    run = config_set(get_run_preset(preset), *sets)
    split = load_split(scene_dir, "train", run.downscale)
    points = scene_points(scene_dir)
    render, effects = declare_effects(run.render, "auto", scene_dir, split, None if points is None else points[0])
    run = run.replace(render=render)
    model = train(run, scene_dir, run_dir, resume=resume, progress=False, notes={"effects": effects},
                  log=lambda s: print("  " + s, flush=True))
    out = {"config_key": config_key(model.run), "effects": effects["effects"], **_score(model, scene_dir),
           "train_seconds": round(model.recorded_seconds, 1), "steps": int(model.state.step),
           "initial_points": model.initial.get("points"), "initial_source": model.initial.get("source"),
           "final_points": int(np.asarray(model.scene.points.alive).sum())}
    return model, out


def run_edits(model, scene_dir: Path, runs: Path, finetune_edits: list[str]) -> dict:
    meta = json.loads((scene_dir / "scene.json").read_text())
    out = {}
    context = model_edit_context(model)  # shared by every edit of the model
    for name in get_scene(meta["scene"]).edits:
        edit, truth = benchmark_edit(scene_dir, name)
        if truth is None:
            continue
        edited, _ = edit_model(model, edit, runs / f"edit_{name}", scene_dir=truth, context=context)
        row = {"zero_shot": _score(edited, truth)}
        if name in finetune_edits:
            tuned = finetune(load_trained(runs / f"edit_{name}"), runs / f"finetune_{name}", 1, progress=False,
                             log=lambda s: None)
            row["finetuned"] = {**_score(tuned, truth), "steps": int(tuned.run.total_steps)}
        out[name] = row
        print(f"  edit {name}: " + json.dumps(row), flush=True)
    return out


def write_results(preset: str, root: Path, scenes: dict, results: Path, sets=()) -> str:
    report = {"what": "capture variant of the benchmark: opaque images, SfM start, learned background; full-image "
                      "PSNR/SSIM on the held-out images (every 8th), per layout; benchmark edits zero-shot and "
                      "fine-tuned one epoch on the COLMAP copy",
              "preset": preset, "root": str(root), "commit": commit(), "set": list(sets), "scenes": scenes,
              "command": f"python -m experiments.capture_benchmark --preset {preset} --root {root.name} --runs RUNS"
                         + "".join(f" --set {s}" for s in sets)}
    lines = [f"Preset `{preset}` on `{root.name}`, commit {report['commit']}; `{report['command']}`.", "",
             "| scene | COLMAP PSNR (dB) | SSIM | nerfstudio PSNR (dB) | same split | train time (s) | "
             "points SfM start -> final |", "|---|---:|---:|---:|---|---:|---|"]
    psnrs = []
    for name, s in scenes.items():
        c, n = s.get("colmap"), s.get("nerfstudio")
        if c is None:
            continue
        psnrs.append(c["psnr"])
        ns = f"{n['psnr']:.2f}" if n else "-"
        same = ("yes" if [Path(v).name for v in n["views"]] == [Path(v).name for v in c["views"]] else "no") \
            if n else "-"
        lines.append(f"| {name} | {c['psnr']:.2f} | {c['ssim']:.3f} | {ns} | {same} | {c['train_seconds']:.0f} | "
                     f"{c['initial_points']} -> {c['final_points']} |")
    if psnrs:
        lines.append(f"| mean | **{np.mean(psnrs):.2f}** | | | | | |")
    edit_rows = [(scene, e, r) for scene, s in scenes.items() for e, r in s.get("edits", {}).items()]
    if edit_rows:
        lines += ["", "| scene | edit | zero-shot PSNR (dB) | fine-tuned PSNR (dB) |", "|---|---|---:|---:|"]
        for scene, e, r in edit_rows:
            ft = f"{r['finetuned']['psnr']:.2f}" if "finetuned" in r else "-"
            lines.append(f"| {scene} | {e} | {r['zero_shot']['psnr']:.2f} | {ft} |")
    text = "\n".join(lines) + "\n"
    common.write_results(results, f"capture_benchmark_{preset}", report, text, echo=False)
    return text


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default="tiny", choices=["tiny", "default"])
    parser.add_argument("--root", type=Path, required=True, help="a capture benchmark folder (make-benchmark "
                        "--preset tiny_capture|default_capture)")
    parser.add_argument("--runs", type=Path, required=True, help="folder of the run directories (resumed)")
    parser.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    parser.add_argument("--layouts", nargs="+", default=list(LAYOUTS), choices=list(LAYOUTS))
    parser.add_argument("--no-edits", action="store_true", help="skip the edits")
    parser.add_argument("--finetune", nargs="*", default=["bend", "twist"], metavar="EDIT",
                        help="edits also fine-tuned one epoch (default: bend twist)")
    parser.add_argument("--set", action="append", default=[], metavar="FIELD.PATH=VALUE",
                        help="change one field of the preset's RunConfig (repeatable); a changed config writes "
                             "a new table: pass another --results folder")
    parser.add_argument("--results", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    try:
        config_set(get_run_preset(args.preset), *args.set)
    except ValueError as e:
        parser.error(f"--set: {e}")
    old = args.results / f"capture_benchmark_{args.preset}.json"
    scenes = json.loads(old.read_text())["scenes"] if old.is_file() else {}
    for name in args.scenes:
        row = scenes.setdefault(name, {})
        for layout in args.layouts:
            scene_dir = args.root / LAYOUTS[layout].format(scene=name)
            print(f"== {name} ({layout}: {scene_dir})", flush=True)
            run_dir = args.runs / f"{name}_{layout}"
            model, row[layout] = run_layout(args.preset, scene_dir, run_dir, resume=run_dir.is_dir(), sets=args.set)
            print("  " + json.dumps(row[layout]), flush=True)
            if layout == "colmap" and not args.no_edits:
                row["edits"] = run_edits(model, scene_dir, args.runs / name, args.finetune)
            text = write_results(args.preset, args.root, scenes, args.results, args.set)
    print(text)


if __name__ == "__main__":
    entry(main)

"""Training on the benchmark scenes: test PSNR/SSIM, wall time and point-cloud accuracy.

    python -m experiments.train_benchmark --preset tiny                  # tiny scenes, RunConfig.tiny
    python -m experiments.train_benchmark --preset default --scenes glossy --epochs 4
    python -m experiments.train_benchmark --root DIR ...                 # an existing benchmark folder
    python -m experiments.train_benchmark --preset default --root DIR --runs RUNS --resume  # continue stopped runs
    python -m experiments.train_benchmark --preset tiny --root BENCH/tiny_pt --runs RUNS  # the path-traced variant

For every scene: generate it (unless ``--root``), train with the preset's :class:`RunConfig`, score the
test views and the Chamfer distance of the initial and the optimised cloud to the scene's ground-truth
surface samples (:func:`run_scene`; docs/studies/training.md). Writes ``train_benchmark_<preset>.{json,md}``
to ``experiments/results`` (``<preset>_pt`` on a path-traced ``--root``, whose ``scene.json`` names the
renderer); the run directories go to ``--runs``.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

from experiments import common
from experiments.common import RESULTS, benchmark_suffix, entry
from ne_jax.benchmark.generate import generate_benchmark, get_preset, seen_surface_samples
from ne_jax.benchmark.scenes import SCENE_SETS, SCENES, scene_names
from ne_jax.config_json import config_key, config_set
from ne_jax.data.nerf_synthetic import load_split
from ne_jax.eval import evaluate_model, save_images
from ne_jax.eval.regions import split_regions, view_shares
from ne_jax.pointcloud.init import Views, ground_truth_cloud
from ne_jax.pointcloud.metrics import chamfer
from ne_jax.provenance import commit
from ne_jax.train.loop import initial_cloud, train
from ne_jax.train.run import get_run_preset


def run_scene(scene_dir: Path, run, run_dir: Path, progress: bool, resume: bool = False) -> dict:
    """Train ``run`` on the scene (from a visual-hull carving) and score it: test PSNR/SSIM on full images,
    the Chamfer distances of the initial and the final cloud to the surface (all of it, and the seen part)."""
    gt = ground_truth_cloud(scene_dir)
    views = Views.from_split(load_split(scene_dir, "train"))
    init = initial_cloud(run.init, scene_dir, views)
    result = train(run, scene_dir, run_dir, resume=resume, progress=progress)
    train_seconds = result.recorded_seconds  # summed over the sessions of a resumed run
    split = load_split(scene_dir, "test")
    t0 = time.perf_counter()
    report, images = evaluate_model(result, split, progress=progress)
    eval_seconds = time.perf_counter() - t0
    holes = view_shares(split_regions(split, images, result.background)[1], "hole")
    save_images(images, run_dir / "eval_test" / "images", [f"{i:03d}.png" for i in range(len(images))])
    final = np.asarray(result.scene.points.xyz)[np.asarray(result.scene.points.alive)]
    seen = seen_surface_samples(scene_dir)  # the samples some training camera sees
    before, after = chamfer(init.xyz, gt.xyz), chamfer(final, gt.xyz)
    before_seen, after_seen = chamfer(init.xyz, gt.xyz[seen]), chamfer(final, gt.xyz[seen])
    # accuracy against every sample (a point on a hidden surface is still on the surface),
    # completeness against the seen ones (a hidden surface cannot be recovered from the images)
    seen_initial = 0.5 * (before.accuracy_mean + before_seen.completeness_mean)
    seen_final = 0.5 * (after.accuracy_mean + after_seen.completeness_mean)
    rounds = [e["points"] for e in result.history if "points" in e]
    cpu_seconds = result.recorded_cpu_seconds
    return {"test_psnr": round(report["psnr"], 2), "test_ssim": round(report["ssim"], 4),
            "per_view_psnr": [round(v["psnr"], 2) for v in report["views"]],
            "hole_pixels_worst_view": round(float(holes.max()), 6),
            "train_seconds": round(train_seconds, 1), "eval_seconds": round(eval_seconds, 1),
            "train_cpu_seconds": None if cpu_seconds is None else round(cpu_seconds, 1),
            "steps": int(result.state.step), "skipped_steps": int(result.state.skipped),
            "initial_points": len(init), "final_points": len(final),
            "chamfer_initial": round(before.mean, 5), "chamfer_final": round(after.mean, 5),
            "chamfer_ratio": round(before.mean / after.mean, 3),
            "accuracy_initial": round(before.accuracy_mean, 5), "accuracy_final": round(after.accuracy_mean, 5),
            "seen_share": round(float(seen.mean()), 4),
            "completeness_seen_initial": round(before_seen.completeness_mean, 5),
            "completeness_seen_final": round(after_seen.completeness_mean, 5),
            "chamfer_seen_initial": round(seen_initial, 5), "chamfer_seen_final": round(seen_final, 5),
            "chamfer_seen_ratio": round(seen_initial / seen_final, 3),
            "grown": sum(r.get("grown", {}).get("added", 0) for r in rounds),
            "pruned": sum(r.get("pruned", 0) for r in rounds), "denoised": sum(r.get("denoised", 0) for r in rounds),
            "lost_segments": report.get("lost_segments"),
            "train_psnr_by_epoch": [round(e["psnr"], 2) for e in result.history]}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default="tiny", choices=["tiny", "default"],
                        help="benchmark preset and training preset (same name)")
    parser.add_argument("--root", default=None, help="existing benchmark preset folder (default: generate)")
    parser.add_argument("--scenes", nargs="+", default=list(SCENES),
                        help="scenes or a set of them (heldout: the scenes no setting is chosen on; the results "
                             "are then train_benchmark_<preset>[_pt]_heldout)")
    parser.add_argument("--epochs", type=int, default=None, help="override the preset's epochs")
    parser.add_argument("--steps-per-epoch", type=int, default=None)
    parser.add_argument("--set", action="append", default=[], metavar="FIELD.PATH=VALUE",
                        help="change one field of the preset's RunConfig (repeatable), e.g. "
                             "render.kdtree.density_falloff=1.0; a changed config writes a new table: pass "
                             "another --results folder")
    parser.add_argument("--runs", default=None, help="folder for the run directories (default: a temp folder)")
    parser.add_argument("--progress", action="store_true")
    parser.add_argument("--results", type=Path, default=RESULTS, help="folder of the JSON and Markdown results")
    parser.add_argument("--resume", action="store_true",
                        help="continue the runs in --runs from their last checkpoints (a long preset over "
                             "several sittings; the training time is the sum the loop recorded per epoch)")
    args = parser.parse_args(argv)
    try:
        args.scenes = scene_names(args.scenes)
    except KeyError as e:
        parser.error(f"--scenes: {e.args[0]}")
    held_out = set(args.scenes) <= set(SCENE_SETS["heldout"])
    if not held_out and set(args.scenes) & set(SCENE_SETS["heldout"]):
        parser.error(f"--scenes: expected tuning scenes or held-out ones, found both ({' '.join(args.scenes)}): "
                     "their results go to separate tables")
    if args.resume and args.runs is None:
        parser.error("--resume continues the runs in --runs: pass --runs DIR")
    if args.runs is not None and not args.resume:
        held = [n for n in args.scenes if (Path(args.runs) / n / "checkpoints").is_dir()]
        if held:
            parser.error(f"--runs {args.runs} already holds runs of {held}: pass --resume to continue them, "
                         "or another --runs folder to start afresh")

    run = get_run_preset(args.preset)
    if args.epochs is not None or args.steps_per_epoch is not None:
        run = run.with_schedule(args.epochs, args.steps_per_epoch)
    try:
        run = config_set(run, *args.set)
    except ValueError as e:
        parser.error(f"--set: {e}")
    started_at = commit(short=True)  # the code this process imported
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(args.root) if args.root else Path(tmp) / "bench"
        runs = Path(args.runs) if args.runs else Path(tmp) / "runs"
        if args.root is None:
            generate_benchmark(root, get_preset(args.preset), args.scenes)
        benchmark = args.preset + benchmark_suffix(root, args.scenes)  # the results of a path-traced root: <preset>_pt
        if held_out:
            benchmark += "_heldout"
        scenes = {}
        for name in args.scenes:
            print(f"== {name}", flush=True)
            scenes[name] = {**run_scene(root / name, run, runs / name, args.progress, args.resume),
                            "commit": started_at}
            print(json.dumps(scenes[name]), flush=True)
            # after every scene: a long run keeps what it has
            text = write_results(args.preset, run, scenes, args.results, name=benchmark, sets=args.set)
    print(text)


def _earlier_scenes(name: str, run, results: Path) -> dict:
    """Scenes of an earlier invocation of the same config on the same benchmark ``name`` (kept unless
    re-measured; a changed preset starts a new table)."""
    path = results / f"train_benchmark_{name}.json"
    if not path.is_file():
        return {}
    old = json.loads(path.read_text())
    return old.get("scenes", {}) if old.get("config_key") == config_key(run) else {}


def write_results(preset: str, run, scenes: dict, results: Path = RESULTS, name: str | None = None,
                  sets: list[str] = ()) -> str:
    """``train_benchmark_<name>.{json,md}`` in ``results``: ``name`` is the training ``preset`` on its
    own (ray-cast) benchmark, ``<preset>_pt`` on the path-traced one; ``sets``: the ``--set`` changes to
    the preset (recorded, and in the re-run command)."""
    name = name or preset
    scenes = {**_earlier_scenes(name, run, results), **scenes}  # scenes run one at a time accumulate
    report = {
        "what": "train each benchmark scene from a visual-hull carving; test PSNR/SSIM on full images; "
                "Chamfer distance (world units, mean of both directions) of the initial and the final cloud "
                "to the ground-truth surface samples; the seen-surface Chamfer takes the completeness over "
                "only the samples a training camera sees (seen_share of them; ne_jax.benchmark.generate."
                "seen_surface_samples) and the accuracy over all; train_seconds as the loop recorded it "
                "(initial cloud, epochs with their compiles, point-cloud rounds; summed over the sittings of a "
                "resumed run), train_cpu_seconds the process's CPU time over the same parts (null for a run "
                "directory recorded without it); hole_pixels_worst_view: the largest share of a test view's pixels "
                "labelled hole (object in the ground truth rendered as background; ne_jax.eval.regions)",
        "preset": preset, "benchmark": name,
        "commit": ", ".join(sorted({s.get("commit", "unknown") for s in scenes.values()})),
        "config_key": config_key(run), "epochs": run.epochs, "steps_per_epoch": run.steps_per_epoch,
        "batch_size": run.sampler.batch_size, "background": run.background, "set": list(sets), "scenes": scenes,
        "machine": common.machine(python=True, jax_devices=jax.device_count(),
                                  load_average_1_5_15_min=[round(x, 2) for x in os.getloadavg()])}
    changes = "".join(f" --set {s}" for s in sets)
    rerun = f"`python -m experiments.train_benchmark --preset {preset}{changes}`"
    if name.endswith("_heldout"):  # the held-out scenes of a benchmark variant
        variant = name.removesuffix("_heldout")
        rerun = (f"on the `{name}` benchmark, `python -m experiments.train_benchmark --preset {preset} --root "
                 f"BENCH/{variant} --scenes heldout --runs RUNS{changes}` (BENCH from `ne-jax make-benchmark --preset "
                 f"{variant} --scenes heldout --out BENCH/{variant}`)")
    elif name != preset:  # a benchmark variant: its folder is an input
        rerun = (f"on the `{name}` benchmark, `python -m experiments.train_benchmark --preset {preset} --root "
                 f"BENCH/{name} --runs RUNS{changes}` (BENCH from `python -m experiments.make_benchmark --preset "
                 f"{name} --out BENCH`)")
    lines = [f"Preset `{preset}`: {run.epochs} epochs x {run.steps_per_epoch} steps of {run.sampler.batch_size} "
             f"rays; commit {report['commit']}, config key {report['config_key']}; {rerun}.", "",
             "| scene | test PSNR (dB) | test SSIM | train time (s) | points initial -> final | "
             "Chamfer initial -> final | ratio | seen-surface Chamfer initial -> final | ratio | holes, worst view |",
             "|---|---:|---:|---:|---|---|---:|---|---:|---:|"]
    for scene, s in scenes.items():
        seen = (f"{s['chamfer_seen_initial']:.4f} -> {s['chamfer_seen_final']:.4f} "
                f"({100 * s['seen_share']:.0f}% seen) | {s['chamfer_seen_ratio']:.2f}"
                if "chamfer_seen_ratio" in s else "not measured | -")
        holes = f"{100 * s['hole_pixels_worst_view']:.2f}%" if "hole_pixels_worst_view" in s else "-"
        lines.append(f"| {scene} | {s['test_psnr']:.2f} | {s['test_ssim']:.3f} | {s['train_seconds']:.0f} | "
                     f"{s['initial_points']} -> {s['final_points']} | {s['chamfer_initial']:.4f} -> "
                     f"{s['chamfer_final']:.4f} | {s['chamfer_ratio']:.2f} | {seen} | {holes} |")
    text = "\n".join(lines) + "\n"
    common.write_results(results, f"train_benchmark_{name}", report, text, echo=False)
    return text


if __name__ == "__main__":
    entry(main)

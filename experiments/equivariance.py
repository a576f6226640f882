"""Equivariance of edits: a trained model moved rigidly must render as the original seen from moved
cameras (:mod:`ne_jax.edit.fidelity`; docs/editing.md): per model each of :func:`motions` with the tree
carried and rebuilt, and with ``--diagnose`` one rotation a stage at a time (:func:`diagnose`).

    python -m experiments.equivariance --runs RUN [RUN ...] [--views 4] [--diagnose] [--out NAME]
    python -m experiments.equivariance --summarize experiments/results/equivariance_*tiny*.json --out NAME

Writes ``experiments/results/<NAME>.{json,md}`` (default ``equivariance``); ``--summarize`` writes
``<NAME>.md`` alone: every model of several results files per motion, and the worst rigid motion.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from experiments.common import RESULTS, entry, write_results
from ne_jax.atomic import atomic_write_text
from ne_jax.data.nerf_synthetic import load_split
from ne_jax.edit.apply import EditConfig, apply_edit, edit_context, edited_render_config
from ne_jax.edit.deformations import Edit, rigid_scene
from ne_jax.edit.fidelity import equivariance, exact_rigid_points
from ne_jax.edit.ist import ISTConfig
from ne_jax.provenance import commit
from ne_jax.render.renderer import PointScene
from ne_jax.train.model import load_trained

AXES = {"tilted_a": (1.0, 1.0, 2.0), "tilted_b": (2.0, -1.0, 0.5), "z": (0.0, 0.0, 1.0)}
ANGLES = (2.0, 10.0, 40.0, 90.0, 180.0)
DIAGNOSE = ("tilted_a", 40.0)


def motions(pivot) -> list[tuple[str, Edit, str]]:
    """``(label, edit, kind)`` with kind ``rigid`` or ``scale``."""
    out = [(f"rotate {a:g} deg about {name}", rigid_scene(f"rot_{name}_{a:g}", axis, a, pivot), "rigid")
           for name, axis in AXES.items() for a in ANGLES]
    out.append(("translate by (0.013, -0.021, 0.008)",
                rigid_scene("translate", (0, 0, 1), 0.0, pivot, (0.013, -0.021, 0.008)), "rigid"))
    s = 1.1
    t = np.asarray(pivot, np.float64) * (1 - s)
    m = np.eye(4)
    m[:3, :3] *= s
    m[:3, 3] = t
    scale = Edit("scale_1.1", "scale", lambda p: s * p + t.astype(np.float32),
                 rigid=tuple(tuple(float(x) for x in row) for row in m))
    out.append(("scale by 1.1 about the centre", scale, "scale"))
    return out


def _model_setup(run_dir: Path, views: int):
    model = load_trained(run_dir)
    cameras = load_split(model.scene_dir, "test").cameras()[:views]
    pts = model.state.point_state(model.scene.points)
    xyz = np.asarray(pts.xyz)[np.asarray(pts.alive)]
    pivot = tuple(float(v) for v in 0.5 * (xyz.min(axis=0) + xyz.max(axis=0)))
    return model, cameras, pts, pivot


def measure_motions(model, cameras, pts, pivot, log) -> tuple[list[dict], np.ndarray]:
    run = model.run
    near, far = run.sampler.near, run.sampler.far
    ref = None
    rows = []
    context = edit_context(EditConfig(), pts, model.scene, run.render)  # shared by every motion of the model
    for label, edit, kind in motions(pivot):
        row = {"motion": label, "kind": kind}
        for tree in ("carry", "rebuild"):
            cfg = EditConfig(rebuild_tree=tree == "rebuild")
            t0 = time.perf_counter()
            points = apply_edit(pts, edit, cfg, context)
            render = edited_render_config(run.render, ist=True)
            scene = cfg.scene(model.scene, points, render, context)
            res = equivariance(run.render, model.state.params, model.scene, render, scene, edit.matrix, cameras,
                               run.background, near, far, reference=ref)
            ref = res["reference"]
            row[tree] = round(res["psnr"], 2)
            row[f"{tree}_seconds"] = round(time.perf_counter() - t0, 1)
        rows.append(row)
        log(f"  {label:>40}: carried {row['carry']:7.2f} dB, rebuilt {row['rebuild']:7.2f} dB")
    return rows, ref


def diagnose(model, cameras, pts, pivot, ref, log) -> list[dict]:
    """One rotation (:data:`DIAGNOSE`) with one stage of the edit path held exact, or switched, at a time
    (each row's label says which): the tree, the KNN, normals and ISTs, the IST's filling, the IST effect."""
    run = model.run
    near, far = run.sampler.near, run.sampler.far
    name, angle = DIAGNOSE
    edit = rigid_scene("diagnose", AXES[name], angle, pivot)
    render = edited_render_config(run.render, ist=True)
    base = model.scene
    context = edit_context(EditConfig(), pts, base, run.render)  # shared by every stage
    fitted = apply_edit(pts, edit, context=context)  # normals re-estimated, ISTs fitted (the default edit path)
    exact = exact_rigid_points(pts, edit.matrix)
    no_fill = apply_edit(pts, edit, EditConfig(ist=ISTConfig(fill_passes=0, smooth_iters=0)), context)
    carried = {"context": context.carry}  # the carries' keyword arguments (PointScene.edited)
    rebuilt = PointScene.build(fitted, render, base.capacities)
    stages = [
        ("tree rebuilt (paper)", "rebuild", render, rebuilt),
        ("tree rebuilt, spacing kept", "rebuild", render,
         rebuilt.replace(tree=rebuilt.tree.replace(spacing=base.tree.spacing))),
        ("tree rebuilt, normals and ISTs exact", "rebuild", render, PointScene.build(exact, render, base.capacities)),
        ("partition kept; world boxes re-fitted, candidate sets re-chosen", "carry", render,
         base.edited(fitted, render, oriented=False, recompute_candidates=True, **carried)),
        ("partition and candidate sets kept; world boxes re-fitted", "carry", render,
         base.edited(fitted, render, oriented=False, **carried)),
        ("tree carried: boxes in their frames (default)", "carry", render, base.edited(fitted, render, **carried)),
        ("tree carried, normals and ISTs exact", "carry", render, base.edited(exact, render, **carried)),
        ("tree carried, IST without filling and smoothing", "carry", render,
         base.edited(no_fill, render, **carried)),
        ("tree carried, IST effect off", "carry", edited_render_config(run.render, ist=False),
         base.edited(fitted, render, **carried)),
    ]
    rows = []
    for label, tree, cfg, scene in stages:
        res = equivariance(run.render, model.state.params, base, cfg, scene, edit.matrix, cameras, run.background,
                           near, far, reference=ref)
        rows.append({"stage": label, "tree": tree, "psnr": round(res["psnr"], 2)})
        log(f"  {label:>66}: {res['psnr']:7.2f} dB")
    # exact KNN on both sides: what the candidate sets' approximation costs under a rebuild
    ex = dataclasses.replace(run.render, exact_knn=True)
    ex_edit = dataclasses.replace(render, exact_knn=True)
    res = equivariance(ex, model.state.params, base, ex_edit, rebuilt, edit.matrix, cameras, run.background, near, far)
    rows.append({"stage": "tree rebuilt, exact KNN on both sides", "tree": "rebuild", "psnr": round(res["psnr"], 2)})
    log(f"  {'tree rebuilt, exact KNN on both sides':>66}: {res['psnr']:7.2f} dB")
    return rows


def write(out: str, results: list[dict], command: str) -> None:
    lines = [f"Equivariance of edits: PSNR (dB) between the edited model seen from moved test cameras and the "
             f"unedited model ({commit(short=True)}; re-run: `{command}`). 120 = identical renders.", ""]
    for res in results:
        lines += [f"**{res['run']}** (preset `{res['preset']}`, {res['views']} test views, {res['points']} points)", "",
                  "| motion | tree carried | tree rebuilt (paper) |", "|---|---:|---:|"]
        lines += [f"| {r['motion']} | {r['carry']:.2f} | {r['rebuild']:.2f} |" for r in res["motions"]]
        lines += [f"| worst rigid motion | {_worst(res['motions'], 'carry'):.2f} | "
                  f"{_worst(res['motions'], 'rebuild'):.2f} |", ""]
        if res.get("diagnosis"):
            name, angle = DIAGNOSE
            lines += [f"Diagnosis: rotation by {angle:g} deg about {name} {AXES[name]}, one stage at a time.", "",
                      "| stage | PSNR |", "|---|---:|"]
            lines += [f"| {r['stage']} | {r['psnr']:.2f} |" for r in res["diagnosis"]]
            lines.append("")
    write_results(RESULTS, out, {"commit": commit(short=True), "command": command, "models": results}, "\n".join(lines))


def _worst(motions: list[dict], tree: str) -> float:
    return min(r[tree] for r in motions if r["kind"] == "rigid")


def summary(sources: list[Path]) -> str:
    """One table of every model in the results files ``sources`` (``--summarize``)."""
    models, notes = [], []
    for path in sources:
        data = json.loads(path.read_text(encoding="utf-8"))
        models += data["models"]
        notes.append(f"- `{path.name}`: commit {data['commit']}, `{data['command']}`")
    lines = ["PSNR (dB) between the edited model seen from moved test cameras and the unedited model "
             "(120 = identical renders); each cell: tree carried / tree rebuilt (paper).", "",
             "| motion | " + " | ".join(f"{Path(m['scene_dir']).name} ({m['preset']})" for m in models) + " |",
             "|---|" + "---:|" * len(models)]
    for i, row in enumerate(models[0]["motions"]):
        cells = [f"{m['motions'][i]['carry']:.1f} / {m['motions'][i]['rebuild']:.1f}" for m in models]
        lines.append(f"| {row['motion']} | " + " | ".join(cells) + " |")
    worst = [f"{_worst(m['motions'], 'carry'):.1f} / {_worst(m['motions'], 'rebuild'):.1f}" for m in models]
    lines += ["| **worst rigid motion** | " + " | ".join(worst) + " |", "",
              "Models: " + "; ".join(f"{Path(m['scene_dir']).name}: {m['points']} points, {m['views']} test views"
                                     for m in models) + ".", "", "Sources:", *notes, ""]
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", nargs="+", help="trained run directories (required unless --summarize)")
    parser.add_argument("--views", type=int, default=8, help="test views per model (the first ones)")
    parser.add_argument("--diagnose", action="store_true", help="also the stage-by-stage diagnosis")
    parser.add_argument("--out", default="equivariance", help="results file stem")
    parser.add_argument("--summarize", nargs="+", type=Path, metavar="RESULTS.json",
                        help="write one table of these results files' models to <out>.md, and stop")
    args = parser.parse_args(argv)
    if args.summarize:
        text = summary(args.summarize)
        atomic_write_text(RESULTS / f"{args.out}.md", text)
        print(text)
        return
    if not args.runs:
        parser.error("the following arguments are required: --runs")
    command = ("python -m experiments.equivariance --runs " + " ".join(Path(r).name for r in args.runs)
               + f" --views {args.views}" + (" --diagnose" if args.diagnose else "") + f" --out {args.out}")
    results = []
    for run_dir in args.runs:
        t0 = time.perf_counter()
        model, cameras, pts, pivot = _model_setup(Path(run_dir), args.views)
        print(f"== {run_dir} ({model.run.name})", flush=True)
        rows, ref = measure_motions(model, cameras, pts, pivot, lambda s: print(s, flush=True))
        res = {"run": Path(run_dir).name, "preset": model.run.name, "views": len(cameras),
               "points": int(np.asarray(pts.alive).sum()), "scene_dir": str(model.scene_dir), "motions": rows}
        if args.diagnose:
            res["diagnosis"] = diagnose(model, cameras, pts, pivot, ref, lambda s: print(s, flush=True))
        res["seconds"] = round(time.perf_counter() - t0, 1)
        results.append(res)
        write(args.out, results, command)


if __name__ == "__main__":
    entry(main)

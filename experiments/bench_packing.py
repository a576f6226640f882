"""What the packing budget costs a `default` training step, and whether it changes the step.

A training batch's segments are packed into ``ceil(R * segments_per_ray)`` slots before sampling,
KNN and shading; training fits that budget to a probe batch (:func:`ne_jax.geometry.capacity.
fit_packing`). This times the `default` training step of :mod:`experiments.profile_hot_path` (100,000
points on the glossy surface, a 2,048-ray batch) at several budgets that all hold the batch, one
after the other in one process (best of ``--repeats`` after a compiling call), and compares each
step's loss and updated parameters with those at the largest budget: a budget that loses no segment
should give the same step.

    python -m experiments.bench_packing --budgets 8 10 12 16

Writes ``experiments/results/bench_packing.{json,md}``.
"""

from __future__ import annotations

import argparse
import os

import jax
import jax.numpy as jnp

from experiments import common
from experiments.profile_hot_path import RESULTS, TRAIN_RAYS, best_time, build_inputs
from ne_jax.config_json import config_key
from ne_jax.geometry.intersect import intersect
from ne_jax.train.sampler import Batch
from ne_jax.train.state import init_train_state
from ne_jax.train.step import make_train_step


def measure(budgets: list[float], repeats: int, quick: bool) -> dict:
    """Time and compare the step at each of ``budgets`` (ascending)."""
    run, scene, _, trays, _, _ = build_inputs(quick)
    cfg = run.train_render
    mean = float(jnp.mean(intersect(scene.tree, trays, cfg.kdtree, scene.capacities).num_segments))
    bg = jnp.ones(3)
    state = init_train_state(run.train, cfg, scene.points, jax.random.key(1))
    batch = Batch(rays=trays, pixel=jnp.zeros(TRAIN_RAYS, jnp.int32), in_band=jnp.zeros(TRAIN_RAYS, bool),
                  background=bg)
    step = make_train_step(run.train, cfg)
    rows, outs = [], {}
    for budget in budgets:
        sc = scene.replace(capacities=scene.capacities.replace(segments_per_ray=float(budget)))
        seconds = best_time(lambda sc=sc: step(state, sc, batch)[1]["loss/total"], repeats)
        new_state, metrics = step(state, sc, batch)
        outs[budget] = (new_state.params, metrics)
        rows.append({"segments_per_ray": budget, "step_ms": round(1e3 * seconds, 1),
                     "lost_packing": int(metrics["lost/packing"]), "loss": float(metrics["loss/total"])})
        print(rows[-1], flush=True)
    ref_params, ref_metrics = outs[budgets[-1]]  # budgets sorted: the largest
    largest = rows[-1]
    for r in rows:
        params, metrics = outs[r["segments_per_ray"]]
        diffs = jax.tree_util.tree_map(lambda a, b: float(jnp.max(jnp.abs(a - b))), params, ref_params)
        r["max_param_diff_vs_largest"] = max(jax.tree_util.tree_leaves(diffs))
        r["loss_diff_vs_largest"] = abs(float(metrics["loss/total"]) - float(ref_metrics["loss/total"]))
        r["time_vs_largest"] = round(r["step_ms"] / largest["step_ms"], 3)
    return {"config_key": config_key(run), "mean_segments_per_ray": round(mean, 3), "rows": rows}


def to_markdown(report: dict) -> str:
    lines = [f"`default` training step (config key {report['config_key']}) at several packing budgets, commit "
             f"{report['commit']}: `{report['command']}`; the batch finds {report['mean_segments_per_ray']:.2f} "
             f"segments per ray; load average {report['load_average_1_5_15_min']}.", "",
             "| segments per ray | step ms | time / largest | segments lost | loss | largest parameter change "
             "vs largest budget |", "|---:|---:|---:|---:|---:|---:|"]
    for r in report["rows"]:
        lines.append(f"| {r['segments_per_ray']:g} | {r['step_ms']:.1f} | {r['time_vs_largest']:.3f}x | "
                     f"{r['lost_packing']} | {r['loss']:.6f} | {r['max_param_diff_vs_largest']:.2e} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--budgets", type=float, nargs="+", default=[8.0, 10.0, 12.0, 16.0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--quick", action="store_true", help="20,000 points (a smoke run)")
    parser.add_argument("--out", default="bench_packing")
    args = parser.parse_args(argv)
    report = measure(sorted(args.budgets), args.repeats, args.quick)
    report["command"] = ("python -m experiments.bench_packing --budgets " + " ".join(f"{b:g}" for b in args.budgets)
                         + (" --quick" if args.quick else "") + f" --repeats {args.repeats}")
    report["commit"] = common.commit()
    report["load_average_1_5_15_min"] = [round(x, 2) for x in os.getloadavg()]
    report["jax_devices"] = jax.device_count()
    common.write_results(RESULTS, args.out, report, to_markdown(report))


if __name__ == "__main__":
    import ne_jax

    ne_jax.setup(huge_pages=True)  # as `ne-jax` does: a host device per core, huge pages (restarts)
    main()

"""Differentiable editing, worked example: recover the unknown angle of a benchmark bend from images.

A tiny model of the benchmark scene ``glossy`` is trained on the unedited scene (or reused with
``--run``). Its ``bend`` edit bends the object by 60 degrees over 1.6 units along z towards +x; the
geometry of the bend (centre, axis, direction, length) is taken as known, its angle as unknown. From
the ground-truth images of the *edited* scene (``<scene>/edits/bend``, train split, a subset of
views and pixels) the angle is recovered by gradient descent through the differentiable part of
editing (positions, IST under a fixed plan) and the renderer (:mod:`ne_jax.edit.differentiable`),
with the plan and the K-D tree rebuilt at the current estimate every few steps.

    .venv/bin/python -m experiments.recover_bend                      # tiny benchmark + training if needed
    .venv/bin/python -m experiments.recover_bend --run /tmp/tb/runs/glossy --bench /tmp/bench

Writes ``experiments/results/recover_bend.json`` and ``recover_bend.png`` (angle and loss vs step).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shlex
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax

from ne_jax.atomic import atomic_write_json
from ne_jax.benchmark import scenes as S
from ne_jax.benchmark.generate import generate_benchmark
from ne_jax.data.nerf_synthetic import load_split, parse_background, split_rays
from ne_jax.edit.apply import edited_render_config
from ne_jax.edit.differentiable import (
    bend_deformation,
    make_edit_loss,
    recover_parameter,
)
from ne_jax.train.loop import train
from ne_jax.train.model import load_trained
from ne_jax.train.run import RunConfig

RESULTS = Path(__file__).resolve().parent / "results"
# The glossy scene's bend (ne_jax/benchmark/scenes.py make_glossy): everything but the angle is known.
BEND = {"center": (0.0, 0.0, -0.8), "along": (0.0, 0.0, 1.0), "toward": (1.0, 0.0, 0.0), "length": 1.6}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bench", default="/tmp/bench", help="tiny benchmark root (generated if the scene is missing)")
    ap.add_argument("--scene", default="glossy")
    ap.add_argument("--edit", default="bend")
    ap.add_argument("--run", default=None, help="reuse a trained run directory of the scene (default: train one)")
    ap.add_argument("--run-out", default="/tmp/recover_bend/run", help="where to train when --run is not given")
    ap.add_argument("--start-deg", type=float, default=None, help="starting angle (default: half the true angle)")
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--lr", type=float, default=0.04, help="Adam learning rate (radians per step)")
    ap.add_argument("--schedule", choices=["cosine", "constant"], default="constant",
                    help="learning-rate schedule (cosine: decays to 10%% over the steps)")
    ap.add_argument("--rebuild-every", type=int, default=4)
    ap.add_argument("--views", type=int, default=6, help="train views of the edited scene used")
    ap.add_argument("--rays-per-view", type=int, default=1024)
    ap.add_argument("--normals", choices=["deform", "plan"], default="deform")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=str(RESULTS / "recover_bend"), help="output path without extension")
    args = ap.parse_args(argv)
    t_start = time.perf_counter()

    scene_dir = Path(args.bench) / args.scene
    if not (scene_dir / "scene.json").is_file():
        print(f"generating the tiny benchmark scene {args.scene} under {args.bench}")
        generate_benchmark(args.bench, "tiny", scenes=[args.scene])
    edit_dir = scene_dir / "edits" / args.edit
    meta = json.loads((scene_dir / "scene.json").read_text())
    edit = S.get_scene(args.scene, meta["preset"]["detail"]).edits[args.edit]
    if edit.kind != "bend":
        raise SystemExit(f"{args.scene}/{args.edit}: expected a bend edit, found {edit.kind}")

    # the true angle (used only to check the known geometry and to score the result)
    true_deg = float(edit.description.split("bend by ")[1].split(" deg")[0])
    deform = bend_deformation(**BEND)
    probe = jnp.asarray(np.random.default_rng(0).uniform(-1, 1, (4096, 3)), jnp.float32)
    geometry_err = float(jnp.max(jnp.abs(deform(jnp.deg2rad(true_deg), probe) - edit.move(probe))))
    assert geometry_err < 1e-4, f"the known bend geometry does not match the benchmark's edit ({geometry_err})"

    if args.run is None:
        run_dir = Path(args.run_out)
        t0 = time.perf_counter()
        print(f"training RunConfig.tiny() on {scene_dir} into {run_dir}")
        train(RunConfig.tiny(), scene_dir, run_dir)
        train_seconds = time.perf_counter() - t0
    else:
        run_dir, train_seconds = Path(args.run), None
    model = load_trained(run_dir)
    points, params = model.scene.points, model.state.params
    background = parse_background(model.run.background)

    # targets: a subset of views and pixels of the edited scene's train split
    split = load_split(edit_dir, "train")
    rng = np.random.default_rng(args.seed)
    views = np.sort(rng.choice(split.num_views, size=min(args.views, split.num_views), replace=False))
    all_rays = split_rays(split, meta["near"], meta["far"], background)
    hw = split.height * split.width
    pick = np.concatenate([v * hw + np.sort(rng.choice(hw, size=min(args.rays_per_view, hw), replace=False))
                           for v in views])
    rays = all_rays.take(jnp.asarray(pick))
    targets = rays.target[:, :3]
    rays = rays.replace(target=None)

    render_cfg = edited_render_config(model.run.render).replace(chunk=rays.num_rays)
    true = float(np.deg2rad(true_deg))
    start = float(np.deg2rad(true_deg / 2 if args.start_deg is None else args.start_deg))
    problem = make_edit_loss(render_cfg, deform, normals=args.normals)
    # a packing budget for the rays at the start (grown by recover_parameter if a step needs more)
    start_topology = problem.topology(points, start, capacities=model.run.capacities)
    capacities = problem.scene(start, points, start_topology).fitted(render_cfg, rays, headroom=2.0).capacities

    def report(step, traj):
        th = float(traj.theta[-1][0])
        print(f"step {step:3d}  angle {np.rad2deg(th):8.3f} deg  loss {traj.loss[-1]:.6f}  "
              f"grad {float(traj.grad[-1][0]):+.5f}{'  (rebuilt)' if traj.rebuilt[-1] else ''}"
              f"  {traj.seconds[-1]:.1f}s", flush=True)

    print(f"true angle {true_deg:g} deg, start {np.rad2deg(start):g} deg, {rays.num_rays} rays from views "
          f"{views.tolist()}, {args.steps} Adam steps (lr {args.lr}), rebuild every {args.rebuild_every}")
    t0 = time.perf_counter()
    lr = optax.cosine_decay_schedule(args.lr, args.steps, alpha=0.1) if args.schedule == "cosine" else args.lr
    _, traj = recover_parameter(problem, params, points, start, rays, targets, background, steps=args.steps,
                                optimizer=optax.adam(lr), rebuild_every=args.rebuild_every, capacities=capacities,
                                callback=report)
    descent_seconds = time.perf_counter() - t0
    # the loss at the true angle under its own topology, for reference
    problem = traj.problem
    topo_true = problem.topology(points, true, capacities=traj.capacities)
    (loss_true, _), grad_true = problem.value_and_grad(jnp.float32(true), params, points, topo_true, rays,
                                                       targets, background)
    angles = np.rad2deg([float(t[0]) for t in traj.theta])
    best = int(np.argmin(traj.loss))
    result = {
        "scene": args.scene, "edit": args.edit, "edit_description": edit.description,
        "run_dir": str(run_dir), "bench": str(args.bench), "train_seconds": train_seconds,
        "true_deg": true_deg, "start_deg": float(np.rad2deg(start)), "final_deg": float(angles[-1]),
        "final_error_deg": float(angles[-1] - true_deg), "start_error_deg": float(np.rad2deg(start) - true_deg),
        "lowest_loss_step": best, "lowest_loss_deg": float(angles[best]),
        "loss_at_true_angle": float(loss_true), "grad_at_true_angle": float(grad_true),
        "steps": args.steps, "learning_rate": args.lr, "schedule": args.schedule, "rebuild_every": args.rebuild_every,
        "views": views.tolist(), "rays": int(rays.num_rays), "normals": args.normals, "mode": problem.mode,
        "segments_per_ray": {"start": capacities.segments_per_ray, "end": traj.capacities.segments_per_ray},
        "capacities": {"start": dataclasses.asdict(capacities), "end": dataclasses.asdict(traj.capacities)},
        "descent_seconds": round(descent_seconds, 2), "total_seconds": round(time.perf_counter() - t_start, 2),
        "device": str(jax.devices()[0]), "geometry_check_max_abs": geometry_err,
        "angle_deg": angles.tolist(), "trajectory": traj.to_dict(),
        "command": " ".join(shlex.quote(a) for a in [sys.executable, *sys.argv]),
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out_json, out_png = Path(f"{out}.json"), Path(f"{out}.png")
    atomic_write_json(out_json, result)
    plot(result, out_png)
    print(f"\nrecovered {angles[-1]:.3f} deg (true {true_deg:g}, start {np.rad2deg(start):g}): error "
          f"{angles[-1] - true_deg:+.3f} deg after {args.steps} steps, descent {descent_seconds:.1f} s; "
          f"loss {traj.loss[0]:.6f} -> {traj.loss[-1]:.6f} (at the true angle {float(loss_true):.6f}); "
          f"compilations during the descent: {traj.compiles}")
    print(f"wrote {out_json} and {out_png}")
    print(f"re-run: .venv/bin/python -m experiments.recover_bend --run {run_dir} --bench {args.bench}")
    return result


def plot(result: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = np.arange(len(result["angle_deg"]))
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.6))
    a.plot(steps, result["angle_deg"], "o-", ms=3, label="estimate")
    a.axhline(result["true_deg"], color="k", ls="--", label=f"true ({result['true_deg']:g} deg)")
    rebuilt = np.flatnonzero(result["trajectory"]["rebuilt"])
    a.plot(rebuilt, np.asarray(result["angle_deg"])[rebuilt], "x", color="C3", label="plan + tree rebuilt")
    a.set_xlabel("step")
    a.set_ylabel("bend angle (deg)")
    a.legend()
    b.semilogy(steps, result["trajectory"]["loss"], "o-", ms=3)
    b.axhline(result["loss_at_true_angle"], color="k", ls="--", label="at the true angle")
    b.set_xlabel("step")
    b.set_ylabel("image MSE")
    b.legend()
    fig.suptitle(f"{result['scene']}/{result['edit']}: recovering the bend angle by gradient descent")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    import ne_jax

    ne_jax.setup(huge_pages=True)  # as `ne-jax` does: a host device per core, huge pages (restarts)
    main()

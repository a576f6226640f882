"""The GPU check in one command: what a lent accelerator does with the ``default`` and ``paper`` presets
(docs/devices.md).

    python -m experiments.gpu_check [--budget-s 420] [--scene-root DIR] [--out-dir DIR] [--tiny]
    python -m experiments.gpu_check --generate-only --scene-root DIR   # the scenes alone (needs Open3D)

Within ``--budget-s`` seconds (start-up and scene generation aside), in this order: the devices; the
rates of each preset's training step and test render (:func:`rates`); a whole ``default`` run on a
200 px scene (:func:`default_run`); the ``paper`` preset on an 800 px scene for what is left of the
budget, and the full run projected from it (:func:`paper_run`). The scenes are the benchmark's
``glossy``, ray-cast with Open3D into ``--scene-root`` (or generated elsewhere and carried). ``--tiny``:
every part at a toy size, a smoke test on a CPU. Writes ``gpu_check[_tiny]_<device>.{json,md}`` to
``--out-dir`` (``<device>``: ``common.device_tag``).
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import platform
import resource
import time
from pathlib import Path

from experiments import common
from experiments.common import SCENE

PAPER_STEPS = 80_000
"""The ``paper`` preset's steps (16 epochs x 5,000)."""
PAPER_ROUNDS = 9
"""The ``paper`` preset's point-cloud rounds (after epochs 4-12)."""
TEST_VIEWS = 200
"""Test views of a NeRF Synthetic scene, for the projected evaluation."""
SCENE_ROOT = Path("/tmp/ne_jax_gpu_check/scenes")
"""Where the generated scenes are kept by default."""


@dataclasses.dataclass(frozen=True)
class Sizes:
    """How big each part of the check is: the ``default`` and the ``paper`` run's scenes (``small``,
    ``large``: :class:`~ne_jax.benchmark.generate.BenchmarkPreset`), the timed training steps and
    renders per preset (after a compiling one), the test views the ``paper`` run is scored on."""

    small: object
    large: object
    rate_steps: int
    repeats: int
    score_views: int
    tiny: bool


def sizes(tiny: bool) -> Sizes:
    from ne_jax.benchmark.generate import BenchmarkPreset

    if tiny:
        return Sizes(small=BenchmarkPreset("gpu_check_tiny_16", 16, 8, 1, 2, 1, 0.5, 2_000),
                     large=BenchmarkPreset("gpu_check_tiny_24", 24, 8, 1, 2, 1, 0.5, 3_000),
                     rate_steps=2, repeats=1, score_views=2, tiny=True)
    return Sizes(small=BenchmarkPreset("gpu_check_200", 200, 100, 1, 4, 1, 1.0, 100_000),
                 large=BenchmarkPreset("gpu_check_800", 800, 100, 1, 4, 1, 1.0, 300_000),
                 rate_steps=50, repeats=3, score_views=4, tiny=False)


def toy(run, points: int):
    """``run`` at a toy size for a CPU smoke test: ``points`` carved points on a 32-voxel grid, 128
    rays a batch, render chunks of 256 rays, a 128-ray round, 3 epochs of 2 steps with a round after
    the second, its tree fitted to the cloud (the ``paper`` preset's is fixed at 21 levels)."""
    carve = dataclasses.replace(run.init.carve, resolution=32, num_points=points)
    render = run.render.replace(kdtree=run.render.kdtree.replace(depth=None), chunk=256)
    rounds = dataclasses.replace(run.rounds, grow_rays=128, grow_chunk=128)
    return run.replace(init=dataclasses.replace(run.init, carve=carve), sampler=run.sampler.replace(batch_size=128),
                       rounds=rounds, render=render).with_schedule(epochs=3, steps_per_epoch=2).replace(
                           round_epochs=(2, 2))


def presets(s: Sizes) -> dict:
    """``{"default": RunConfig, "paper": RunConfig}`` at the check's size (the presets themselves, or
    :func:`toy` ones)."""
    from ne_jax.train.run import RunConfig

    d, p = RunConfig.default(), RunConfig.paper()
    return {"default": toy(d, 1_500), "paper": toy(p, 2_000)} if s.tiny else {"default": d, "paper": p}


def scene_dir(preset, root: Path, log=print) -> Path:
    """``root/<preset name>/glossy``: the scene of ``preset`` (generated there if not yet: Open3D)."""
    from ne_jax.benchmark.generate import generate_scene

    out = Path(root) / preset.name
    if not (out / SCENE / "scene.json").is_file():
        t0 = time.perf_counter()
        generate_scene(SCENE, preset, out, edits=(), resume=True)
        log(f"generated {out / SCENE} ({preset.resolution} px, {preset.train_views} training views) in "
            f"{time.perf_counter() - t0:.0f} s")
    return out / SCENE


def declared(run, scene: Path):
    """``run`` with the effects the scene declares, as ``ne-jax train`` declares them."""
    from ne_jax.train.effects import declare_effects

    render, _ = declare_effects(run.render, "scene", scene)
    return run.replace(render=render)


def device_info() -> dict:
    import jax
    import jaxlib

    devs = jax.devices()
    stats = _memory_stats(devs[0])
    return {"platform": devs[0].platform, "kind": devs[0].device_kind, "count": len(devs),
            "devices": [str(d) for d in devs], "memory_limit_bytes": stats.get("bytes_limit"),
            "jax": jax.__version__, "jaxlib": jaxlib.__version__, "python": platform.python_version(),
            "cpus": os.cpu_count(), "machine": platform.platform()}


def _memory_stats(dev) -> dict:
    try:
        return dev.memory_stats() or {}
    except Exception:  # noqa: BLE001  (a backend without memory statistics)
        return {}


def peak_memory() -> dict:
    """The device's peak bytes in use so far (``None`` where the backend keeps none: a CPU) and the
    process's peak resident memory in bytes."""
    import jax

    return {"device_peak_bytes": _memory_stats(jax.devices()[0]).get("peak_bytes_in_use"),
            "host_peak_rss_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024}


def rates(run, scene: Path, steps: int, repeats: int) -> dict:
    """Rays per second of ``run``'s training step and of its test render of view 0, on the scene's
    ground-truth surface samples (``run.init.carve.num_points`` of them) with an untrained model."""
    import types

    import jax
    import numpy as np

    from ne_jax.data.nerf_synthetic import load_split
    from ne_jax.geometry.points import PointState
    from ne_jax.pointcloud.init import ground_truth_cloud
    from ne_jax.render.renderer import PointScene
    from ne_jax.train.run import INIT_CAPACITY_HEADROOM
    from ne_jax.train.sampler import build_pool
    from ne_jax.train.state import init_train_state

    cloud = ground_truth_cloud(scene)
    n = min(len(cloud), run.init.carve.num_points)
    pick = np.random.default_rng(0).choice(len(cloud), n, replace=False)
    points = PointState.from_numpy(cloud.xyz[pick], int(math.ceil(n * INIT_CAPACITY_HEADROOM)),
                                   run.render.shading.feature_dim, normal=cloud.normals[pick], key=jax.random.key(0))
    t0 = time.perf_counter()
    built = PointScene.build(points, run.render, run.capacities)
    build_s = time.perf_counter() - t0
    state = init_train_state(run.train, run.render, points, jax.random.key(1), total_steps=run.total_steps)
    pool = build_pool(run.sampler, load_split(scene, "train"), run.background)
    model = types.SimpleNamespace(state=state, scene=built)  # what time_steps reads of a trained model
    step = common.time_steps(run, model, pool, built, steps)
    view = load_split(scene, "test").take([0])
    first, t_img = common.time_test_render(run, state.params, built, view.camera(0), repeats)
    rays = view.width * view.height * run.render.pixel_samples ** 2
    return {"points": n, "tree_depth": int(built.tree.depth), "tree_build_s": round(build_s, 2),
            "train_rays_per_s": round(step["batch_rays"] / (step["ms_per_step"] / 1e3)), **step,
            "image_px": view.width, "image_rays": rays, "ms_per_image": round(1e3 * t_img, 1),
            "image_compile_s": round(max(0.0, first - t_img), 2), "render_rays_per_s": round(rays / t_img),
            "memory": peak_memory()}


def _epochs(history: list) -> list[dict]:
    """The per-epoch figures of a run's ``metrics.json`` records."""
    return [{"epoch": r["epoch"], "steps": r["steps"], "train_s": r["train_seconds"], "psnr_train": r.get("psnr"),
             "alive": r["alive"], "round_s": r["points"]["seconds"] if "points" in r else None,
             "compiles": r["compiles"]} for r in history]


def score(model, scene: Path, views: int) -> dict:
    """``model`` scored on the first ``views`` test views (LPIPS left out), each view timed: the first
    compiles, the rest give the time per view."""
    from ne_jax.data.nerf_synthetic import load_split
    from ne_jax.eval.views import evaluate_model

    test = load_split(scene, "test")
    views = min(views, test.num_views)
    seconds, reports = [], []
    for i in range(views):
        t0 = time.perf_counter()
        report, _ = evaluate_model(model, test.take([i]), progress=False, lpips_net=None)
        seconds.append(time.perf_counter() - t0)
        reports.append(report)
    later = seconds[1:] or seconds
    return {"views": views, "image_px": test.width, "psnr": round(sum(r["psnr"] for r in reports) / views, 2),
            "ssim": round(sum(r["ssim"] for r in reports) / views, 4),
            "lost_segments": sum(r["lost_segments"] for r in reports), "view_s": [round(s, 2) for s in seconds],
            "s_per_view": round(min(later), 3)}


def default_run(run, scene: Path, run_dir: Path, views: int, log=print) -> dict:
    """The whole ``run`` on ``scene`` from scratch (its rounds, checkpoints), then scored."""
    from ne_jax.config_json import config_key
    from ne_jax.train.loop import train

    t0 = time.perf_counter()
    model = train(run, scene, run_dir, resume=False, progress=False, log=lambda s: log("  default: " + s))
    train_s = time.perf_counter() - t0
    scored = score(model, scene, views)
    return {"config_key": config_key(run), "run_dir": str(run_dir), "steps": run.total_steps,
            "batch_rays": run.sampler.batch_size, "wall_s": round(train_s, 1),
            "initial_cloud": {k: model.initial.get(k) for k in ("source", "points", "seconds")},
            "epochs": _epochs(model.history), "test": scored, "memory": peak_memory()}


PAPER_EPOCHS = 4
"""Epochs of the check's shortened ``paper`` run (a point-cloud round after the second)."""


def steps_per_epoch(left_s: float, s_per_step: float, epochs: int, views: int, s_per_view: float) -> int:
    """Steps per epoch of the shortened ``paper`` run given ``left_s`` seconds: what is left after
    scoring ``views`` views (and two more for the compile), half of it for the steps (the rest for the
    initial cloud, the round, the checkpoints and the compiles), at least 10."""
    left = left_s - (views + 2) * s_per_view
    return max(10, int(0.5 * left / s_per_step / epochs))


def next_epoch_fits(spent_s: float, calls: list[dict], budget_s: float, views: int, s_per_view: float) -> bool:
    """Whether another epoch (as long as the longest after the first of ``calls``, each ``{"s": ..}``)
    and scoring ``views`` views (one more for the compile) still end within ``budget_s``."""
    epoch_s = max(c["s"] for c in calls[1:] or calls)
    return spent_s + epoch_s + (views + 1) * s_per_view <= budget_s


def paper_run(run, scene: Path, run_dir: Path, s_per_step: float, budget_s: float, views: int, s_per_view: float,
              tiny: bool, log=print) -> dict:
    """The ``paper`` preset on ``scene``, shortened to :data:`PAPER_EPOCHS` epochs (a round after the
    second) of steps sized from ``s_per_step`` to end within ``budget_s`` seconds, trained epoch by epoch
    (each call resuming) until the next epoch would not fit, then scored on ``views`` test views; and the
    full run projected from it: :data:`PAPER_STEPS` steps at the step time of its epochs that compiled
    nothing, :data:`PAPER_ROUNDS` rounds at its round's time, :data:`TEST_VIEWS` views at its time per view."""
    from ne_jax.config_json import config_key
    from ne_jax.data.nerf_synthetic import load_split
    from ne_jax.train.loop import train

    epochs = PAPER_EPOCHS
    t0 = time.perf_counter()
    split = load_split(scene, "train", run.downscale)
    load_s = time.perf_counter() - t0
    steps = 2 if tiny else steps_per_epoch(budget_s - load_s, s_per_step, epochs, views, s_per_view)
    run = run.with_schedule(epochs=epochs, steps_per_epoch=steps).replace(round_epochs=(2, 2))
    log(f"  paper: {epochs} epochs of {steps} steps (~{s_per_step * 1e3:.0f} ms each), a round after epoch 2, "
        f"{budget_s:.0f} s left")
    model, calls, stopped = None, [], None
    for k in range(1, epochs + 1):
        spent = time.perf_counter() - t0
        if model is not None and not tiny and not next_epoch_fits(spent, calls, budget_s, views, s_per_view):
            stopped = f"after epoch {k - 1}: the next epoch and the scoring would pass the budget"
            break
        c0 = time.perf_counter()
        model = train(run, scene, run_dir, resume=k > 1, progress=False, stop_after_epoch=k, split=split,
                      log=lambda s: log("  paper: " + s))
        calls.append({"epoch": k, "resumed": k > 1, "s": round(time.perf_counter() - c0, 1),
                      "host_peak_rss_bytes": peak_memory()["host_peak_rss_bytes"]})  # the process's so far
    train_s = time.perf_counter() - t0
    scored = score(model, scene, views)
    hist = _epochs(model.history)
    # the epochs that compiled nothing (a round can change the capacities), else those after the first
    later = [e for e in hist if not e["compiles"]] or [e for e in hist if e["epoch"] > 1] or hist
    step_s = sum(e["train_s"] for e in later) / sum(e["steps"] for e in later)
    round_s = next((e["round_s"] for e in hist if e["round_s"] is not None), None)
    init_s = model.initial.get("seconds") or 0.0
    projected = {"train_s": round(PAPER_STEPS * step_s), "rounds_s": None if round_s is None else
                 round(PAPER_ROUNDS * round_s), "initial_cloud_s": init_s,
                 "eval_s": round(TEST_VIEWS * scored["s_per_view"])}
    projected["total_h"] = round(sum(v for v in projected.values() if v) / 3600, 2)
    return {"config_key": config_key(run), "run_dir": str(run_dir), "epochs_planned": epochs,
            "steps_per_epoch": steps, "batch_rays": run.sampler.batch_size, "stopped": stopped, "calls": calls,
            "wall_s": round(train_s, 1), "load_images_s": round(load_s, 1),
            "initial_cloud": {k: model.initial.get(k) for k in ("source", "points", "seconds")},
            "epochs": hist, "s_per_step": round(step_s, 4), "train_rays_per_s": round(run.sampler.batch_size / step_s),
            "test": scored, "projected": {"steps": PAPER_STEPS, "rounds": PAPER_ROUNDS, "test_views": TEST_VIEWS,
                                          **projected}, "memory": peak_memory()}


def check(s: Sizes, scene_root: Path, run_root: Path, budget_s: float, log=print, save=lambda res: None) -> dict:
    """Every part of the check (module docstring); ``budget_s`` counts from the first part. ``save``
    is given the results so far after each part (a check stopped part way still leaves them)."""
    log_t = lambda m: log(f"[{time.perf_counter() - t0:6.0f} s] {m}")  # noqa: E731
    small, large = scene_dir(s.small, scene_root, log), scene_dir(s.large, scene_root, log)
    t0 = time.perf_counter()
    res = {"devices": device_info(), "budget_s": budget_s, "scene": SCENE,
           "scenes": {"small": dataclasses.asdict(s.small), "large": dataclasses.asdict(s.large)}}
    log_t(f"devices: {res['devices']['devices']}")
    runs = presets(s)
    runs = {"default": declared(runs["default"], small), "paper": declared(runs["paper"], large)}
    res["rates"] = {}
    for name, scene in (("default", small), ("paper", large)):
        r = res["rates"][name] = rates(runs[name], scene, s.rate_steps, s.repeats)
        save(res)
        log_t(f"{name}: step {r['ms_per_step']:.1f} ms ({r['train_rays_per_s']} rays/s), {r['image_px']} px image "
              f"{r['ms_per_image']:.0f} ms ({r['render_rays_per_s']} rays/s)")
    d = res["default_run"] = default_run(runs["default"], small, run_root / "default", 1 if s.tiny else 4, log=log_t)
    save(res)
    log_t(f"default run: {d['steps']} steps in {d['wall_s']:.0f} s, test PSNR {d['test']['psnr']:.2f} dB")
    paper_rate = res["rates"]["paper"]
    left = budget_s - (time.perf_counter() - t0)
    p = res["paper_run"] = paper_run(runs["paper"], large, run_root / "paper", paper_rate["ms_per_step"] / 1e3, left,
                                     s.score_views, paper_rate["ms_per_image"] / 1e3, s.tiny, log=log_t)
    log_t(f"paper run: {sum(e['steps'] for e in p['epochs'])} steps, {p['s_per_step'] * 1e3:.1f} ms/step, test PSNR "
          f"{p['test']['psnr']:.2f} dB on {p['test']['views']} views ({p['test']['s_per_view']:.1f} s/view); "
          f"full run ~{p['projected']['total_h']:.2f} h")
    res["seconds"] = round(time.perf_counter() - t0, 1)
    res["within_budget"] = res["seconds"] <= budget_s
    return res


def _mb(b) -> str:
    return "" if b is None else f"{b / 2**20:.0f}"


def markdown(res: dict) -> str:
    d, r, dr, pr = res["devices"], res["rates"], res["default_run"], res["paper_run"]
    L = [f"GPU check on {d['kind']} ({d['platform']}, {d['count']} device(s), jax {d['jax']}, {d['cpus']} CPUs): "
         f"commit {res['commit']}, `{res['command']}`; {res['seconds']:.0f} s of a {res['budget_s']:.0f} s budget. "
         f"Scene `{res['scene']}` at {res['scenes']['small']['resolution']} and "
         f"{res['scenes']['large']['resolution']} px.", "",
         "| preset | points | tree depth | rays / step | ms / step | train rays/s | image px | ms / image | "
         "render rays/s | compile step / image (s) | device peak (MiB) |",
         "|---|---:|---:|---:|---:|---:|---:|---:|---:|---|---:|"]
    for name, x in r.items():
        L.append(f"| {name} | {x['points']} | {x['tree_depth']} | {x['batch_rays']} | {x['ms_per_step']:.1f} | "
                 f"{x['train_rays_per_s']} | {x['image_px']} | {x['ms_per_image']:.0f} | {x['render_rays_per_s']} | "
                 f"{x['step_compile_s']:.0f} / {x['image_compile_s']:.0f} | {_mb(x['memory']['device_peak_bytes'])} |")
    L += ["", f"Whole `default` run (config key {dr['config_key']}): {dr['steps']} steps of {dr['batch_rays']} rays in "
          f"{dr['wall_s']:.0f} s, initial cloud {dr['initial_cloud']['points']} points in "
          f"{dr['initial_cloud']['seconds']} s, rounds " + ", ".join(f"{e['round_s']:.1f}" for e in dr["epochs"]
                                                                      if e["round_s"] is not None)
          + f" s; test PSNR {dr['test']['psnr']:.2f} dB on {dr['test']['views']} view(s).", "",
          f"`paper` on {pr['test']['image_px']} px (config key {pr['config_key']}): "
          f"{len(pr['epochs'])} of {pr['epochs_planned']} epochs of {pr['steps_per_epoch']} steps "
          f"({pr['stopped'] or 'all'}), {pr['s_per_step'] * 1e3:.1f} ms per step in epochs without a compile "
          f"({pr['train_rays_per_s']} rays/s), initial cloud {pr['initial_cloud']['points']} points in "
          f"{pr['initial_cloud']['seconds']} s; test PSNR {pr['test']['psnr']:.2f} dB on {pr['test']['views']} views, "
          f"{pr['test']['s_per_view']:.2f} s per view. Projected full run: {pr['projected']['steps']} steps "
          f"{pr['projected']['train_s']} s + {pr['projected']['rounds']} rounds {pr['projected']['rounds_s']} s + "
          f"{pr['projected']['test_views']} test views {pr['projected']['eval_s']} s = "
          f"{pr['projected']['total_h']:.2f} h; device peak {_mb(pr['memory']['device_peak_bytes'])} MiB, host peak "
          f"{_mb(pr['memory']['host_peak_rss_bytes'])} MiB."]
    return "\n".join(L) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--budget-s", type=float, default=420.0,
                    help="seconds for the whole check after its scenes exist (default 420: fits 10 minutes of device "
                         "time with the machine's start)")
    ap.add_argument("--scene-root", type=Path, default=SCENE_ROOT,
                    help="where the generated scenes are kept (generated there if missing; needs Open3D)")
    ap.add_argument("--run-root", type=Path, default=Path("/tmp/ne_jax_gpu_check/runs"),
                    help="the runs' directories (started afresh)")
    ap.add_argument("--out-dir", type=Path, default=common.RESULTS)
    ap.add_argument("--commit", help="the commit to record where the checkout has no git (a copied tree)")
    ap.add_argument("--tiny", action="store_true", help="every part at a toy size (a CPU smoke test)")
    ap.add_argument("--generate-only", action="store_true",
                    help="generate the scenes into --scene-root and stop (where Open3D is, for a machine without)")
    args = ap.parse_args(argv)
    if args.budget_s <= 0:
        raise SystemExit(f"--budget-s: expected a positive number of seconds, found {args.budget_s}")
    log = common.log
    if args.generate_only:
        for preset in (sizes(args.tiny).small, sizes(args.tiny).large):
            log(f"scene: {scene_dir(preset, args.scene_root, log)}")
        return 0
    stem = f"gpu_check{'_tiny' if args.tiny else ''}_{common.device_tag()}"
    known = {"command": common.command("gpu_check", argv), "commit": args.commit or common.commit()}

    def save(res):  # the parts so far, marked incomplete
        from ne_jax.atomic import atomic_write_json

        args.out_dir.mkdir(parents=True, exist_ok=True)
        atomic_write_json(args.out_dir / f"{stem}.json", {**res, **known, "complete": False})

    res = check(sizes(args.tiny), args.scene_root, args.run_root, args.budget_s, log, save)
    res.update(known, complete=True)
    common.write_results(args.out_dir, stem, res, markdown(res))
    return 0


if __name__ == "__main__":
    common.entry(main)

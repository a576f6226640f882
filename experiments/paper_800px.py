"""The ``paper`` preset at NeRF Synthetic scale on this machine: an 800 px scene, a shortened run.

    python -m experiments.paper_800px [--budget-s 3000] [--views 3] [--scene-root DIR] [--runs DIR]

The benchmark's ``glossy`` scene ray-cast at 800 x 800 in a NeRF Synthetic scene's layout (100 training,
200 test views); the ``paper`` preset shortened, ``--views`` test views scored and the full run projected
as :func:`experiments.gpu_check.paper_run` does (sized from ``--s-per-step`` to end within ``--budget-s``),
and the process's peak memory (docs/devices.md). Writes ``paper_800px[_<device>].{json,md}`` to ``--out-dir``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from experiments.common import RESULTS, command, commit, device_tag, entry, log, write_results
from experiments.gpu_check import SCENE_ROOT, declared, device_info, paper_run, scene_dir

HOST_MEMORY_GOAL = 16 * 2**30
"""The issue's bound on the process's peak resident memory."""


def preset():
    """The 800 px scene: 100 training, 1 validation and 200 test views, one ray a pixel, the ``paper``
    preset's 300,000 surface samples."""
    from ne_jax.benchmark.generate import BenchmarkPreset

    return BenchmarkPreset("paper_800", 800, 100, 1, 200, 1, 1.0, 300_000)


def markdown(res: dict) -> str:
    p, m = res["paper"], res["paper"]["memory"]
    host = m["host_peak_rss_bytes"] / 2**30
    rss = {c["epoch"]: c.get("host_peak_rss_bytes") for c in p["calls"]}
    gib = {k: "" if v is None else f"{v / 2**30:.1f}" for k, v in rss.items()}
    e = "\n".join(f"| {r['epoch']} | {r['steps']} | {r['train_s']} | {r['psnr_train']:.2f} | {r['alive']} | "
                  f"{r['round_s'] if r['round_s'] is not None else ''} | {r['compiles']} | {gib.get(r['epoch'], '')} |"
                  for r in p["epochs"])
    pr = p["projected"]
    return (f"`paper` preset on an 800 px ray-cast `glossy` scene (100 training, 200 test views) on "
            f"{res['device']['kind']}; commit {res['commit']}, config key {p['config_key']}; `{res['command']}`.\n\n"
            f"{p['epochs_planned']} epochs of {p['steps_per_epoch']} steps of {p['batch_rays']} rays, a round after "
            f"epoch 2, each epoch a resumed call ({'; stopped ' + p['stopped'] if p['stopped'] else 'all ran'}); "
            f"images loaded in {p['load_images_s']} s, initial cloud {p['initial_cloud']['points']} points "
            f"({p['initial_cloud']['source']}) in {p['initial_cloud']['seconds']} s, training {p['wall_s']} s in "
            "all.\n\n| epoch | steps | train s | train PSNR | alive | round s | compiles | peak RSS so far (GiB) |\n"
            "|---:|---:|---:|---:|---:|---:|---:|---:|\n"
            f"{e}\n\n"
            f"A step: {p['s_per_step']} s ({p['train_rays_per_s']} rays/s, the epochs that compiled nothing). "
            f"{p['test']['views']} test views of {p['test']['image_px']} px scored: PSNR {p['test']['psnr']} dB "
            f"(a shortened run), {p['test']['view_s']} s each (the first compiles), {p['test']['s_per_view']} s a view "
            f"after it, {p['test']['lost_segments']} segments lost.\n\n"
            f"Projected full run: {pr['steps']} steps {pr['train_s']} s + {pr['rounds']} rounds {pr['rounds_s']} s + "
            f"initial cloud {pr['initial_cloud_s']} s + {pr['test_views']} test views {pr['eval_s']} s = "
            f"**{pr['total_h']} h**.\n\n"
            f"Peak resident memory of the process: **{host:.1f} GiB** (goal: within "
            f"{HOST_MEMORY_GOAL / 2**30:.0f} GiB: {'met' if host * 2**30 <= HOST_MEMORY_GOAL else 'NOT met'}).\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--budget-s", type=float, default=3000.0, help="seconds for training and scoring")
    ap.add_argument("--s-per-step", type=float, default=4.0,
                    help="the expected seconds of a paper step here (sizes the epochs)")
    ap.add_argument("--s-per-view", type=float, default=300.0, help="the expected seconds of an 800 px test view")
    ap.add_argument("--views", type=int, default=3, help="test views to score (the first compiles)")
    ap.add_argument("--scene-root", type=Path, default=SCENE_ROOT)
    ap.add_argument("--runs", type=Path, default=Path("/tmp/ne_jax_paper_800px/runs"))
    ap.add_argument("--out-dir", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    if args.views < 1 or args.budget_s <= 0:
        raise SystemExit("--views: expected at least 1; --budget-s: expected > 0")
    from ne_jax.train.run import RunConfig

    scene = scene_dir(preset(), args.scene_root, log)
    run = declared(RunConfig.paper(), scene)
    res = {"device": device_info(), "scene": str(scene), "commit": commit(), "command": command("paper_800px", argv)}
    res["paper"] = paper_run(run, scene, args.runs / "paper", args.s_per_step, args.budget_s, args.views,
                             args.s_per_view, tiny=False, log=log)
    res["host_memory_goal_bytes"] = HOST_MEMORY_GOAL
    tag = device_tag()
    write_results(args.out_dir, "paper_800px" if tag == "cpu" else f"paper_800px_{tag}", res, markdown(res))
    return 0


if __name__ == "__main__":
    entry(main)

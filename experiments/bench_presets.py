"""What each training preset costs per step and per image on this machine, on one trained cloud.

    python -m experiments.bench_presets --run RUN_DIR [--scene DIR] [--steps 20] [--repeats 3]
                                        [--settings LABEL ...] [--quick]

The presets differ in what a step renders (K, candidates, levels, samples per segment, the tree's
depth and width) and in how many rays a batch holds, and a full run of the ``paper`` preset (80,000
steps of 4,096 rays) is far beyond a CPU. This measures every preset on the same cloud, a trained
run's final points and colour model, so the costs compare and a preset's training time can be
projected on a machine (a GPU) where it was never trained. Per preset, and for six variants:
``default`` walked in one pass (the reference for the two-pass walk), ``default`` with the tree's
default box margins, with its images at one ray per pixel and trained at 2 x 2 rays per pixel,
``default`` with the paper's
per-sample settings (the training study's most accurate candidate) and ``paper`` with 32 segment
slots a ray instead of 64 (its capacity before this benchmark showed what it loses):

* the tree built over the cloud with the preset's tree config (its depth);
* ``--steps`` training steps from the run's parameters with the preset's train config and sampler
  (batch size) on the run's training split, the packing budget fitted to the first batch as
  training does: time per step and per ray after the compiling first, the compile time,
  the segments lost (to the traversal's capacities and to the packing budget), the first batch's
  segments per ray and its rays that fill every segment slot or overflow, and the projection
  ``total_steps x time per step`` (point-cloud rounds and evaluation excluded);
* test view 0 rendered with the preset's render config (best of ``--repeats`` after a compiling
  call): time per image and its PSNR with the run's parameters (the same model for every row, so it
  shows what the render settings do to that model, not what training with them would reach).

Ratios are against the ``default`` preset's row, measured in the same process. Writes
``bench_presets_<device>.{json,md}`` to ``--out-dir`` (default ``experiments/results``).
"""

from __future__ import annotations

import argparse
import functools
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"

from experiments.common import best_time, device_tag, timed_steps  # noqa: E402
from experiments.common import write_results as write_bench  # noqa: E402

REFERENCE = "default"


def settings(quick: bool) -> list[tuple[str, object]]:
    """``(label, RunConfig)``: every preset; ``default`` walked in one 64-wide pass, with the tree's
    default box margins (``margin_factor`` 1), with its images at one ray per pixel (the preset
    renders 2 x 2), trained at 2 x 2 rays per pixel (a batch of the same rays, a quarter of the
    pixels) and with the paper's sampling (also walked in
    one pass, as it was measured); ``paper`` with 32 segment slots a ray (its capacity until it was
    measured) instead of 64."""
    from ne_jax.render.renderer import RenderConfig
    from ne_jax.train.run import PRESETS, RunConfig

    out = [(name, make()) for name, make in PRESETS.items()]
    d = RunConfig.default()
    one_pass = d.capacities.replace(first_pass_frontier=None)
    paper_sampling = RenderConfig()  # the paper's per-sample settings on the default preset's tree
    margin1 = d.render.kdtree.replace(margin_factor=1.0)
    out[2:2] = [("default, one pass", d.replace(capacities=one_pass)),
                ("default, margin 1", d.replace(render=d.render.replace(kdtree=margin1))),
                ("default, images at one ray per pixel", d.replace(render=d.render.replace(pixel_samples=1))),
                ("default, trained at 2x2 rays per pixel", d.replace(sampler=d.sampler.replace(pixel_samples=2))),
                ("default, paper sampling", d.replace(render=d.render.replace(kdtree=paper_sampling.kdtree,
                                                                              quadrature=paper_sampling.quadrature),
                                                      capacities=one_pass))]
    p = RunConfig.paper()
    out.append(("paper, 32 segment slots", p.replace(capacities=p.capacities.replace(max_segments=32))))
    return [s for s in out if s[0] in ("tiny", REFERENCE)] if quick else out


def time_steps(run, model, pool, scene, steps: int) -> dict:
    """``steps`` training steps of ``run``'s config from ``model``'s parameters and cloud."""
    import jax

    from ne_jax.geometry.intersect import intersect
    from ne_jax.train.sampler import sample_batch
    from ne_jax.train.state import init_train_state
    from ne_jax.train.step import make_train_step

    key = jax.random.PRNGKey(0)
    points = model.state.point_state(model.scene.points)
    state = init_train_state(run.train, run.render, points, key).replace(params=model.state.params)
    train_render = run.train_render
    batches = [sample_batch(run.sampler, pool, jax.random.fold_in(key, i), train_render.pixel_samples)
               for i in range(steps + 1)]
    scene = scene.fitted(train_render, batches[0].rays)  # the packing budget, as training fits it
    step = make_train_step(run.train, train_render)
    _, per_step, first_s, lost = timed_steps(step, state, scene, batches)
    segs = intersect(scene.tree, batches[0].rays, run.render.kdtree, scene.capacities)
    found = np.asarray(segs.valid).sum(1)
    rays = run.sampler.batch_size
    cap = scene.capacities
    return {"batch_rays": rays, "segments_per_ray": cap.segments_per_ray, "ms_per_step": round(1e3 * per_step, 2),
            "us_per_ray": round(1e6 * per_step / rays, 3), "step_compile_s": round(first_s - per_step, 2),
            "train_segments_lost": lost.total, "lost_to_capacity": lost.frontier + lost.slots,
            "lost_to_budget": lost.packing,
            "first_batch": {"mean_segments": round(float(found.mean()), 2),
                            "rays_at_max_segments": int((found == cap.max_segments).sum()),
                            "rays_overflowing": int((np.asarray(segs.lost().count) > 0).sum())},
            "total_steps": run.total_steps, "projected_train_min": round(run.total_steps * per_step / 60, 1)}


def run_bench(run_dir: Path, scene_dir: Path | None, steps: int, repeats: int, quick: bool, log=print,
              only: list[str] | None = None) -> dict:
    """Every setting of :func:`settings` (``only``: those labels, and always the reference)."""
    import jax

    from ne_jax.data.nerf_synthetic import load_split, parse_background
    from ne_jax.eval.views import evaluate_split
    from ne_jax.render.quadrature import at_test_time
    from ne_jax.render.renderer import PointScene, render_image
    from ne_jax.train.model import load_trained
    from ne_jax.train.sampler import build_pool

    chosen = settings(quick)
    if only:
        unknown = sorted(set(only) - {label for label, _ in chosen})
        if unknown:
            raise ValueError(f"--settings: expected labels among {[label for label, _ in chosen]}, found {unknown}")
        chosen = [(label, run) for label, run in chosen if label in only or label == REFERENCE]
    model = load_trained(run_dir)
    scene_dir = Path(scene_dir or model.scene_dir or "")
    if not (scene_dir / "transforms_test.json").is_file():
        raise FileNotFoundError(f"--scene {scene_dir}: expected a scene folder with transforms_test.json, found none")
    view0 = load_split(scene_dir, "test").take([0])
    train_split = load_split(scene_dir, "train")
    camera = view0.camera(0)
    points = model.state.point_state(model.scene.points)
    rows = []
    for label, run in chosen:
        t0 = time.perf_counter()
        scene = PointScene.build(points, run.render, run.capacities)
        build_s = time.perf_counter() - t0
        bg = parse_background(run.background)
        near, far = run.sampler.near, run.sampler.far
        pool = build_pool(run.sampler, train_split, run.background)
        row = {"label": label, "preset": run.name, "tree_depth": int(scene.tree.depth),
               "frontier": [run.capacities.first_pass_frontier, run.capacities.frontier],
               "knn_k": run.render.kdtree.knn_k, "tree_build_s": round(build_s, 2)}
        row.update(time_steps(run, model, pool, scene, steps))

        cfg = run.render.replace(quadrature=at_test_time(run.render.quadrature))
        image = functools.partial(render_image, cfg, model.state.params, scene, camera, bg, near, far, progress=False)
        first, t_img = best_time(lambda image=image: jax.block_until_ready(image().rgb), repeats)
        report, _ = evaluate_split(run.render, model.state.params, scene, view0, run.background, near, far,
                                   progress=False)
        row.update({"ms_per_image": round(1e3 * t_img, 1), "image_compile_s": round(max(0.0, first - t_img), 2),
                    "psnr_view0": round(float(report["psnr"]), 2)})
        rows.append(row)
        log(f"{label}: depth {row['tree_depth']}, {row['ms_per_step']:.1f} ms/step of {row['batch_rays']} rays "
            f"(compile {row['step_compile_s']:.0f} s, {row['train_segments_lost']} segments lost), "
            f"{row['total_steps']} steps ~ {row['projected_train_min']:.1f} min; image {row['ms_per_image']:.0f} ms, "
            f"{row['psnr_view0']:.2f} dB")
    ref = next(r for r in rows if r["label"] == REFERENCE)
    for r in rows:
        r["step_ratio"] = round(r["ms_per_step"] / ref["ms_per_step"], 3)
        r["ray_ratio"] = round(r["us_per_ray"] / ref["us_per_ray"], 3)
        r["image_ratio"] = round(r["ms_per_image"] / ref["ms_per_image"], 3)
    dev = jax.devices()[0]
    return {"run": str(run_dir), "scene": str(scene_dir), "model_preset": model.run.name, "steps": steps,
            "repeats": repeats, "alive_points": int(np.asarray(points.alive).sum()),
            "device": {"platform": dev.platform, "kind": dev.device_kind},
            "machine": {"cpus": os.cpu_count(), "platform": platform.platform()}, "jax": jax.__version__, "rows": rows}


def markdown(res: dict) -> str:
    d = res["device"]
    L = [f"Presets on {d['kind']} ({d['platform']}, jax {res['jax']}), on the cloud and colour model of the "
         f"`{res['model_preset']}` run `{res['run']}` ({res['alive_points']} points): {res['steps']} training steps "
         f"after a compiling one, test view 0 rendered (best of {res['repeats']}). Ratios against `{REFERENCE}`; "
         "the projection is total steps x time per step (no point rounds, no evaluation).", "",
         "| setting | tree depth | frontier | K | rays / batch | ms / step | us / ray | step / ref | "
         "segments lost (capacity / budget) | first batch: segments / ray, rays filling the slots | steps | "
         "projected training (min) | ms / image | image / ref | PSNR view 0 (dB) |",
         "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in res["rows"]:
        first, width = r["frontier"]
        frontier = f"{width}" if first is None else f"{first} then {width}"
        L.append(f"| {r['label']} | {r['tree_depth']} | {frontier} | {r['knn_k']} | {r['batch_rays']} | "
                 f"{r['ms_per_step']:.1f} | {r['us_per_ray']:.2f} | {r['step_ratio']:.2f} | "
                 f"{r['lost_to_capacity']} / {r['lost_to_budget']} | {r['first_batch']['mean_segments']:.1f}, "
                 f"{r['first_batch']['rays_at_max_segments']} | "
                 f"{r['total_steps']} | {r['projected_train_min']:.1f} | {r['ms_per_image']:.0f} | "
                 f"{r['image_ratio']:.2f} | "
                 f"{r['psnr_view0']:.2f} |")
    return "\n".join(L) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--run", type=Path, required=True, help="a trained run directory (its cloud and colour model)")
    ap.add_argument("--scene", type=Path, help="the scene folder, if not the one the run recorded")
    ap.add_argument("--steps", type=int, default=20, help="timed training steps per preset")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--settings", nargs="+", metavar="LABEL", help="measure only these rows (and always `default`)")
    ap.add_argument("--quick", action="store_true", help="tiny and default only, 2 steps, 1 repeat (smoke test)")
    ap.add_argument("--out-dir", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    if not args.run.is_dir():
        raise SystemExit(f"--run {args.run}: expected a trained run directory, found nothing")
    if args.steps < 1:
        raise SystemExit(f"--steps: expected at least 1, found {args.steps}")
    res = run_bench(args.run, args.scene, 2 if args.quick else args.steps, 1 if args.quick else args.repeats,
                    args.quick, log=lambda s: print(s, file=sys.stderr, flush=True), only=args.settings)
    res["command"] = "python -m experiments.bench_presets " + " ".join(argv if argv is not None else sys.argv[1:])
    write_bench(args.out_dir, f"bench_presets_{device_tag()}", res, markdown(res))
    return 0


if __name__ == "__main__":
    import ne_jax

    ne_jax.setup(huge_pages=True)  # as `ne-jax` does: a host device per core, huge pages (restarts)
    raise SystemExit(main())

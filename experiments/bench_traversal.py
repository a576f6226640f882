"""The two-pass traversal against one pass at full width, on a trained model's cloud and test views.

    python -m experiments.bench_traversal --run RUN_DIR [--scene DIR] [--views 5] [--train-steps 50] [--quick]

A ray walks the K-D tree level by level with a frontier of ``Capacities.frontier`` nodes, and the
cost follows that width; most rays of a surface-like cloud need far fewer nodes per level. With
``Capacities.first_pass_frontier`` every ray is walked at a narrow width first and only the rays
that overflow it (at most ``retry_share`` of a call's rays) are walked again at full width. Per
setting, on all pixels of ``--views`` evenly spaced test views of the run's scene:

* ``intersect`` alone: rays per second, in chunks of the run's render chunk, against one pass at the
  run's own width (the reference, measured in the same process); the rays whose segments lose
  anything (frontier or segment overflow) and whether the segments equal the reference's bit for
  bit;
* ``render_image`` of test view 0 (best of ``--repeats`` after a compiling call): the time per image
  against the reference, and the largest pixel difference;
* ``--train-steps N`` training steps from the trained state on the same batches (the run's sampler
  on its training split, its packing budget as it ended): the time per step against the reference,
  the segments lost, and the
  largest difference of any parameter after the N steps (0: the same training).

The reference is measured twice: the second row is the run-to-run noise of the times and, on a GPU
(which does not repeat a computation bit for bit), of the pixels and parameters.

Writes ``experiments/results/bench_traversal.{json,md}`` (``--out-dir``; on an accelerator
``bench_traversal_<device>.{json,md}``); prints the table.
"""

from __future__ import annotations

import argparse
import functools
import os
import platform
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"

from experiments.common import best_time, device_tag, timed_steps  # noqa: E402
from experiments.common import write_results as write_bench  # noqa: E402


def settings(width: int, quick: bool) -> list[tuple[str, dict]]:
    """``(label, Capacities changes)``: the reference first, then narrower single passes (lossy)
    and two-pass walks of the same full width."""
    def two(w, share):
        return (f"two passes, {w} then {width}, retry share 1/{round(1 / share)}",
                dict(first_pass_frontier=w, retry_share=share))

    ref = (f"one pass, frontier {width} (reference)", {})
    if quick:
        return [ref, two(width // 4, 1.0)]
    out = [ref, (f"one pass, frontier {width} (the reference again: run-to-run noise)", {})]
    out += [(f"one pass, frontier {w} (lossy)", dict(frontier=w)) for w in (width // 4, width // 2)]
    out += [two(width // 8, 1 / 4), two(width // 4, 1 / 16), two(width // 4, 1 / 8), two(width // 4, 1 / 4),
            two(width // 2, 1 / 16)]
    return out


def train_steps(model, scene_dir: Path, capacities, steps: int) -> tuple[float, int, dict]:
    """``steps`` training steps from ``model``'s state with the traversal of ``capacities`` (the packing
    budget as the run ended): ``(s per step after the compiling first, segments lost, parameters
    after)``."""
    import jax

    from ne_jax.data.nerf_synthetic import load_split
    from ne_jax.train.sampler import build_pool, sample_batch
    from ne_jax.train.step import make_train_step

    run = model.run
    budget = model.scene.capacities.segments_per_ray  # as the run ended
    scene = model.scene.replace(capacities=capacities.replace(segments_per_ray=budget))
    step = make_train_step(run.train, run.train_render)
    pool = build_pool(run.sampler, load_split(scene_dir, "train"), run.background)
    key = jax.random.PRNGKey(0)
    batches = [sample_batch(run.sampler, pool, jax.random.fold_in(key, i), run.train_render.pixel_samples)
               for i in range(steps + 1)]
    state, per_step, _, lost = timed_steps(step, model.state, scene, batches)
    return per_step, lost.total, state.params


def run_bench(run_dir: Path, scene_dir: Path | None, views: int, repeats: int, quick: bool, steps: int = 0,
              log=print) -> dict:
    import jax
    import jax.numpy as jnp

    from ne_jax.data.nerf_synthetic import load_split, parse_background
    from ne_jax.data.rays import camera_rays
    from ne_jax.geometry.intersect import intersect
    from ne_jax.render.renderer import render_image
    from ne_jax.train.model import load_trained

    model = load_trained(run_dir)
    scene_dir = Path(scene_dir or model.scene_dir or "")
    if not (scene_dir / "transforms_test.json").is_file():
        raise FileNotFoundError(f"--scene {scene_dir}: expected a scene folder with transforms_test.json, found none")
    run, tree = model.run, model.scene.tree
    split = load_split(scene_dir, "test")
    near, far = run.sampler.near, run.sampler.far
    idx = np.linspace(0, split.num_views - 1, min(views, split.num_views)).round().astype(int)
    rays = [camera_rays(split.camera(int(i)), near, far) for i in idx]
    rays = jax.tree_util.tree_map(lambda *a: jnp.concatenate(a), *rays)
    chunk = min(run.render.chunk, rays.num_rays)
    n = rays.num_rays - rays.num_rays % chunk  # whole chunks: one compiled shape
    chunks = [jax.tree_util.tree_map(lambda a, s=s: a[s:s + chunk], rays) for s in range(0, n, chunk)]
    bg = parse_background(run.background)
    camera = split.camera(int(idx[0]))
    rows, ref_seg, ref_rgb, ref_params = [], None, None, None
    one_pass = run.capacities.replace(first_pass_frontier=None)  # the reference, whatever the run walked
    for label, changes in settings(one_pass.frontier, quick):
        cap = one_pass.replace(**changes)

        def walk(cap=cap):
            return [intersect(tree, c, run.render.kdtree, cap) for c in chunks]

        segs = jax.block_until_ready(walk())
        _, t_walk = best_time(lambda: jax.block_until_ready(walk()), repeats)
        fields = [np.concatenate([np.asarray(getattr(s, f)) for s in segs]) for f in ("t_lo", "t_hi", "node", "valid")]
        lost = int(sum(int(jnp.sum(s.lost().count > 0)) for s in segs))
        scene = model.scene.replace(capacities=cap)  # the run's starting packing budget, as it was measured
        image = functools.partial(render_image, run.render, model.state.params, scene, camera, bg, near, far,
                                  progress=False)
        first, t_img = best_time(lambda image=image: jax.block_until_ready(image().rgb), repeats)
        rgb = np.asarray(image().rgb)
        if steps and "frontier" not in changes:  # training: the reference and the two-pass walks
            t_step, lost_train, params = train_steps(model, scene_dir, cap, steps)
        if ref_seg is None:
            ref_seg, ref_rgb, ref_walk, ref_img = fields, rgb, t_walk, t_img
            if steps:
                ref_step, ref_params = t_step, params
        row = {"label": label, "changes": changes, "rays": n, "rays_per_s": round(n / t_walk),
               "walk_ratio": round(t_walk / ref_walk, 3), "rays_losing_segments": lost,
               "segments_equal_reference": all(np.array_equal(a, b) for a, b in zip(fields, ref_seg)),
               "ms_per_image": round(1e3 * t_img, 1), "image_ratio": round(t_img / ref_img, 3),
               "compile_s": round(max(0.0, first - t_img), 2), "max_abs_rgb_diff": float(np.abs(rgb - ref_rgb).max())}
        if steps and "frontier" not in changes:
            diff = jax.tree_util.tree_map(lambda a, b: float(jnp.max(jnp.abs(a - b))), params, ref_params)
            row.update({"ms_per_step": round(1e3 * t_step, 1), "step_ratio": round(t_step / ref_step, 3),
                        "train_segments_lost": lost_train,
                        "max_abs_param_diff": max(jax.tree_util.tree_leaves(diff))})
        rows.append(row)
        log(f"{label}: {row['rays_per_s']} rays/s ({row['walk_ratio']:.2f}x the time), {lost} rays losing segments, "
            f"segments equal: {row['segments_equal_reference']}; image {row['ms_per_image']:.0f} ms "
            f"({row['image_ratio']:.2f}x), max |drgb| {row['max_abs_rgb_diff']:.1e}"
            + (f"; training {row['ms_per_step']:.0f} ms/step ({row['step_ratio']:.2f}x), {row['train_segments_lost']} "
               f"segments lost, max |dparam| {row['max_abs_param_diff']:.1e}" if "ms_per_step" in row else ""))
    return {"run": str(run_dir), "scene": str(scene_dir), "preset": run.name, "views": [int(i) for i in idx],
            "chunk": chunk, "repeats": repeats, "train_steps": steps, "tree_depth": int(tree.depth),
            "alive_points": int(np.asarray(model.scene.points.alive).sum()),
            "machine": {"cpus": os.cpu_count(), "platform": platform.platform()}, "jax": jax.__version__,
            "device": {"platform": jax.devices()[0].platform, "kind": jax.devices()[0].device_kind}, "rows": rows}


def markdown(res: dict) -> str:
    L = [f"Traversal on the `{res['preset']}` model `{res['run']}` ({res['alive_points']} points, tree depth "
         f"{res['tree_depth']}): all pixels of test views {res['views']} in chunks of {res['chunk']} rays, and test "
         f"view {res['views'][0]} rendered whole (best of {res['repeats']} after a compiling call); "
         f"{res['train_steps']} training steps from the trained state on the same batches.", "",
         "| setting | rays / s | walk time / ref | rays losing segments | segments = ref | ms / image | image / ref | "
         "max abs RGB diff | ms / step | step / ref | training: segments lost | max abs param diff |",
         "|---|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in res["rows"]:
        train = (f"{r['ms_per_step']:.0f} | {r['step_ratio']:.2f} | {r['train_segments_lost']} | "
                 f"{r['max_abs_param_diff']:.1e}" if "ms_per_step" in r else "| | |")
        L.append(f"| {r['label']} | {r['rays_per_s']} | {r['walk_ratio']:.2f} | {r['rays_losing_segments']} | "
                 f"{'yes' if r['segments_equal_reference'] else 'no'} | {r['ms_per_image']:.0f} | "
                 f"{r['image_ratio']:.2f} | "
                 f"{r['max_abs_rgb_diff']:.1e} | {train} |")
    return "\n".join(L) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--run", type=Path, required=True, help="a trained run directory")
    ap.add_argument("--scene", type=Path, help="the scene folder, if not the one the run recorded")
    ap.add_argument("--views", type=int, default=5, help="test views walked (evenly spaced)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--train-steps", type=int, default=50, help="training steps per setting (0: none)")
    ap.add_argument("--quick", action="store_true", help="the reference and one two-pass setting, 1 view (smoke test)")
    ap.add_argument("--out-dir", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    if not args.run.is_dir():
        raise SystemExit(f"--run {args.run}: expected a trained run directory, found nothing")
    res = run_bench(args.run, args.scene, 1 if args.quick else args.views, 1 if args.quick else args.repeats,
                    args.quick, min(args.train_steps, 2) if args.quick else args.train_steps,
                    log=lambda s: print(s, file=sys.stderr, flush=True))
    res["command"] = "python -m experiments.bench_traversal " + " ".join(argv if argv is not None else sys.argv[1:])
    tag = device_tag()
    write_bench(args.out_dir, "bench_traversal" if tag == "cpu" else f"bench_traversal_{tag}", res, markdown(res))
    return 0


if __name__ == "__main__":
    import ne_jax

    ne_jax.setup(huge_pages=True)  # as `ne-jax` does: a host device per core, huge pages (restarts)
    raise SystemExit(main())

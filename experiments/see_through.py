"""Why rendered pixels see through a surface, and what the K-D boxes' margin does about it.

A ``see_through`` pixel (:mod:`ne_jax.eval.regions`) is rendered behind the surface its neighbours
stop at: dark or bright dots over a surface ("speckle"). For a trained model this experiment

1. takes the see-through pixels of some test views and walks their rays through the model's tree
   again: how many have a segment within one point spacing of their neighbours' (median) depth, and
   how far the place where the ray crosses that surface lies from the nearest point, against ordinary
   object pixels. No segment there means the ray passed between the boxes of the surface's voxels
   (the boxes are the points' bounding boxes grown by a margin, ``KDTreeConfig.margin_factor``);
2. renders the same views with the tree rebuilt at other margins (zero-shot: the model is not
   trained again): PSNR, see-through pixels and their share of the squared error, segments per
   object ray, seconds per image.

    python -m experiments.see_through --run RUN_DIR SCENE_DIR [--views 0 1] [--margins 1.0 1.5 2.0] --out NAME

Writes ``experiments/results/see_through_<NAME>.{json,md}``.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

from experiments.common import RESULTS, command, write_results

OBJECT_ALPHA = 0.5


def crossing_report(model, split, views: list[int], depths: dict, labels: dict) -> dict:
    """Step 1 of the module docstring, over ``views`` (their depth maps and region labels)."""
    import jax
    from scipy.spatial import cKDTree

    from ne_jax.data.rays import camera_rays
    from ne_jax.eval.regions import REGIONS, neighbour_depth
    from ne_jax.geometry.intersect import intersect

    tree, cfg = model.scene.tree, model.run.render.kdtree
    spacing = float(tree.spacing)
    points = model.scene.points
    kd = cKDTree(np.asarray(points.xyz)[np.asarray(points.alive)])
    see = REGIONS.index("see_through")
    rng = np.random.default_rng(0)
    covered, through, gap, ordinary = 0, 0, [], []
    for v in views:
        rays = camera_rays(split.camera(v), model.near, model.far)
        depth = depths[v].reshape(-1)
        near = neighbour_depth(depths[v]).reshape(-1)
        label = labels[v].reshape(-1)
        idx = np.flatnonzero(label == see)
        origin, direction = np.asarray(rays.origin), np.asarray(rays.direction)
        if idx.size:
            sub = jax.tree_util.tree_map(lambda a, i=idx: a[i], rays)
            seg = jax.device_get(intersect(tree, sub, cfg, model.scene.capacities))
            t = near[idx][:, None]
            hit = seg.valid & (seg.t_lo - spacing <= t) & (t <= seg.t_hi + spacing)
            covered += int(hit.any(-1).sum())
            through += idx.size
            gap.append(kd.query(origin[idx] + near[idx, None] * direction[idx])[0])
        flat = np.flatnonzero(np.isin(label, [REGIONS.index("flat"), REGIONS.index("texture")]))
        pick = rng.choice(flat, min(500, flat.size), replace=False)
        ordinary.append(kd.query(origin[pick] + depth[pick, None] * direction[pick])[0])
    gap = np.concatenate(gap) / spacing if gap else np.zeros(0)
    ordinary = np.concatenate(ordinary) / spacing
    q = lambda a: [round(float(x), 2) for x in np.percentile(a, [25, 50, 75])] if a.size else None  # noqa: E731
    return {"see_through_pixels": through, "with_a_segment_at_the_surface": covered,
            "crossing_to_nearest_point_spacings_quartiles": q(gap),
            "ordinary_pixels_to_nearest_point_spacings_quartiles": q(ordinary), "spacing": spacing}


def margin_row(model, split, views: list[int], margin: float | None) -> tuple[dict, dict, dict]:
    """Render ``views`` with the tree rebuilt at ``margin`` (``None``: the model's own tree). Returns
    ``(row, depths, labels)``."""
    from ne_jax.data.nerf_synthetic import composite, parse_background
    from ne_jax.eval.metrics import psnr
    from ne_jax.eval.regions import REGIONS, label_regions, region_errors
    from ne_jax.render.renderer import PointScene

    if margin is not None:
        render = dataclasses.replace(model.run.render,
                                     kdtree=dataclasses.replace(model.run.render.kdtree, margin_factor=margin))
        model = model.replace(run=dataclasses.replace(model.run, render=render),
                              scene=PointScene.build(model.scene.points, render, model.scene.capacities))
    bg = np.asarray(parse_background(model.background), np.float32)
    scores, seconds, segments, depths, labels, preds, truths = [], [], [], {}, {}, [], []
    for v in views:
        truth = composite(split.images[v:v + 1], bg)[0].astype(np.float32)
        alpha = np.asarray(split.images[v][..., 3])
        t0 = time.perf_counter()
        out = model.render_image(split.camera(v))
        pred = np.asarray(out.rgb, np.float32)
        seconds.append(time.perf_counter() - t0)
        depths[v] = np.asarray(out.depth, np.float32)
        labels[v] = label_regions(truth, alpha, pred, bg, depth=depths[v])
        scores.append(float(psnr(pred, truth)))
        segments.append(float(np.asarray(out.num_segments)[alpha >= OBJECT_ALPHA].mean()))
        preds.append(pred)
        truths.append(truth)
    errors = region_errors(np.stack([labels[v] for v in views]), np.stack(preds), np.stack(truths))
    see = REGIONS.index("see_through")
    row = {"margin_factor": float(model.run.render.kdtree.margin_factor), "psnr": round(float(np.mean(scores)), 2),
           "psnr_per_view": [round(p, 2) for p in scores],
           "see_through_pixels": int(sum((labels[v] == see).sum() for v in views)),
           "see_through_error_share": round(errors["see_through"]["error"], 4),
           "segments_per_object_ray": round(float(np.mean(segments)), 2),
           # the first view compiles the renderer (a new tree: new capacities may compile again)
           "seconds_per_image": round(float(np.median(seconds[1:] if len(seconds) > 1 else seconds)), 2)}
    return row, depths, labels


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", nargs=2, required=True, metavar=("RUN_DIR", "SCENE_DIR"),
                        help="a trained model's run directory and the scene folder of its test views")
    parser.add_argument("--views", type=int, nargs="+", default=[0, 1, 2], help="test views to render")
    parser.add_argument("--margins", type=float, nargs="*", default=[1.5, 2.0],
                        help="other box margins to render zero-shot (KDTreeConfig.margin_factor)")
    parser.add_argument("--out", required=True, help="results file stem: see_through_<out>")
    args = parser.parse_args(argv)

    from ne_jax.config_json import config_key
    from ne_jax.data.nerf_synthetic import load_split
    from ne_jax.train.model import load_trained

    t0 = time.perf_counter()
    model = load_trained(args.run[0])
    split = load_split(args.run[1], "test")
    bad = [v for v in args.views if not 0 <= v < split.num_views]
    if bad:
        raise SystemExit(f"--views: expected test views 0..{split.num_views - 1} of {args.run[1]}, found {bad}")
    own, depths, labels = margin_row(model, split, args.views, None)
    crossing = crossing_report(model, split, args.views, depths, labels)
    print(f"own tree: {own}\nsee-through rays: {crossing}", flush=True)
    rows = [own]
    for m in args.margins:
        rows.append(margin_row(model, split, args.views, m)[0])
        print(f"margin {m}: {rows[-1]}", flush=True)
    res = {"what": "see-through pixels: their rays, and the box margin rendered zero-shot",
           "command": command("see_through", argv), "run": args.run[0], "scene_dir": args.run[1],
           "config_key": config_key(model.run), "views": args.views, "crossing": crossing, "margins": rows,
           "seconds": round(time.perf_counter() - t0, 1)}
    c = crossing
    md = (f"See-through pixels of `{args.run[0]}` (config key {res['config_key']}), test views {args.views}; "
          f"`{res['command']}`.\n\n"
          f"Of {c['see_through_pixels']} see-through pixels, {c['with_a_segment_at_the_surface']} have a segment "
          f"within one point spacing ({c['spacing']:.5f}) of their neighbours' depth. Where their ray crosses "
          f"that surface, the nearest point is {c['crossing_to_nearest_point_spacings_quartiles']} spacings away "
          f"(quartiles), against {c['ordinary_pixels_to_nearest_point_spacings_quartiles']} for ordinary object "
          "pixels.\n\n"
          "| margin factor | tree | PSNR | see-through pixels | their share of the squared error | "
          "segments per object ray | s / image |\n|---:|---|---:|---:|---:|---:|---:|\n"
          + "\n".join(f"| {r['margin_factor']:g} | {'trained' if i == 0 else 'rebuilt'} | {r['psnr']:.2f} | "
                      f"{r['see_through_pixels']} | {100 * r['see_through_error_share']:.0f}% | "
                      f"{r['segments_per_object_ray']:.1f} | {r['seconds_per_image']:.2f} |"
                      for i, r in enumerate(rows)) + "\n")
    write_results(RESULTS, f"see_through_{args.out}", res, md)


if __name__ == "__main__":
    import ne_jax

    ne_jax.setup(huge_pages=True)  # as `ne-jax` does: a host device per core, huge pages (restarts)
    main()

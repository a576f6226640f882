"""Accuracy against time for the renderer's numerical knobs (issue 7).

    python -m experiments.accuracy_vs_time --study numerics           # part 1: a few minutes on 2 CPU cores
    python -m experiments.accuracy_vs_time --study numerics --quick   # reduced sizes (the smoke test)
    python -m experiments.accuracy_vs_time --study image --run RUN_DIR [--edit bend] [--scene DIR] [--quick]
                                          [--test-views N] [--timing-passes P]
                                                                      # part 2: a trained model and its edit
                                                                      # (experiments/accuracy_vs_time_image.py)
    python -m experiments.accuracy_vs_time --study training --scene DIR [--preset tiny] [--runs DIR] [--quick]
                                          [--candidates full|short] [--train-only I ...] [--finished-only]
                                                                      # part 3: models trained with each setting
                                                                      # (experiments/accuracy_vs_time_training.py)

``--study numerics`` needs no training. Three studies, each measured against an exact reference:

* **quadrature** — the segment mean of a field on ``[0, 1]`` (one segment in segment units) by every
  rule of ``ne_jax.render.quadrature`` (the library's host weights, samples at the library's
  fractions) against the analytic mean, for ``s`` samples per segment, on three kinds of field:
  ``smooth`` (sums of broad Gaussians), ``sharp`` (sums of narrow Gaussians, width 2-5 % of the
  segment) and ``step`` (a jump at a random place). Errors in float64 numpy, mean and max of
  ``|error|`` over random fields (RMS for the stochastic rule, which is random); the convergence order
  is the least-squares slope of ``log error`` against ``log h`` (``h = 1/(s-1)``, the sample spacing;
  ``1/s``, the bin width, for the stochastic rule) over ``s >= 8``. Time: the jitted
  ``level_samples`` + field evaluation + ``integrate`` of ``10^5`` segments in float32.
* **knn** — the candidate-set KNN of ``ne_jax.geometry.knn`` against exact KNN (scipy's
  ``cKDTree``) on a surface cloud (the ``glossy`` benchmark scene's surface samples) at the real
  ``(sample, node)`` pairs of camera rays (``intersect``, 8 evenly spaced samples per segment, as the
  renderer samples the bottom level), for several candidate-set sizes and ``K``: recall, and the
  difference of the interpolated values (random ``N(0, 1)`` per-point values and a smooth field of
  the position) between candidate and exact neighbours, plus the exact neighbours' own error on the
  smooth field. Time: the renderer's fused KNN + quadrature step (``knn_integrate``, 32 feature
  channels) per ``10^6`` samples, candidate mode and ``exact=True`` (brute force) on the same samples.
* **precision** — the same randomly initialised model (same points, features and colour-model
  weights) rendered in float32 and in float64 (each in its own process; float64 needs
  ``JAX_ENABLE_X64=1`` before anything is traced): max and mean differences and the time ratio.

Timings are the minimum over repeats (``block_until_ready``; the first, compiling call excluded and
reported separately). The machine this was written on has 2 CPU cores shared with other jobs, so the
timings are noisy; ratios measured in one process are more trustworthy than absolute values.

Writes ``accuracy_vs_time.json``, ``accuracy_vs_time_{quadrature,knn,precision}.png`` and
``accuracy_vs_time_numerics.md`` to ``--out-dir`` (default ``experiments/results``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.special import erf

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent

RESULTS = HERE / "results"
SHARED_NOTE = ("2 CPU cores shared with other jobs: timings are noisy (minimum over repeats, "
               "compile excluded); ratios from one process are more reliable than absolute values")
RENDER_S = (8, 11, 16, 22)
"""The renderer's samples per level (default preset), marked on the plots."""


@dataclasses.dataclass(frozen=True)
class Sizes:
    """Problem sizes of one run (``full`` for the committed results, ``quick`` for the smoke test)."""

    s_values: tuple[int, ...]
    num_fields: int
    time_segments: int
    knn_points: int
    knn_res: int
    knn_segments: int
    knn_time_segments: int
    knn_exact_segments: int
    candidate_sizes: tuple[int, ...]
    ks: tuple[int, ...]
    render_points: int
    render_res: int
    render_views: int
    render_preset: str
    repeats: int
    parallel_workers: bool = False
    """Run the float32 and float64 render processes at the same time, and alongside the other studies
    (quick mode only: the timings are then not meaningful)."""

    @classmethod
    def full(cls) -> Sizes:
        return cls(s_values=(2, 3, 4, 6, 8, 11, 16, 22, 32, 45, 64), num_fields=4000, time_segments=100_000,
                   knn_points=50_000, knn_res=96, knn_segments=8192, knn_time_segments=4096,
                   knn_exact_segments=256, candidate_sizes=(64, 96, 128, 192, 256), ks=(8, 16, 32, 64),
                   render_points=50_000, render_res=64, render_views=2, render_preset="default", repeats=5)

    @classmethod
    def quick(cls) -> Sizes:
        return cls(s_values=(2, 4, 8, 16, 22), num_fields=200, time_segments=2000,
                   knn_points=3000, knn_res=24, knn_segments=256, knn_time_segments=128,
                   knn_exact_segments=16, candidate_sizes=(64, 96), ks=(8,),
                   render_points=2000, render_res=16, render_views=1, render_preset="tiny", repeats=1,
                   parallel_workers=True)


def best_time(fn, repeats: int) -> tuple[float, float]:
    """``(first_call_s, best_s)``: the first call (compiles) and the minimum of ``repeats`` more."""
    import jax

    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - t0)
    return first, best


# ----------------------------------------------------------------------------------- quadrature


FIELDS = {
    "smooth": "sum of 3 Gaussians, widths U(0.15, 0.4), centres U(-0.2, 1.2), amplitudes U(0.5, 1)",
    "sharp": "sum of 3 Gaussians, widths U(0.02, 0.05), centres U(0.05, 0.95), amplitudes U(0.5, 1)",
    "step": "a unit step at U(0, 1)",
}


def random_fields(kind: str, n: int, seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    if kind == "step":
        return {"kind": kind, "c": rng.uniform(0.0, 1.0, (n, 1))}
    lo, hi, c_lo, c_hi = (0.15, 0.4, -0.2, 1.2) if kind == "smooth" else (0.02, 0.05, 0.05, 0.95)
    return {"kind": kind, "a": rng.uniform(0.5, 1.0, (n, 3)), "c": rng.uniform(c_lo, c_hi, (n, 3)),
            "w": rng.uniform(lo, hi, (n, 3))}


def field_values(f: dict, u, xp=np):
    """``f(u)`` for fields ``[n]`` at positions ``u [n, s]`` (``xp``: numpy or jax.numpy)."""
    if f["kind"] == "step":
        return (u > xp.asarray(f["c"], u.dtype)).astype(u.dtype)
    a, c, w = (xp.asarray(f[k], u.dtype)[:, None, :] for k in "acw")
    return xp.sum(a * xp.exp(-0.5 * ((u[..., None] - c) / w) ** 2), axis=-1)


def field_means(f: dict) -> np.ndarray:
    """Analytic mean over ``[0, 1]`` of each field ``[n]`` (float64)."""
    if f["kind"] == "step":
        return 1.0 - f["c"][:, 0]
    a, c, w = f["a"], f["c"], f["w"]
    r = w * math.sqrt(2.0)
    return np.sum(a * w * math.sqrt(math.pi / 2.0) * (erf((1.0 - c) / r) - erf(-c / r)), axis=1)


def fit_order(s_values, errors, rule: str, s_min: int = 8, floor: float = 1e-13) -> float | None:
    """Least-squares slope ``p`` of ``log err = p log h + b`` over ``s >= s_min`` (and errors above the
    float64 floor); ``h = 1/(s-1)``, or ``1/s`` for the stochastic rule."""
    s = np.asarray(s_values, float)
    e = np.asarray(errors, float)
    keep = (s >= s_min) & (e > floor)
    if keep.sum() < 2:
        return None
    h = 1.0 / (s if rule == "stochastic" else s - 1.0)
    return float(np.polyfit(np.log(h[keep]), np.log(e[keep]), 1)[0])


def quadrature_errors(rule: str, s: int, fields: dict, truth: np.ndarray, seed: int) -> np.ndarray:
    """Signed errors ``[n]`` of ``rule`` with ``s`` samples (float64; stochastic positions from the
    library's ``sample_fractions`` with a fresh key per field)."""
    import jax

    from ne_jax.render.quadrature import quadrature_weights, sample_fractions

    n = truth.shape[0]
    w = quadrature_weights(s, rule)
    if rule == "stochastic":
        u = np.asarray(sample_fractions(s, rule, jax.random.key(seed), (n,)), np.float64)
    else:
        u = np.broadcast_to(np.linspace(0.0, 1.0, s), (n, s))  # the library's fractions, in float64
    return field_values(fields, u) @ w - truth


def time_quadrature(rule: str, s: int, fields: dict, segments: int, repeats: int) -> tuple[float, float]:
    """``(compile_s, ms per 10^5 segments)`` of sample placement + field evaluation + weighted sum
    (float32, jitted) for ``segments`` segments of random lengths."""
    import jax
    import jax.numpy as jnp

    from ne_jax.render.quadrature import QuadratureConfig, integrate, level_samples

    cfg = QuadratureConfig(rule=rule, samples_per_level=(s,))
    rng = np.random.default_rng(7)
    t_lo = jnp.asarray(rng.uniform(0.0, 1.0, segments), jnp.float32)
    t_hi = t_lo + jnp.asarray(rng.uniform(0.5, 1.5, segments), jnp.float32)
    lvl = jnp.zeros(segments, jnp.int32)
    f = {k: (np.resize(v, (segments, v.shape[1])) if isinstance(v, np.ndarray) else v) for k, v in fields.items()}

    @jax.jit
    def run(t_lo, t_hi, lvl, key):
        t, w = level_samples(cfg, t_lo, t_hi, lvl, key)
        y = field_values(f, t - t_lo[:, None], jnp)
        return integrate(y[..., None], w)[..., 0]

    first, best = best_time(lambda: run(t_lo, t_hi, lvl, jax.random.key(0)), repeats)
    return first - best, 1e3 * best * 1e5 / segments


def quadrature_study(sz: Sizes) -> dict:
    from ne_jax.render.quadrature import RULES

    fields = {k: random_fields(k, sz.num_fields, seed=i) for i, k in enumerate(FIELDS)}
    truth = {k: field_means(f) for k, f in fields.items()}
    out = {"s_values": list(sz.s_values), "fields": FIELDS, "num_fields": sz.num_fields,
           "error_metric": "mean and max |error| over the fields (stochastic: RMS and max over fields, "
                           "one random draw each); segment means in float64",
           "order_fit": "slope of log(error) vs log(h) over s >= 8; h = 1/(s-1) (stochastic: 1/s)",
           "time": f"jitted float32 level_samples + smooth-field evaluation + integrate, ms per 10^5 segments "
                   f"(measured on {sz.time_segments} segments, min of {sz.repeats})",
           "rules": {}}
    for rule in RULES:
        row = {"error": {}, "order": {}}
        for kind, f in fields.items():
            errs = [quadrature_errors(rule, s, f, truth[kind], seed=1000 + s) for s in sz.s_values]
            central = [float(np.sqrt(np.mean(e ** 2))) if rule == "stochastic" else float(np.mean(np.abs(e)))
                       for e in errs]
            row["error"][kind] = {"mean_abs" if rule != "stochastic" else "rms": central,
                                  "max_abs": [float(np.max(np.abs(e))) for e in errs]}
            row["order"][kind] = fit_order(sz.s_values, central, rule)
        times = [time_quadrature(rule, s, fields["smooth"], sz.time_segments, sz.repeats) for s in sz.s_values]
        row["compile_s"] = [round(t[0], 3) for t in times]
        row["ms_per_1e5_segments"] = [round(t[1], 3) for t in times]
        out["rules"][rule] = row
        print(f"quadrature {rule}: orders {row['order']}", file=sys.stderr, flush=True)
    return out


def quadrature_error(q: dict, rule: str, kind: str) -> list[float]:
    e = q["rules"][rule]["error"][kind]
    return e["rms"] if "rms" in e else e["mean_abs"]


# ------------------------------------------------------------------------------------------ KNN


def glossy_points(n: int, seed: int = 0):
    from ne_jax.benchmark import scenes as S

    smp = S.surface_samples(S.get_scene("glossy", 1.0), n, seed=seed)
    return smp["xyz"].astype(np.float32), smp["normal"].astype(np.float32)


def orbit_rays(res: int, views: int, dtype=np.float32):
    """Pixel-centre rays of ``views`` orbit cameras of the benchmark scenes, in ``dtype``."""
    import jax.numpy as jnp

    from ne_jax.data import cameras
    from ne_jax.data.rays import Rays, pixel_centers, rays_through_pixels

    focal = 0.5 * res / math.tan(0.5 * cameras.CAMERA_ANGLE_X)
    pix = jnp.asarray(pixel_centers(res, res), dtype)
    parts = [rays_through_pixels(jnp.asarray(c2w, dtype), jnp.asarray(focal, dtype), jnp.asarray(focal, dtype),
                                 jnp.asarray(0.5 * res, dtype), jnp.asarray(0.5 * res, dtype), pix,
                                 cameras.NEAR, cameras.FAR)
             for c2w in cameras.orbit_cameras(views)]
    def cat(name):
        return jnp.concatenate([getattr(r, name) for r in parts])
    return Rays(origin=cat("origin"), direction=cat("direction"), near=cat("near"), far=cat("far"))


def smooth_point_field(xyz: np.ndarray) -> np.ndarray:
    """A smooth scalar field of the position (about one period per scene unit)."""
    x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    return (np.sin(4.0 * x + 1.0) * np.cos(3.0 * y) + 0.5 * np.sin(5.0 * z)).astype(np.float32)


def hit_fraction(idx: np.ndarray, ref: np.ndarray, chunk: int = 4096) -> np.ndarray:
    """Per row, the fraction of ``ref``'s K indices found in ``idx`` (both ``[N, K]``), in chunks."""
    k = ref.shape[1]
    return np.concatenate([(idx[a:a + chunk, :, None] == ref[a:a + chunk, None, :]).any(-1).sum(-1) / k
                           for a in range(0, idx.shape[0], chunk)])


def knn_study(sz: Sizes) -> dict:
    import jax
    import jax.numpy as jnp
    from scipy.spatial import cKDTree

    from ne_jax.geometry import (
        KDTreeConfig,
        Neighbors,
        PointState,
        build_tree,
        interpolate,
        intersect_checked,
        knn_weights,
    )
    from ne_jax.geometry.knn import knn_integrate, knn_interpolate
    from ne_jax.render.quadrature import quadrature_weights, sample_positions

    xyz, normal = glossy_points(sz.knn_points)
    n = xyz.shape[0]
    alive = np.ones(n, bool)
    rng = np.random.default_rng(3)
    state = PointState.from_numpy(xyz, feature=rng.normal(size=(n, 32)).astype(np.float32), normal=normal)
    state = state.replace(conf_logit=jnp.asarray(rng.normal(1.0, 1.0, n), jnp.float32))
    values = {"random": jnp.asarray(rng.normal(size=(n, 8)), jnp.float32),
              "smooth": jnp.asarray(smooth_point_field(xyz)[:, None])}

    # (sample, node) pairs of camera rays: the tree topology does not depend on the candidate sets,
    # so one traversal serves every candidate size (same heap indices, same samples).
    base = KDTreeConfig()
    tree0 = build_tree(xyz, alive, base)
    seg, _ = intersect_checked(tree0, orbit_rays(sz.knn_res, 4), base)
    r_idx, m_idx = np.nonzero(np.asarray(seg.valid))
    pick = np.random.default_rng(0).permutation(r_idx.size)[: sz.knn_segments]
    r_idx, m_idx = r_idx[pick], m_idx[pick]
    rays = orbit_rays(sz.knn_res, 4)
    o, d = np.asarray(rays.origin)[r_idx], np.asarray(rays.direction)[r_idx]
    s = 8
    t = np.asarray(sample_positions(jnp.asarray(np.asarray(seg.t_lo)[r_idx, m_idx]),
                                    jnp.asarray(np.asarray(seg.t_hi)[r_idx, m_idx]), s))
    points = jnp.asarray((o[:, None, :] + t[..., None] * d[:, None, :]).astype(np.float32))  # [B, s, 3]
    nodes = jnp.asarray(np.asarray(seg.node)[r_idx, m_idx].astype(np.int32))
    level = np.repeat((tree0.depth - 1) - np.asarray(seg.level)[r_idx, m_idx], s)  # 0 = bottom level, per sample
    b = points.shape[0]
    flat = np.asarray(points).reshape(-1, 3)
    kmax = max(sz.ks)
    ex_dist, ex_idx = cKDTree(xyz).query(flat, k=kmax, workers=-1)
    truth_smooth = smooth_point_field(flat)
    w_seg = jnp.broadcast_to(jnp.asarray(quadrature_weights(s, "hermite"), jnp.float32), (b, s))
    feat = {"feature": state.feature}

    out = {"num_points": n, "segments": int(b), "samples": int(b * s), "samples_per_segment": s,
           "cloud": "glossy benchmark scene, area-uniform surface samples",
           "rays": f"4 orbit views at {sz.knn_res}x{sz.knn_res}, segments of intersect (default tree), "
                   "8 evenly spaced samples each",
           "reference": "scipy cKDTree exact K nearest; the same softmax(log conf - log(dist + eps)) weights",
           "time": "knn_integrate (KNN + interpolation of 32 feature channels + quadrature, the renderer's "
                   f"fused step), ms per 10^6 samples (candidate mode on {sz.knn_time_segments * s} samples, "
                   f"exact mode on {sz.knn_exact_segments * s}; min of {sz.repeats})",
           "rows": [], "exact": []}
    tb, eb = min(sz.knn_time_segments, b), min(sz.knn_exact_segments, b)
    tree = None
    for kc in sz.candidate_sizes:
        tree = build_tree(xyz, alive, base.replace(candidate_min=kc))
        for k in sz.ks:
            if k > kc:
                continue
            cfg = base.replace(candidate_min=kc, knn_k=k)
            interp, nb = knn_interpolate(state, tree, points, nodes, cfg, False, values)
            idx = np.asarray(nb.index).reshape(-1, k)
            ref = ex_idx[:, :k]
            hits = hit_fraction(idx, ref)
            eps = jnp.float32(cfg.knn_eps_factor * float(tree.spacing))
            ref_valid = jnp.ones(ref.shape, bool)
            ref_nb = Neighbors(index=jnp.asarray(ref, jnp.int32), dist=jnp.asarray(ex_dist[:, :k], jnp.float32),
                               valid=ref_valid, weight=knn_weights(state.conf_logit[ref],
                                                                   jnp.asarray(ex_dist[:, :k], jnp.float32),
                                                                   ref_valid, eps))
            ref_interp = interpolate(ref_nb, values)
            d_rand = np.abs(np.asarray(interp["random"]).reshape(-1, 8) - np.asarray(ref_interp["random"]))
            d_smooth = np.abs(np.asarray(interp["smooth"]).reshape(-1) - np.asarray(ref_interp["smooth"])[:, 0])
            e_smooth = np.abs(np.asarray(ref_interp["smooth"])[:, 0] - truth_smooth)
            def run(tree=tree, cfg=cfg):
                return knn_integrate(state, tree, points[:tb], nodes[:tb], w_seg[:tb], feat, cfg)
            first, best = best_time(run, sz.repeats)
            row = {"candidates": cfg.num_candidates, "k": k, "recall": float(hits.mean()),
                   "recall_p01": float(np.quantile(hits, 0.01)), "exact_fraction": float((hits == 1).mean()),
                   "diff_random_mean": float(d_rand.mean()), "diff_random_max": float(d_rand.max()),
                   "diff_smooth_mean": float(d_smooth.mean()), "diff_smooth_max": float(d_smooth.max()),
                   "exact_smooth_err_mean": float(e_smooth.mean()),
                   "recall_by_level": {str(lv): float(hits[level == lv].mean()) for lv in np.unique(level)},
                   "samples_by_level": {str(lv): int((level == lv).sum()) for lv in np.unique(level)},
                   "ms_per_1e6_samples": round(1e3 * best * 1e6 / (tb * s), 1), "compile_s": round(first - best, 2)}
            out["rows"].append(row)
            print(f"knn Kc={kc} K={k}: recall {row['recall']:.4f}, {row['ms_per_1e6_samples']} ms/1e6",
                  file=sys.stderr, flush=True)
    # exact mode: cost on the same samples, and its recall against scipy (a correctness check)
    for k in sz.ks:
        cfg = base.replace(knn_k=k)
        nb = jax.jit(lambda p, cfg=cfg: knn_interpolate(state, tree0, p, None, cfg, True, values)[1])(points[:eb])
        idx = np.asarray(nb.index).reshape(-1, k)
        ref = ex_idx[: eb * s, :k]
        rec = float(hit_fraction(idx, ref).mean())
        def run(cfg=cfg):
            return knn_integrate(state, tree0, points[:eb], nodes[:eb], w_seg[:eb], feat, cfg, True)
        first, best = best_time(run, sz.repeats)
        out["exact"].append({"k": k, "recall_vs_scipy": rec,
                             "ms_per_1e6_samples": round(1e3 * best * 1e6 / (eb * s), 1),
                             "compile_s": round(first - best, 2)})
        print(f"knn exact K={k}: {out['exact'][-1]}", file=sys.stderr, flush=True)
    return out


# ------------------------------------------------------------------------------------ precision


def make_model(sz: Sizes, path: str) -> None:
    """The precision study's model, made once in float32 and saved to ``path`` for both render processes:
    the glossy scene's surface samples, features ``0.5 N(0, 1)`` and the colour-model weights
    (``init_color_model``, key 1) as flat leaves."""
    import jax

    from ne_jax.render.shading import init_color_model
    from ne_jax.train.run import get_run_preset

    xyz, normal = glossy_points(sz.render_points)
    feat = (0.5 * np.random.default_rng(1).normal(size=(xyz.shape[0], 32))).astype(np.float32)
    cfg = get_run_preset(sz.render_preset).render
    init = jax.jit(init_color_model, static_argnums=0)  # compiling is faster than flax's eager init
    leaves = jax.tree_util.tree_leaves(init(cfg.shading, jax.random.key(1)))
    np.savez(path, xyz=xyz, normal=normal, feature=feat, **{f"param_{i}": np.asarray(x) for i, x in enumerate(leaves)})


def render_worker(dtype_name: str, sz: Sizes, model_npz: str, out_npz: str) -> None:
    """Render the model in ``model_npz`` in ``dtype_name`` (the process's x64 flag must already match)
    and save the outputs and timings to ``out_npz``."""
    import jax
    import jax.numpy as jnp

    from ne_jax.geometry.points import PointState
    from ne_jax.render.renderer import PointScene, render_chunked
    from ne_jax.render.shading import init_color_model

    dtype = np.dtype(dtype_name)
    if dtype == np.float64 and not jax.config.jax_enable_x64:
        raise RuntimeError("float64 rendering needs JAX_ENABLE_X64=1")
    with np.load(model_npz) as z:
        model = {k: z[k] for k in z.files}
    pts = PointState.from_numpy(model["xyz"].astype(dtype), feature=model["feature"].astype(dtype),
                                normal=model["normal"].astype(dtype), dtype=dtype)
    pts = pts.replace(conf_logit=jnp.full(pts.conf_logit.shape, 2.0, dtype))
    from ne_jax.train.run import get_run_preset

    preset = get_run_preset(sz.render_preset)
    cfg = preset.render
    t0 = time.perf_counter()
    scene = PointScene.build(pts, cfg, preset.capacities)
    build_s = time.perf_counter() - t0
    treedef = jax.tree_util.tree_structure(jax.eval_shape(lambda: init_color_model(cfg.shading, jax.random.key(1))))
    leaves = [model[f"param_{i}"] for i in range(treedef.num_leaves)]
    checksum = float(sum(np.abs(x.astype(np.float64)).sum() for x in leaves))
    params = jax.tree_util.tree_unflatten(treedef, [jnp.asarray(x, dtype) for x in leaves])
    rays = orbit_rays(sz.render_res, sz.render_views, dtype)
    bg = jnp.ones(3, dtype)
    def render():
        return render_chunked(cfg, params, scene, rays, bg, progress=False)
    out = render()  # settles capacity growth
    first, best = best_time(render, sz.repeats)
    np.savez(out_npz, rgb=np.asarray(out.rgb), opacity=np.asarray(out.opacity), depth=np.asarray(out.depth),
             num_segments=np.asarray(out.num_segments), lost=np.asarray(out.lost.count),
             checksum=checksum, best_s=best, first_s=first, build_s=build_s, depth_tree=scene.tree.depth,
             dtype=str(out.rgb.dtype))


def start_precision(sz: Sizes) -> dict:
    """Write the model and start the float32 and float64 render processes: one after the other (each
    timed alone), or both at once with ``sz.parallel_workers``. Returns a handle for ``precision_study``."""
    tmp = tempfile.mkdtemp(prefix="accuracy_vs_time_")
    model = os.path.join(tmp, "model.npz")
    make_model(sz, model)
    procs = {}
    for name in ("float32", "float64"):
        path = os.path.join(tmp, f"{name}.npz")
        env = dict(os.environ, JAX_ENABLE_X64="1" if name == "float64" else "0")
        cmd = [sys.executable, str(Path(__file__).resolve()), "--render-worker", name, model, path,
               "--sizes-json", json.dumps(dataclasses.asdict(sz))]
        procs[name] = (subprocess.Popen(cmd, env=env, cwd=str(ROOT)), path)
        if not sz.parallel_workers:
            procs[name][0].wait()
    return {"tmp": tmp, "procs": procs}


def precision_study(sz: Sizes, handle: dict | None = None) -> dict:
    """float32 against float64 renders of one model (``handle``: from ``start_precision``, started
    earlier; by default started here)."""
    handle = handle or start_precision(sz)
    res = {}
    try:
        for name, (proc, path) in handle["procs"].items():
            if proc.wait() != 0:
                raise RuntimeError(f"the {name} render process failed (exit {proc.returncode})")
            with np.load(path) as z:
                res[name] = {k: z[k] for k in z.files}
    finally:
        shutil.rmtree(handle["tmp"], ignore_errors=True)
    a, b = res["float32"], res["float64"]
    if float(a["checksum"]) != float(b["checksum"]):
        raise RuntimeError("the two processes rendered different colour models")
    if str(b["dtype"]) != "float64":
        raise RuntimeError(f"the float64 render came out as {b['dtype']}")
    d_rgb = np.abs(a["rgb"].astype(np.float64) - b["rgb"])
    d_op = np.abs(a["opacity"].astype(np.float64) - b["opacity"])
    hit = (a["opacity"] > 1e-3) | (b["opacity"] > 1e-3)
    d_depth = np.abs(a["depth"].astype(np.float64) - b["depth"])[hit]
    seg_diff = a["num_segments"] != b["num_segments"]
    per_pixel = d_rgb.max(-1)
    return {
        "preset": sz.render_preset, "points": sz.render_points, "image": f"{sz.render_res}x{sz.render_res}",
        "views": sz.render_views, "rays": int(per_pixel.size),
        "model": "random colour model (init_color_model, key 1), features 0.5 N(0, 1), confidence sigmoid(2), "
                 "the glossy scene's surface samples; float64 run: the same values cast",
        "rgb_max_abs_diff": float(d_rgb.max()), "rgb_mean_abs_diff": float(d_rgb.mean()),
        "rgb_p99_abs_diff": float(np.quantile(per_pixel, 0.99)),
        "rays_rgb_diff_over_1e-3": int((per_pixel > 1e-3).sum()),
        "opacity_max_abs_diff": float(d_op.max()), "opacity_mean_abs_diff": float(d_op.mean()),
        "depth_max_abs_diff": float(d_depth.max()) if d_depth.size else 0.0,
        "depth_mean_abs_diff": float(d_depth.mean()) if d_depth.size else 0.0,
        "rays_with_different_segment_count": int(seg_diff.sum()),
        "lost_segments": [int(a["lost"].sum()), int(b["lost"].sum())],
        "ms_per_render_float32": round(1e3 * float(a["best_s"]), 1),
        "ms_per_render_float64": round(1e3 * float(b["best_s"]), 1),
        "time_ratio_f64_over_f32": round(float(b["best_s"] / a["best_s"]), 2),
        "timed_concurrently": sz.parallel_workers,
        "first_call_s": [round(float(a["first_s"]), 2), round(float(b["first_s"]), 2)],
        "_images": {"rgb32": a["rgb"], "diff": per_pixel, "res": sz.render_res},
    }


# ---------------------------------------------------------------------------------- plots, text


def plot_all(results: dict, out_dir: Path, images: dict) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    q = results["quadrature"]
    s = np.asarray(q["s_values"])
    fig, axes = plt.subplots(1, 4, figsize=(20, 4.6))
    for ax, kind in zip(axes[:3], FIELDS):
        for rule in q["rules"]:
            e = np.asarray(quadrature_error(q, rule, kind))
            p = q["rules"][rule]["order"][kind]
            ax.loglog(s, np.maximum(e, 1e-17), "o-", ms=3, label=f"{rule} (order {p:.2f})" if p is not None else rule)
        for v in RENDER_S:
            ax.axvline(v, color="0.85", lw=0.8, zorder=0)
        ax.set_xticks(s, [str(v) for v in s], fontsize=7)
        ax.minorticks_off()
        ax.set_title(f"{kind}: {FIELDS[kind][:48]}", fontsize=8)
        ax.set_xlabel("samples per segment s")
        ax.set_ylabel("|error| of the segment mean")
        ax.legend(fontsize=7)
    ax = axes[3]
    for rule in q["rules"]:
        ax.loglog(q["rules"][rule]["ms_per_1e5_segments"], quadrature_error(q, rule, "smooth"), "o-", ms=3, label=rule)
    ax.set_xlabel("ms per 10^5 segments (float32, CPU, shared)")
    ax.set_ylabel("|error|, smooth field")
    ax.set_title("accuracy vs time (smooth field); grey: renderer's s", fontsize=8)
    ax.legend(fontsize=7)
    fig.tight_layout()
    paths.append(out_dir / "accuracy_vs_time_quadrature.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    kn = results["knn"]
    rows = kn["rows"]
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.6))
    for i, k in enumerate(sorted({r["k"] for r in rows})):
        rr = [r for r in rows if r["k"] == k]
        kc = [r["candidates"] for r in rr]
        c = f"C{i}"
        axes[0].plot(kc, [r["recall"] for r in rr], "o-", color=c, label=f"K={k}")
        axes[1].semilogy(kc, [r["diff_random_mean"] for r in rr], "o-", color=c, label=f"K={k}, random values")
        axes[1].semilogy(kc, [r["diff_smooth_mean"] for r in rr], "s--", color=c, label=f"K={k}, smooth field")
        axes[2].plot([r["ms_per_1e6_samples"] for r in rr], [r["recall"] for r in rr], "o-", color=c, label=f"K={k}")
    for i, e in enumerate(kn["exact"]):
        axes[2].plot([e["ms_per_1e6_samples"]], [e["recall_vs_scipy"]], "x", color=f"C{i}", ms=8,
                     label=f"exact mode K={e['k']}")
    axes[0].set_xlabel("candidate-set size")
    axes[0].set_ylabel("recall vs exact KNN")
    axes[1].set_xlabel("candidate-set size")
    axes[1].set_ylabel("mean |candidate - exact| interpolation")
    axes[2].set_xscale("log")
    axes[2].set_xlabel("ms per 10^6 samples (knn_integrate, F=32, CPU, shared)")
    axes[2].set_ylabel("recall")
    for ax in axes:
        ax.legend(fontsize=7)
    fig.suptitle(f"candidate-set KNN on {kn['num_points']} surface points, {kn['samples']} ray samples", fontsize=9)
    fig.tight_layout()
    paths.append(out_dir / "accuracy_vs_time_knn.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    pr = results["precision"]
    r = images["res"]
    rgb = np.asarray(images["rgb32"]).reshape(-1, r, r, 3)[0]
    diff = np.asarray(images["diff"]).reshape(-1, r, r)[0]
    fig, axes = plt.subplots(1, 2, figsize=(9, 4.2))
    axes[0].imshow(np.clip(rgb, 0, 1))
    axes[0].set_title(f"float32 render ({pr['preset']} preset, random model)", fontsize=8)
    im = axes[1].imshow(np.log10(np.maximum(diff, 1e-12)), cmap="magma", vmin=-12, vmax=0)
    axes[1].set_title(f"log10 max|f32 - f64| per pixel; f64/f32 time {pr['time_ratio_f64_over_f32']}x", fontsize=8)
    fig.colorbar(im, ax=axes[1])
    for ax in axes:
        ax.axis("off")
    fig.tight_layout()
    paths.append(out_dir / "accuracy_vs_time_precision.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)
    return [str(p) for p in paths]


def _g(x, digits=2) -> str:
    return "–" if x is None else f"{x:.{digits}g}" if abs(x) < 1e-2 or abs(x) >= 1e4 else f"{x:.{digits + 1}g}"


def summary_markdown(res: dict) -> str:
    q, kn, pr = res["quadrature"], res["knn"], res["precision"]
    s_vals = q["s_values"]
    show = [s for s in s_vals if s in (4, 8, 16, 22, 64)] or s_vals
    L = [f"### Numerics: accuracy against time (`{res['command']}`)", "",
         f"Measured on {res['machine']['platform']}, JAX {res['jax']} ({res['device']}); "
         f"{SHARED_NOTE}. Study wall time {res['wall_s']:.0f} s.", "",
         "#### Quadrature", "",
         "Error of the segment mean on `[0, 1]` against the analytic integral (mean |error| over "
         f"{q['num_fields']} random fields; RMS for `stochastic`), fitted order `p` (error ~ h^p, s >= 8), "
         "and the time of sample placement + field evaluation + weighted sum per 10^5 segments.", "",
         "| rule | order smooth | order sharp | order step | " + " | ".join(f"err smooth s={s}" for s in show)
         + " | " + " | ".join(f"ms/1e5 s={s}" for s in show) + " |",
         "|---|" + "---:|" * (3 + 2 * len(show))]
    for rule, row in q["rules"].items():
        e = quadrature_error(q, rule, "smooth")
        t = row["ms_per_1e5_segments"]
        L.append(f"| {rule} | " + " | ".join(_g(row["order"][k]) for k in FIELDS) + " | "
                 + " | ".join(_g(e[s_vals.index(s)]) for s in show) + " | "
                 + " | ".join(f"{t[s_vals.index(s)]:.1f}" for s in show) + " |")
    L += ["", "| rule | " + " | ".join(f"err sharp s={s}" for s in show) + " | "
          + " | ".join(f"err step s={s}" for s in show) + " |", "|---|" + "---:|" * (2 * len(show))]
    for rule in q["rules"]:
        L.append(f"| {rule} | " + " | ".join(_g(quadrature_error(q, rule, "sharp")[s_vals.index(s)]) for s in show)
                 + " | " + " | ".join(_g(quadrature_error(q, rule, "step")[s_vals.index(s)]) for s in show) + " |")
    L += ["", "#### KNN candidate sets", "",
          f"{kn['num_points']} surface points (glossy scene), {kn['samples']} samples of camera-ray segments "
          "(8 per segment); recall against exact KNN, mean |candidate - exact| of the interpolated values "
          "(random N(0, 1) values and a smooth field), the exact neighbours' own error on the smooth field, "
          "and the time of `knn_integrate` (32 feature channels) per 10^6 samples.", "",
          "| candidates | K | recall | 1% quantile | all K exact | diff random (mean / max) | diff smooth (mean) "
          "| exact KNN err smooth | ms / 1e6 samples |", "|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in kn["rows"]:
        L.append(f"| {r['candidates']} | {r['k']} | {r['recall']:.4f} | {r['recall_p01']:.3f} | "
                 f"{r['exact_fraction']:.3f} | {_g(r['diff_random_mean'])} / {_g(r['diff_random_max'])} | "
                 f"{_g(r['diff_smooth_mean'])} | {_g(r['exact_smooth_err_mean'])} | {r['ms_per_1e6_samples']:.0f} |")
    for e in kn["exact"]:
        L.append(f"| exact (brute force) | {e['k']} | {e['recall_vs_scipy']:.4f} | | | | | | "
                 f"{e['ms_per_1e6_samples']:.0f} |")
    L += ["", "#### float32 against float64", "",
          f"The same random model rendered in both precisions ({pr['preset']} preset, {pr['points']} points, "
          f"{pr['views']} view(s) at {pr['image']}).", "",
          "| max abs RGB diff | mean abs RGB diff | 99% quantile (per ray) | rays > 1e-3 | max abs opacity diff "
          "| max abs depth diff | rays with different segment counts | f32 ms | f64 ms | f64 / f32 |",
          "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
          f"| {_g(pr['rgb_max_abs_diff'])} | {_g(pr['rgb_mean_abs_diff'])} | {_g(pr['rgb_p99_abs_diff'])} | "
          f"{pr['rays_rgb_diff_over_1e-3']} / {pr['rays']} | {_g(pr['opacity_max_abs_diff'])} | "
          f"{_g(pr['depth_max_abs_diff'])} | {pr['rays_with_different_segment_count']} | "
          f"{pr['ms_per_render_float32']:.0f} | {pr['ms_per_render_float64']:.0f} | {pr['time_ratio_f64_over_f32']}x |",
          ""]
    L += ["#### What each knob buys and costs", ""]
    for para in res.get("discussion", []):
        L += [para, ""]
    L += ["", "Plots: `experiments/results/accuracy_vs_time_quadrature.png`, `accuracy_vs_time_knn.png`, "
          "`accuracy_vs_time_precision.png`; numbers: `experiments/results/accuracy_vs_time.json`.", ""]
    return "\n".join(L)


def discussion(res: dict) -> list[str]:
    """One paragraph per knob, written from the measured numbers (comparisons are computed, not assumed)."""
    q, kn, pr = res["quadrature"], res["knn"], res["precision"]
    s_vals = q["s_values"]
    rules = list(q["rules"])
    o = {r: q["rules"][r]["order"] for r in rules}
    i22 = s_vals.index(22) if 22 in s_vals else len(s_vals) - 1
    i8 = s_vals.index(8) if 8 in s_vals else 0
    def err(r, k, i):
        return quadrature_error(q, r, k)[i]
    t = {r: q["rules"][r]["ms_per_1e5_segments"] for r in rules}
    det = [r for r in rules if r != "stochastic"]
    det_t = [t[r][i22] for r in det]
    # local slope of the spline error between the two largest s (the fit over s >= 8 is pre-asymptotic)
    e_sp = quadrature_error(q, "spline", "smooth")
    local = math.log(e_sp[-2] / e_sp[-1]) / math.log((s_vals[-1] - 1) / (s_vals[-2] - 1))
    sharp_best = min(det, key=lambda r: err(r, "sharp", i22))
    t_lo_s, t_hi_s = (sum(t[r][i] for r in det) / len(det) for i in (i8, i22))

    rows = kn["rows"]
    paper = next((r for r in rows if r["candidates"] == 96 and r["k"] == 32), rows[-1])
    same_k = sorted((r for r in rows if r["k"] == paper["k"]), key=lambda r: r["candidates"])
    small, big = same_k[0], same_k[-1]
    ks = sorted({r["k"] for r in rows})
    at_kc = sorted((r for r in rows if r["candidates"] == paper["candidates"]), key=lambda r: r["k"])
    ex = next((e for e in kn["exact"] if e["k"] == paper["k"]), kn["exact"][-1])
    lv = paper.get("recall_by_level", {})
    lv_txt = ", ".join(f"level {k}: {v:.3f}" for k, v in sorted(lv.items())) if lv else ""
    e_sm = [r["exact_smooth_err_mean"] for r in at_kc]
    return [
        f"**Quadrature rule.** On the smooth field the fitted orders (s = 8..{s_vals[-1]}) are "
        + ", ".join(f"{r} {_g(o[r]['smooth'])}" for r in rules)
        + " (RMS for stochastic); the module docstring predicts 3, 4, 4, 3, 2 and 1.5. The spline's fit is "
        f"above 4 because an h^5 term still dominates at these s: its local slope between s = {s_vals[-2]} and "
        f"{s_vals[-1]} is {local:.2f}, falling towards 4. At s = {s_vals[i22]} the smooth-field error is "
        + ", ".join(f"{r} {_g(err(r, 'smooth', i22))}" for r in rules)
        + f". The rule costs nothing extra at render time: every deterministic rule is one weighted sum with "
        f"different constant weights ({min(det_t):.0f}-{max(det_t):.0f} ms per 10^5 segments at s = "
        f"{s_vals[i22]} here; the spread is timing noise on the shared CPU), and the stochastic rule adds a "
        f"random draw ({t['stochastic'][i22]:.0f} ms). The rule only matters on smooth fields: on a step every "
        f"rule is first order (orders {', '.join(_g(o[r]['step']) for r in rules)}, errors "
        f"{_g(min(err(r, 'step', i22) for r in det))}-{_g(max(err(r, 'step', i22) for r in det))} at s = "
        f"{s_vals[i22]}), and on narrow Gaussians (2-5 % of the segment) s = {s_vals[i8]} is still "
        f"pre-asymptotic (hermite {_g(err('hermite', 'sharp', i8))}, trapezoid {_g(err('trapezoid', 'sharp', i8))}); "
        f"at s = {s_vals[i22]} {sharp_best} is best there. Swapping hermite for hermite_o4 or spline is free and "
        f"gains one order (about {err('hermite', 'smooth', i22) / err('spline', 'smooth', i22):.0f}x less error "
        f"at s = {s_vals[i22]}) on smooth fields; the stochastic rule is the least accurate at every s.",
        f"**Samples per segment s.** The quadrature alone costs about {t_lo_s:.0f} ms per 10^5 segments at "
        f"s = {s_vals[i8]} and {t_hi_s:.0f} ms at s = {s_vals[i22]} (mean over the deterministic rules), "
        f"roughly linear in s. In the renderer each sample also costs a KNN interpolation (about "
        f"{paper['ms_per_1e6_samples'] / 1e3:.1f} µs per sample at {paper['candidates']} candidates, "
        f"K = {paper['k']}, from the KNN table), which dominates: doubling s doubles the per-segment cost, while "
        f"it divides a cubic rule's smooth-field error by 8-16 (2^3-2^4) and a step's error only by 2.",
        f"**Candidate-set size and K.** At the paper's setting ({paper['candidates']} candidates, K = {paper['k']}) "
        f"recall against exact KNN is {paper['recall']:.4f} on average, and {paper['exact_fraction']:.1%} of the "
        f"samples get all K exact neighbours; the misses concentrate in a tail (1 % of samples have recall "
        f"<= {paper['recall_p01']:.2f}){'; by level (0 = bottom): ' + lv_txt if lv_txt else ''}. The interpolated "
        f"values differ from the exact-KNN ones by {_g(paper['diff_random_mean'])} on average for random "
        f"unit-variance values (max {_g(paper['diff_random_max'])}) and by {_g(paper['diff_smooth_mean'])} for "
        f"the smooth field, whose error against the field itself is {_g(paper['exact_smooth_err_mean'])} even "
        f"with exact neighbours (the interpolation's own error, which barely moves with K: "
        + ", ".join(f"{_g(e)}" for e in e_sm) + f" for K = {', '.join(str(r['k']) for r in at_kc)}). Going from "
        f"{small['candidates']} to {big['candidates']} candidates raises recall from {small['recall']:.4f} to "
        f"{big['recall']:.4f} at {big['ms_per_1e6_samples'] / small['ms_per_1e6_samples']:.1f}x the time; at a "
        f"fixed candidate set a larger K lowers recall (K = {ks[0]} to {ks[-1]} at {paper['candidates']}: "
        f"{at_kc[0]['recall']:.4f} to {at_kc[-1]['recall']:.4f}) and costs "
        f"{at_kc[-1]['ms_per_1e6_samples'] / at_kc[0]['ms_per_1e6_samples']:.1f}x the time. Exact brute-force KNN "
        f"costs {ex['ms_per_1e6_samples'] / 1e3:.0f} s per 10^6 samples at K = {ex['k']} on {kn['num_points']} "
        f"points ({ex['ms_per_1e6_samples'] / paper['ms_per_1e6_samples']:.0f}x the candidate mode, growing "
        f"linearly with the cloud size): a reference, not a rendering mode.",
        f"**float32 vs float64.** Rendering the same model in float64 changes RGB by at most "
        f"{_g(pr['rgb_max_abs_diff'])} (mean {_g(pr['rgb_mean_abs_diff'])}; {pr['rays_rgb_diff_over_1e-3']} of "
        f"{pr['rays']} rays differ by more than 1e-3; {pr['rays_with_different_segment_count']} rays get a "
        f"different number of segments), opacity by at most {_g(pr['opacity_max_abs_diff'])}, and costs "
        f"{pr['time_ratio_f64_over_f32']}x the time on this CPU"
        + (" (timed concurrently: ratio not meaningful)" if pr.get("timed_concurrently") else "")
        + ". float32 is enough: the difference is far below an 8-bit colour step (1/255 ~ 4e-3).",
    ]


# ---------------------------------------------------------------------------------------- main


def run_numerics(sz: Sizes, out_dir: Path, command: str) -> dict:
    import jax

    from ne_jax.atomic import atomic_write_json, atomic_write_text

    t0 = time.perf_counter()
    res = {"study": "numerics", "command": command, "sizes": dataclasses.asdict(sz),
           "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "note": SHARED_NOTE},
           "jax": jax.__version__, "device": str(jax.devices()[0])}
    res["study_wall_s"] = {}
    # Quick mode: the render processes (mostly compiling) run while this process measures the rest.
    early = start_precision(sz) if sz.parallel_workers else None
    studies = (("quadrature", quadrature_study), ("knn", knn_study),
               ("precision", lambda sz: precision_study(sz, early)))
    for name, fn in studies:
        t1 = time.perf_counter()
        res[name] = fn(sz)
        res["study_wall_s"][name] = round(time.perf_counter() - t1, 1)
        print(f"{name}: {res['study_wall_s'][name]} s", file=sys.stderr, flush=True)
    images = res["precision"].pop("_images")
    res["wall_s"] = round(time.perf_counter() - t0, 1)
    res["discussion"] = discussion(res)
    out_dir.mkdir(parents=True, exist_ok=True)
    res["plots"] = [os.path.basename(p) for p in plot_all(res, out_dir, images)]
    md = summary_markdown(res)
    atomic_write_json(out_dir / "accuracy_vs_time.json", res)
    atomic_write_text(out_dir / "accuracy_vs_time_numerics.md", md)
    print(md)
    return res


TRAINING_PRESETS = ("tiny", "default", "paper")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--study", choices=("numerics", "image", "training"), default="numerics")
    ap.add_argument("--quick", action="store_true", help="reduced sizes (smoke test, well under a minute)")
    ap.add_argument("--out-dir", type=Path, default=RESULTS)
    ap.add_argument("--summary-only", action="store_true",
                    help="rewrite the Markdown summary from the JSON in --out-dir (no measuring, no plots)")
    ap.add_argument("--render-worker", nargs=3, metavar=("DTYPE", "MODEL", "OUT"), help=argparse.SUPPRESS)
    ap.add_argument("--sizes-json", help=argparse.SUPPRESS)
    ap.add_argument("--run", type=Path, help="--study image: a trained run directory (required)")
    ap.add_argument("--edit", default="bend",
                    help="--study image: the benchmark edit (ground truth <scene>/edits/<edit>)")
    ap.add_argument("--scene", type=Path, help="--study image: the scene folder, if not the one the run recorded; "
                                               "--study training: the scene to train on (required)")
    ap.add_argument("--test-views", type=int, metavar="N",
                    help="--study image: score on N evenly spaced test views (default: all)")
    ap.add_argument("--timing-passes", type=int, metavar="P",
                    help="--study image: passes re-timing every render, the best kept (default 3)")
    ap.add_argument("--preset", default="tiny",
                    help="--study training: the training preset whose candidates are trained (tiny, default or "
                         "paper); --summary-only: whose results are rewritten (for --study image: the name of "
                         "the model's run config)")
    ap.add_argument("--runs", type=Path,
                    help="--study training: folder of the cached runs (default runs/avt_training/<scene>)")
    ap.add_argument("--candidates", choices=("full", "short"),
                    help="--study training: which candidates (default: full for tiny, short for the hour-long presets)")
    ap.add_argument("--train-only", type=int, nargs="+", metavar="I",
                    help="--study training: only train these candidates (indices; parallel processes), write nothing")
    ap.add_argument("--finished-only", action="store_true",
                    help="--study training: score only the candidates whose runs have finished (an interim result)")
    args = ap.parse_args(argv)
    if args.render_worker:
        render_worker(args.render_worker[0], Sizes(**{k: tuple(v) if isinstance(v, list) else v
                                                      for k, v in json.loads(args.sizes_json).items()}),
                      args.render_worker[1], args.render_worker[2])
        return 0
    if args.study == "training":
        if args.preset not in TRAINING_PRESETS:
            print(f"--preset: expected one of {', '.join(TRAINING_PRESETS)}, found {args.preset!r}", file=sys.stderr)
            return 2
        if args.scene is None and not args.summary_only:
            print("--study training needs a scene to train on: pass --scene DIR", file=sys.stderr)
            return 2
        from experiments import accuracy_vs_time_training as training
        if args.summary_only:
            print(training.combined_markdown(training.rewrite_summary(args.out_dir, args.preset)))
            return 0
        runs = args.runs or Path("runs") / "avt_training" / args.scene.name
        cset = args.candidates or ("full" if args.preset == "tiny" else "short")
        command = " ".join(["python -m experiments.accuracy_vs_time --study training --scene", str(args.scene),
                            "--preset", args.preset, "--runs", str(runs), "--candidates", cset]
                           + (["--quick"] if args.quick else []) + (["--finished-only"] if args.finished_only else []))
        res = training.run_training(args.scene, runs, args.out_dir, command, preset=args.preset, quick=args.quick,
                                    candidate_set=cset, train_only=args.train_only, finished_only=args.finished_only)
        if res is not None:
            print(training.summary_markdown(res))
        return 0
    if args.study == "image":
        from experiments import accuracy_vs_time_image as image
        if args.summary_only:
            image.rewrite_summary(args.out_dir, args.preset)
            return 0
        if args.run is None:
            print("--study image needs a trained model: pass --run RUN_DIR", file=sys.stderr)
            return 2
        command = " ".join(["python -m experiments.accuracy_vs_time --study image --run", str(args.run)]
                           + ([f"--edit {args.edit}"] if args.edit != "bend" else [])
                           + ([f"--scene {args.scene}"] if args.scene else [])
                           + ([f"--test-views {args.test_views}"] if args.test_views else [])
                           + ([f"--timing-passes {args.timing_passes}"] if args.timing_passes else [])
                           + (["--quick"] if args.quick else []))
        res = image.run_image(args.run, args.out_dir, command, edit=args.edit, scene=args.scene, quick=args.quick,
                              test_views=args.test_views, timing_passes=args.timing_passes)
        print((args.out_dir / f"{image.stem(res['preset'])}.md").read_text())
        return 0 if res["targets"] else 1
    if args.summary_only:
        from ne_jax.atomic import atomic_write_json, atomic_write_text

        res = json.loads((args.out_dir / "accuracy_vs_time.json").read_text())
        res["discussion"] = discussion(res)
        atomic_write_json(args.out_dir / "accuracy_vs_time.json", res)
        atomic_write_text(args.out_dir / "accuracy_vs_time_numerics.md", summary_markdown(res))
        return 0
    command = "python -m experiments.accuracy_vs_time --study numerics" + (" --quick" if args.quick else "")
    run_numerics(Sizes.quick() if args.quick else Sizes.full(), args.out_dir, command)
    return 0


if __name__ == "__main__":
    import ne_jax

    ne_jax.setup(huge_pages=True)  # as `ne-jax` does: a host device per core, huge pages (restarts)
    sys.exit(main())

"""Accuracy against time on images of a trained model and of its zero-shot edit (issue 7, part 2).

    python -m experiments.accuracy_vs_time --study image --run RUN_DIR [--edit bend] [--scene DIR] [--quick]

From the model's own render config (the one it was trained with) one knob is changed at a time:
samples per segment ``s`` (``samples_per_level`` scaled, at least 2), ``K`` (capped by the candidate
set), the candidate-set size (``KDTreeConfig.candidate_min``; the tree is rebuilt), the rendering
levels (``num_render_levels``; rebuilt), the traversal frontier (``Capacities.frontier`` of the
scene: nodes kept per ray and level; a chunk of rays that overflows it is rendered again at twice the
width, see :func:`~ne_jax.render.renderer.render_chunked`, so at render time it is a starting width:
it trades re-rendered chunks against the width, and ``overflow_rays`` counts the rays of the timed
view that overflow it before any growth), the share of points kept (a seeded random
subset of the alive points, the others deleted, rebuilt), the integration rule (every deterministic
quadrature rule, and ``integration="samples"``: shade every sample, no integration), the chunk size
(time only: it changes no pixel), joint settings (everything cheaper, everything richer, s x1.5 with
the spline rule), and the ``tiny`` and ``default`` run presets' tree, quadrature and traversal
capacities where they differ from the own.

Every setting renders with the capacities the model's run config starts with
(``RunConfig.capacities``; the frontier knob and the presets change its traversal widths), not the
ones its training ended with: the packing budget is the run's starting one, as before capacities
were carried by the scene.

Each setting is scored on two targets: the trained model on its scene's test split (``original``),
and the model edited zero-shot by :func:`~ne_jax.edit.model.edit_model` (IST on) on the edited
scene's test split (``<scene>/edits/<edit>``). Per setting: mean test PSNR and SSIM
(:func:`~ne_jax.eval.views.evaluate_split`), the time per image (minimum over repeats of rendering
test view 0 after a first, compiling call; ``block_until_ready``) and the compile time (first call
minus the best). The Pareto front (lower time, higher PSNR) per target goes into the table.

Writes ``accuracy_vs_time_image_<preset>.{json,png,md}`` to ``--out-dir`` (``<preset>``: the name of the
run config the model was trained with). ``--test-views N`` scores on N evenly spaced test views and
``--timing-passes P`` re-times each render P times (default 3): fewer of both for 200 px models, whose
images take seconds each on a CPU.
"""

from __future__ import annotations

import dataclasses
import functools
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

from experiments.common import ROOT, SHARED_NOTE, best_time, device_tag, timed_steps  # noqa: F401 (re-exported)
from experiments.common import write_results as write_bench  # noqa: F401

HERE = Path(__file__).resolve().parent

KNOBS = {
    "own": "the model's own render config (the preset it was trained with)",
    "samples": "samples per segment s: samples_per_level scaled (rounded, at least 2)",
    "k": "K, neighbours per sample (at most the candidate-set size)",
    "candidates": "candidate-set size (KDTreeConfig.candidate_min; tree rebuilt)",
    "levels": "rendering levels (KDTreeConfig.num_render_levels; tree rebuilt)",
    "frontier": "traversal frontier (Capacities.frontier: nodes kept per ray and level; a chunk "
                "that overflows it is rendered again at twice the width, so no segment is lost)",
    "points": "share of the alive points kept (seeded random subset, the rest deleted; tree rebuilt)",
    "rule": "integration: quadrature rule, or 'samples' (shade each sample, no integration)",
    "chunk": "rays per compiled call (time only: no pixel changes, accuracy copied from the own config)",
    "joint": "several knobs at once",
    "preset": "a library preset's tree, quadrature, chunk and traversal capacities (the model's shading and "
              "packing budget kept)",
}


@dataclasses.dataclass(frozen=True)
class ImageSizes:
    """Which settings a run sweeps (``full`` for the committed results, ``quick`` for the smoke test)."""

    s_scales: tuple[float, ...]
    ks: tuple[int, ...]
    candidate_scales: tuple[int, ...]
    level_deltas: tuple[int, ...]
    frontier_scales: tuple[float, ...]
    keep: tuple[float, ...]
    rules: tuple[str, ...] | None
    """``None``: every deterministic rule."""
    samples_integration: bool
    chunk_scales: tuple[float, ...]
    joint: bool
    presets: tuple[str, ...]
    repeats: int
    timing_passes: int = 1
    """Passes over all settings re-timing each (compiled) render: the best over passes is kept, so a
    burst of load from other jobs during one setting's pass does not decide its time."""
    points_seed: int = 0
    test_views: int | None = None
    """Score on this many evenly spaced test views (``None``: all)."""

    @classmethod
    def full(cls) -> ImageSizes:
        return cls(s_scales=(0.5, 0.75, 1.0, 1.5, 2.0), ks=(4, 8, 16, 32), candidate_scales=(1, 2, 4),
                   level_deltas=(-1, 1), frontier_scales=(0.25, 0.5), keep=(1.0, 0.5, 0.25), rules=None,
                   samples_integration=True,
                   chunk_scales=(0.25, 0.5, 2.0, 4.0), joint=True, presets=("tiny", "default"), repeats=3,
                   timing_passes=3)

    @classmethod
    def quick(cls) -> ImageSizes:
        return cls(s_scales=(1.0, 2.0), ks=(), candidate_scales=(), level_deltas=(), frontier_scales=(),
                   keep=(1.0, 0.25), rules=(), samples_integration=False, chunk_scales=(4.0,), joint=False,
                   presets=(), repeats=1)


@dataclasses.dataclass(frozen=True)
class Setting:
    knob: str
    label: str
    value: object
    cfg: object  # RenderConfig
    keep: float = 1.0
    time_only: bool = False
    capacities: object = None
    """The scene's :class:`~ne_jax.geometry.capacity.Capacities` for this setting (``None``: the own)."""


def _scaled_samples(spl: tuple[int, ...], f: float) -> tuple[int, ...]:
    return tuple(max(2, int(round(s * f))) for s in spl)


def _with_levels(cfg, levels: int):
    """``cfg`` with ``levels`` rendering levels; ``samples_per_level`` extended by its last entry if short."""
    q = cfg.quadrature
    spl = tuple(q.samples_per_level)
    if len(spl) < levels + 1:
        spl = spl + (spl[-1],) * (levels + 1 - len(spl))
    tree = cfg.kdtree.replace(num_render_levels=levels)
    tree = tree.replace(knn_k=min(tree.knn_k, tree.num_candidates))
    return cfg.replace(kdtree=tree, quadrature=dataclasses.replace(q, samples_per_level=spl))


def settings_for(own, sz: ImageSizes, capacities=None) -> list[Setting]:
    """The settings of one target, from its own render config ``own`` (a RenderConfig) and the own
    buffer sizes ``capacities`` (default ``Capacities()``), which the frontier knob and the presets
    change."""
    from ne_jax.geometry.capacity import Capacities
    from ne_jax.render.quadrature import DETERMINISTIC_RULES

    caps = Capacities() if capacities is None else capacities
    q, t = own.quadrature, own.kdtree
    spl = tuple(q.samples_per_level)
    nc = t.num_candidates
    out = [Setting("own", "own config", None, own)]
    for f in sz.s_scales:
        out.append(Setting("samples", f"s x{f:g} {_scaled_samples(spl, f)[:t.num_render_levels]}", f,
                           own.replace(quadrature=dataclasses.replace(q, samples_per_level=_scaled_samples(spl, f)))))
    for k in sz.ks:
        if k <= nc:
            out.append(Setting("k", f"K={k}", k, own.replace(kdtree=t.replace(knn_k=k))))
    for c in sz.candidate_scales:
        out.append(Setting("candidates", f"candidates={c * nc}", c * nc,
                           own.replace(kdtree=t.replace(candidate_min=c * nc))))
    for d in sz.level_deltas:
        lv = t.num_render_levels + d
        if lv >= 1:
            cfg = _with_levels(own, lv)
            out.append(Setting("levels", f"levels={lv} (candidates {cfg.kdtree.num_candidates})", lv, cfg))
    for f in sz.frontier_scales:
        fc = max(2, int(round(caps.frontier * f)))
        first = caps.first_pass_frontier if caps.first_pass_frontier is not None and caps.first_pass_frontier < fc \
            else None  # a first pass at least as wide as the frontier: one pass
        out.append(Setting("frontier", f"frontier={fc}", fc, own,
                           capacities=caps.replace(frontier=fc, first_pass_frontier=first)))
    for f in sz.keep:
        out.append(Setting("points", f"points {f:.0%}", f, own, keep=f))
    rules = DETERMINISTIC_RULES if sz.rules is None else sz.rules
    for r in rules:
        out.append(Setting("rule", f"rule {r}", r, own.replace(quadrature=dataclasses.replace(q, rule=r))))
    if sz.samples_integration:
        out.append(Setting("rule", f"samples integration ({q.rule} positions)", "samples",
                           own.replace(integration="samples")))
    for f in sz.chunk_scales:
        c = max(64, int(own.chunk * f))
        out.append(Setting("chunk", f"chunk={c}", c, own.replace(chunk=c), time_only=True))
    if sz.joint:
        cheap_q = dataclasses.replace(q, samples_per_level=_scaled_samples(spl, 0.5))
        out.append(Setting("joint", "cheaper: s x0.5, K=4", "cheaper",
                           own.replace(quadrature=cheap_q, kdtree=t.replace(knn_k=min(4, t.knn_k)))))
        rich_t = t.replace(candidate_min=2 * nc, knn_k=min(2 * t.knn_k, 2 * nc))
        rich_q = dataclasses.replace(q, samples_per_level=_scaled_samples(spl, 2.0), rule="spline")
        out.append(Setting("joint", f"richer: s x2, K={rich_t.knn_k}, candidates={rich_t.num_candidates}, spline",
                           "richer", own.replace(kdtree=rich_t, quadrature=rich_q)))
        mid_q = dataclasses.replace(q, samples_per_level=_scaled_samples(spl, 1.5), rule="spline")
        out.append(Setting("joint", "s x1.5, spline", "s1.5+spline", own.replace(quadrature=mid_q)))
    for name in sz.presets:
        from ne_jax.train.run import get_run_preset

        preset = get_run_preset(name)
        p = preset.render
        cfg = own.replace(kdtree=p.kdtree, quadrature=p.quadrature, chunk=p.chunk)
        cap = preset.capacities.replace(segments_per_ray=caps.segments_per_ray)  # the own packing budget
        if cfg != own or cap != caps:
            out.append(Setting("preset", f"preset {name}", name, cfg, capacities=cap))
    return out


def _overflow_rays(scene, tree_cfg, rays) -> int:
    """How many of ``rays`` overflow ``scene``'s traversal capacities (before any growth)."""
    from ne_jax.geometry.intersect import intersect

    return int(np.sum(np.asarray(intersect(scene.tree, rays, tree_cfg, scene.capacities).lost().count) > 0))


def _kept_points(points, frac: float, seed: int):
    """``points`` with a seeded random ``1 - frac`` of its alive points deleted."""
    import jax.numpy as jnp

    if frac >= 1.0:
        return points
    alive = np.asarray(points.alive)
    idx = np.flatnonzero(alive)
    keep = np.random.default_rng(seed).permutation(idx)[: max(1, int(round(frac * idx.size)))]
    new = np.zeros_like(alive)
    new[keep] = True
    return points.replace(alive=jnp.asarray(new))


def evenly_spaced(total: int, n: int | None) -> list[int]:
    """``n`` view indices spread evenly over ``range(total)`` (all of them if ``n`` is ``None`` or >= total)."""
    if n is None or n >= total:
        return list(range(total))
    if n < 1:
        raise ValueError(f"test views: expected at least 1, found {n}")
    return [int(i) for i in np.unique(np.round(np.linspace(0, total - 1, n)).astype(int))]


def stem(preset: str) -> str:
    """The results' file stem for a model trained with the run config named ``preset``."""
    return f"accuracy_vs_time_image_{preset}"


def measure_target(name: str, model, split, sz: ImageSizes, log=print) -> dict:
    """Every setting of one target (``model``: a TrainedModel; ``split``: the test split to score)."""
    import jax

    from ne_jax.data.nerf_synthetic import parse_background
    from ne_jax.data.rays import camera_rays
    from ne_jax.eval.views import evaluate_split
    from ne_jax.render.quadrature import at_test_time
    from ne_jax.render.renderer import PointScene, render_image

    run = model.run
    own = run.render
    own_caps = run.capacities  # the run's starting buffer sizes (see the module docstring)
    params = model.state.params
    bg = parse_background(run.background)
    near, far = run.sampler.near, run.sampler.far
    camera = split.cameras()[0]
    rays0 = camera_rays(camera, near, far)
    points = model.scene.points
    scenes: dict = {}
    done: dict = {}
    rows = []
    timers = {}
    for st in settings_for(own, sz, own_caps):
        caps = own_caps if st.capacities is None else st.capacities
        skey = (st.cfg.kdtree, st.keep)
        if skey not in scenes:
            t0 = time.perf_counter()
            pts = _kept_points(points, st.keep, sz.points_seed)
            scene = model.scene if (st.cfg.kdtree == own.kdtree and st.keep >= 1.0) else PointScene.build(pts, st.cfg)
            scenes[skey] = (scene, time.perf_counter() - t0)
        scene, build_s = scenes[skey]
        scene = scene.replace(capacities=caps)
        row = {"target": name, "knob": st.knob, "label": st.label, "value": st.value, "keep": st.keep,
               "time_only": st.time_only, "samples_per_level": list(st.cfg.quadrature.samples_per_level),
               "rule": st.cfg.quadrature.rule, "integration": st.cfg.integration, "knn_k": st.cfg.kdtree.knn_k,
               "candidates": st.cfg.kdtree.num_candidates, "levels": st.cfg.kdtree.num_render_levels,
               "chunk": st.cfg.chunk, "alive_points": int(np.asarray(scene.points.alive).sum()),
               "tree_depth": int(scene.tree.depth), "tree_build_s": round(build_s, 3),
               "overflow_rays": _overflow_rays(scene, st.cfg.kdtree, rays0)}
        if (st.cfg, caps, st.keep) in done and not st.time_only:  # the same render as an earlier setting
            prev = done[(st.cfg, caps, st.keep)]
            row.update({k: prev[k] for k in ("psnr", "ssim", "lost_segments", "ms_per_image", "compile_s")})
            row["same_as"] = prev["label"]
            rows.append(row)
            continue
        cfg = st.cfg.replace(quadrature=at_test_time(st.cfg.quadrature))
        t1 = time.perf_counter()
        timers[len(rows)] = fn = functools.partial(render_image, cfg, params, scene, camera, bg, near, far,
                                                   progress=False)
        first, best = best_time(fn, sz.repeats)
        row["ms_per_image"] = round(1e3 * best, 2)
        row["compile_s"] = round(max(0.0, first - best), 3)
        if st.time_only:
            base = done.get((st.cfg.replace(chunk=own.chunk), caps, st.keep)) or rows[0]
            row.update({k: base[k] for k in ("psnr", "ssim", "lost_segments")})
        else:
            report, _ = evaluate_split(st.cfg, params, scene, split, run.background, near, far, progress=False)
            row.update({"psnr": round(report["psnr"], 4), "ssim": round(report["ssim"], 5),
                        "lost_segments": report["lost_segments"]})
            done[(st.cfg, caps, st.keep)] = row
        row["wall_s"] = round(time.perf_counter() - t1, 2)
        row["ms_first_pass"] = row["ms_per_image"]
        rows.append(row)
        log(f"[{name}] {st.label}: PSNR {row['psnr']:.2f} dB, SSIM {row['ssim']:.4f}, {row['ms_per_image']:.0f} ms "
            f"(compile {row['compile_s']:.1f} s)")
    for p in range(1, sz.timing_passes):  # re-time every render (already compiled), keep the best
        for i, fn in timers.items():
            _, best = best_time(fn, sz.repeats)
            rows[i]["ms_per_image"] = round(min(rows[i]["ms_per_image"], 1e3 * best), 2)
        log(f"[{name}] timing pass {p + 1}/{sz.timing_passes} done")
    for r in rows:
        if "same_as" in r:
            r["ms_per_image"] = next(x["ms_per_image"] for x in rows if x["label"] == r["same_as"])
    jax.clear_caches()
    own_row = rows[0]
    for r in rows:
        r["d_psnr"] = round(r["psnr"] - own_row["psnr"], 4)
        r["time_ratio"] = round(r["ms_per_image"] / own_row["ms_per_image"], 4)
    front = pareto_front(rows)
    for i, r in enumerate(rows):
        r["on_front"] = i in front
    return {"target": name, "split": f"{split.name} ({split.num_views} views, {split.width}x{split.height})",
            "scene_dir": str(model.scene_dir), "own_render": _cfg_summary(own),
            "own_capacities": dataclasses.asdict(own_caps), "rows": rows,
            "front": front}


def _cfg_summary(cfg) -> dict:
    return {"samples_per_level": list(cfg.quadrature.samples_per_level), "rule": cfg.quadrature.rule,
            "knn_k": cfg.kdtree.knn_k, "candidates": cfg.kdtree.num_candidates, "levels": cfg.kdtree.num_render_levels,
            "chunk": cfg.chunk, "integration": cfg.integration, "ist": bool(cfg.shading.effects.ist)}


def pareto_front(rows: list[dict], time_key: str = "ms_per_image") -> list[int]:
    """Indices of the rows no other row beats (``time_key`` <= and PSNR >=, one strictly), fastest
    first; rows that repeat an earlier render (``same_as``) are left out."""
    cand = [i for i, r in enumerate(rows) if "same_as" not in r]
    front = []
    for i in cand:
        a = rows[i]
        dominated = any((b[time_key] <= a[time_key] and b["psnr"] >= a["psnr"])
                        and (b[time_key] < a[time_key] or b["psnr"] > a["psnr"])
                        for j in cand if j != i for b in [rows[j]])
        if not dominated:
            front.append(i)
    return sorted(front, key=lambda i: rows[i][time_key])


def front_distance(rows: list[dict], front: list[int], i: int) -> dict:
    """Where row ``i`` sits relative to the front: the PSNR the front gives at no more time
    (``db_below_front``, >= 0) and the time the front needs for at least its PSNR (``time_ratio_front``)."""
    r = rows[i]
    f = [rows[j] for j in front]
    no_slower = [x["psnr"] for x in f if x["ms_per_image"] <= r["ms_per_image"]]
    as_good = [x["ms_per_image"] for x in f if x["psnr"] >= r["psnr"]]
    return {"on_front": i in front,
            "db_below_front": round(max(0.0, max(no_slower) - r["psnr"]), 3) if no_slower else 0.0,
            "time_ratio_front": round(min(as_good) / r["ms_per_image"], 3) if as_good else 1.0}


# -------------------------------------------------------------------------------------- reports


def _f(x, d=2) -> str:
    return f"{x:.{d}f}"


def knob_paragraphs(res: dict) -> list[str]:
    """One paragraph per knob, written from the numbers: per value the PSNR change (dB) and time ratio
    against the own config on each target, the best value and whether the knob reaches the front."""
    out = []
    targets = res["targets"]
    for knob in (k for k in KNOBS if k != "own"):
        parts, notes = [], []
        for t in targets:
            rows = [r for r in t["rows"] if r["knob"] == knob and "same_as" not in r]
            if not rows:
                continue
            items = ", ".join(f"{r['label']} {r['d_psnr']:+.2f} dB / {r['time_ratio']:.2f}x" for r in rows)
            parts.append(f"{t['target']}: {items}")
            if knob == "chunk":
                fast = min(rows + [t["rows"][0]], key=lambda r: r["ms_per_image"])
                notes.append(f"{t['target']}: fastest chunk {fast['chunk']} ({fast['ms_per_image']:.0f} ms vs "
                             f"{t['rows'][0]['ms_per_image']:.0f} ms own)")
                continue
            span = rows + [t["rows"][0]]
            notes.append(f"{t['target']}: across its values (own included) PSNR spans "
                         f"{max(r['psnr'] for r in span) - min(r['psnr'] for r in span):.2f} dB and time "
                         f"{max(r['time_ratio'] for r in span) / min(r['time_ratio'] for r in span):.2f}x")
            best = max(rows, key=lambda r: r["psnr"])
            cheap = min(rows, key=lambda r: r["ms_per_image"])
            on = [r["label"] for r in rows if r["on_front"]]
            notes.append(f"{t['target']}: best {best['label']} ({best['d_psnr']:+.2f} dB at "
                         f"{best['time_ratio']:.2f}x), "
                         f"cheapest {cheap['label']} ({cheap['d_psnr']:+.2f} dB at {cheap['time_ratio']:.2f}x); "
                         + (f"on the front: {', '.join(on)}" if on else "none on the front"))
        if parts:
            out.append(f"**{knob}** ({KNOBS[knob]}). Against the own config (PSNR change / time ratio) — "
                       + "; ".join(parts) + ". " + "; ".join(notes) + ".")
    return out


def own_position(res: dict) -> list[str]:
    """Sentences placing the own config (the preset the model was trained with) relative to each front."""
    out = []
    for t in res["targets"]:
        rows = t["rows"]
        d = front_distance(rows, t["front"], 0)
        r = rows[0]
        which = f"the own config (`{res['preset']}`)"
        if d["on_front"]:
            out.append(f"{t['target']}: {which} is on the front ({r['psnr']:.2f} dB, {r['ms_per_image']:.0f} ms).")
        else:
            out.append(f"{t['target']}: {which} ({r['psnr']:.2f} dB, {r['ms_per_image']:.0f} ms) is off the front: "
                       f"the front gives {d['db_below_front']:.2f} dB more at no more time, or the same PSNR in "
                       f"{d['time_ratio_front']:.2f}x the time.")
    return out


def timing_noise(res: dict) -> list[str]:
    """The deterministic quadrature rules run the same program with other constant weights, so the
    spread of their measured times is a direct estimate of the timing noise."""
    out = []
    for t in res["targets"]:
        rows = [r for r in t["rows"] if r["integration"] == "segment" and r["knob"] in ("own", "rule")
                and "same_as" not in r]
        if len(rows) < 2:
            continue
        ms = [r["ms_per_image"] for r in rows]
        out.append(f"{t['target']}: the {len(rows)} deterministic rules (same work by construction) took "
                   f"{min(ms):.0f}-{max(ms):.0f} ms per image (max/min {max(ms) / min(ms):.2f}): time differences "
                   f"smaller than that are noise, and the front's order among settings of similar cost is too.")
    return out or ["(not measured: fewer than two rules in this run)"]


def summary_markdown(res: dict) -> str:
    L = [f"### Images: accuracy against time (`{res['command']}`)", "",
         f"Model `{res['run']}` (trained with preset `{res['preset']}`), edit `{res['edit']}` zero-shot with IST. "
         f"Measured on {res['machine']['platform']}, JAX {res['jax']} ({res['device']}); {SHARED_NOTE}. "
         f"Time per image: test view 0, minimum of {res['sizes']['repeats']} renders after a compiling call. "
         f"Study wall time {res['wall_s']:.0f} s.", ""]
    for t in res["targets"]:
        own = t["rows"][0]
        L += [f"#### {t['target']}: Pareto front", "",
              f"Test split {t['split']}; own config {own['psnr']:.2f} dB, SSIM {own['ssim']:.4f}, "
              f"{own['ms_per_image']:.0f} ms per image (compile {own['compile_s']:.1f} s).", "",
              "| setting | knob | PSNR | dPSNR | SSIM | ms / image | time / own | compile s |",
              "|---|---|---:|---:|---:|---:|---:|---:|"]
        for i in t["front"]:
            r = t["rows"][i]
            mark = " (own)" if i == 0 else ""
            L.append(f"| {r['label']}{mark} | {r['knob']} | {_f(r['psnr'])} | {r['d_psnr']:+.2f} | {r['ssim']:.4f} | "
                     f"{r['ms_per_image']:.0f} | {r['time_ratio']:.2f} | {r['compile_s']:.1f} |")
        grows = "overflow_rays" in t["rows"][0]  # results before it was recorded have no such column
        L += ["", f"<details><summary>all {len(t['rows'])} settings ({t['target']})</summary>", "",
              "| setting | knob | PSNR | SSIM | ms / image | compile s | lost segments |"
              + (" rays overflowing (view 0, before growth) |" if grows else "") + " front |",
              "|---|---|---:|---:|---:|---:|---:|" + ("---:|" if grows else "") + "---|"]
        for r in t["rows"]:
            note = f" (= {r['same_as']})" if "same_as" in r else (" (time only)" if r["time_only"] else "")
            L.append(f"| {r['label']}{note} | {r['knob']} | {_f(r['psnr'])} | {r['ssim']:.4f} | "
                     f"{r['ms_per_image']:.0f} | "
                     f"{r['compile_s']:.1f} | {r['lost_segments']} |" + (f" {r['overflow_rays']} |" if grows else "")
                     + f" {'yes' if r['on_front'] else ''} |")
        L += ["", "</details>", ""]
    L += ["#### Timing noise", ""] + [f"- {s}" for s in timing_noise(res)] + [""]
    L += ["#### Where the own config sits", ""] + [f"- {s}" for s in res["own_position"]] + [""]
    L += ["#### What each knob buys and costs", ""]
    for p in res["discussion"]:
        L += [p, ""]
    L += [f"Plot: `experiments/results/{stem(res['preset'])}.png`; numbers: "
          f"`experiments/results/{stem(res['preset'])}.json`.", ""]
    return "\n".join(L)


def _label_groups(front: list[dict], db: float) -> list[list[dict]]:
    """Front rows (fastest first) in groups whose points would overlap on the plot: within 15% in time
    and ``db`` in PSNR of the group's first row; one label per group."""
    groups: list[list[dict]] = []
    for r in front:
        g = groups[-1] if groups else None
        if g and r["ms_per_image"] <= 1.15 * g[0]["ms_per_image"] and abs(r["psnr"] - g[0]["psnr"]) <= db:
            g.append(r)
        else:
            groups.append([r])
    return groups


def plot(res: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    targets = res["targets"]
    fig, axes = plt.subplots(1, len(targets), figsize=(6.2 * len(targets), 4.8), squeeze=False)
    colors = {k: c for k, c in zip(KNOBS, plt.rcParams["axes.prop_cycle"].by_key()["color"] * 2)}
    for ax, t in zip(axes[0], targets):
        rows = t["rows"]
        for knob in KNOBS:
            sel = [r for r in rows if r["knob"] == knob and "same_as" not in r]
            if sel and knob != "own":
                ax.scatter([r["ms_per_image"] for r in sel], [r["psnr"] for r in sel], s=22, color=colors[knob],
                           label=knob, alpha=0.85)
        f = [rows[i] for i in t["front"]]
        ax.step([r["ms_per_image"] for r in f], [r["psnr"] for r in f], where="post", color="k", lw=1,
                label="Pareto front")
        own = rows[0]
        ax.scatter([own["ms_per_image"]], [own["psnr"]], marker="*", s=180, color="red", zorder=5,
                   label=f"own config ({res['preset']})")
        for g in _label_groups(f, 0.03 * (max(r["psnr"] for r in rows) - min(r["psnr"] for r in rows))):
            ax.annotate("\n".join(r["label"] for r in g), (g[0]["ms_per_image"], g[0]["psnr"]), fontsize=6,
                        xytext=(3, 3), textcoords="offset points", va="bottom")
        lo, hi = ax.get_ylim()
        ax.set_ylim(lo, hi + 0.12 * (hi - lo))  # room for the stacked labels above the front
        ax.set_xscale("log")
        ax.set_xlabel("ms per image (min of repeats, log)")
        ax.set_ylabel("test PSNR (dB)")
        ax.set_title(f"{t['target']}: {t['split']}", fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6, loc="center right")
    fig.suptitle("accuracy against time, one knob at a time (noisy shared 2-core CPU)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_results(res: dict, out_dir: Path) -> dict:
    """Derive the text (position of the own config, one paragraph per knob), then write the plot, the
    JSON and the Markdown under ``out_dir`` with the stem of ``res['preset']``."""
    from ne_jax.atomic import atomic_write_json, atomic_write_text

    res["own_position"] = own_position(res)
    res["discussion"] = knob_paragraphs(res)
    out_dir.mkdir(parents=True, exist_ok=True)
    base = stem(res["preset"])
    plot(res, out_dir / f"{base}.png")
    res["plots"] = [f"{base}.png"]
    atomic_write_json(out_dir / f"{base}.json", res)
    atomic_write_text(out_dir / f"{base}.md", summary_markdown(res))
    return res


def rewrite_summary(out_dir: Path, preset: str) -> dict:
    """Rewrite the Markdown (and the derived text in the JSON) and the plot from the JSON in ``out_dir``."""
    import json

    path = out_dir / f"{stem(preset)}.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no image study results for preset {preset!r} (run the study first)")
    return write_results(json.loads(path.read_text()), out_dir)


# ----------------------------------------------------------------------------------------- run


def run_image(run_dir: Path, out_dir: Path, command: str, edit: str = "bend", scene: Path | None = None,
              quick: bool = False, test_views: int | None = None, timing_passes: int | None = None,
              log=None) -> dict:
    """Load the model, edit it, measure both targets, write JSON, PNG and Markdown; returns the results."""
    import jax

    from ne_jax.benchmark.edits import benchmark_edit
    from ne_jax.data.nerf_synthetic import load_split
    from ne_jax.edit.model import edit_model
    from ne_jax.train.model import load_trained

    log = log or (lambda s: print(s, file=sys.stderr, flush=True))
    sz = ImageSizes.quick() if quick else ImageSizes.full()
    sz = dataclasses.replace(sz, test_views=test_views if test_views is not None else sz.test_views,
                             timing_passes=timing_passes if timing_passes is not None else sz.timing_passes)
    if sz.test_views is not None and sz.test_views < 1:
        raise ValueError(f"test_views: expected at least 1 test view, found {sz.test_views}")
    t0 = time.perf_counter()
    model = load_trained(run_dir)
    if scene is not None:
        model = dataclasses.replace(model, scene_dir=Path(scene))
    if model.scene_dir is None or not (Path(model.scene_dir) / "transforms_test.json").is_file():
        raise FileNotFoundError(f"{run_dir}: the recorded scene folder {model.scene_dir} has no test split; "
                                "pass --scene DIR")
    scene_dir = Path(model.scene_dir)
    truth = scene_dir / "edits" / edit
    if not (truth / "transforms_test.json").is_file():
        raise FileNotFoundError(f"edit {edit!r}: expected the edited scene's ground truth in {truth}")
    edited, edit_report = edit_model(model, benchmark_edit(scene_dir, edit)[0], ist=True, scene_dir=truth, label=edit)
    res = {"study": "image", "command": command, "sizes": dataclasses.asdict(sz), "run": str(run_dir),
           "preset": model.run.name, "edit": edit, "scene_dir": str(scene_dir),
           "edit_report": {k: v for k, v in edit_report.items() if isinstance(v, (int, float, str, bool))},
           "knobs": KNOBS,
           "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "note": SHARED_NOTE},
           "jax": jax.__version__, "device": str(jax.devices()[0]), "targets": []}
    for name, m, d in (("original", model, scene_dir), ("edit", edited, truth)):
        t1 = time.perf_counter()
        split = load_split(d, "test")
        split = split.take(evenly_spaced(split.num_views, sz.test_views))
        res["targets"].append(measure_target(name, m, split, sz, log))
        res["targets"][-1]["wall_s"] = round(time.perf_counter() - t1, 1)
    res["wall_s"] = round(time.perf_counter() - t0, 1)
    return write_results(res, out_dir)


__all__ = ["ImageSizes", "Setting", "evenly_spaced", "front_distance", "knob_paragraphs", "measure_target",
           "own_position", "pareto_front", "rewrite_summary", "run_image", "settings_for", "stem",
           "summary_markdown", "timing_noise", "write_results"]

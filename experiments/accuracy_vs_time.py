"""What accuracy costs in time: the preset and one-knob changes of it, each trained from scratch and
scored with its own render config, and the preset chosen from the Pareto fronts
(docs/studies/accuracy_vs_time.md).

    python -m experiments.accuracy_vs_time --scene DIR [--preset tiny] [--runs DIR] [--quick]
        [--candidates full|short] [--train-only I [I ...]] [--finished-only]
    python -m experiments.accuracy_vs_time --summary-only --preset tiny   # the rule applied again, no training

Runs are cached in ``--runs`` under :func:`run_key` (a re-run trains only what is missing), test scores
in each run's :data:`SCORE_FILE`; the time per image is measured again at every scoring. Writes
``accuracy_vs_time_training_<preset>_<scene>.{json,png,md}`` to ``--out-dir``, then the summary over
every scene studied there, ``accuracy_vs_time_training_<preset>.{json,png,md}`` (:func:`combine_scenes`).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import sys
import time
from pathlib import Path

from experiments.common import RESULTS, SHARED_NOTE, cached_run, entry, machine, time_test_render
from experiments.common import log as common_log
from ne_jax.config_json import config_key

TWO_PASS_SHARE = 0.25
"""Retry share of the two-pass candidate: the smallest that kept 50 training steps of the `default`
glossy model bit for bit (docs/decisions.md, the two-pass walk)."""

BUDGET = 1.25
"""A preset may cost at most this many times its current training time and time per image."""


def _scaled_samples(spl: tuple[int, ...], f: float) -> tuple[int, ...]:
    """Samples per level scaled by ``f``, at least 2 each."""
    return tuple(max(2, int(round(s * f))) for s in spl)


def pareto_front(rows: list[dict], time_key: str = "ms_per_image") -> list[int]:
    """Indices of the rows no other row beats (``time_key`` <= and PSNR >=, one strictly), fastest first."""
    front = [i for i, a in enumerate(rows)
             if not any(b[time_key] <= a[time_key] and b["psnr"] >= a["psnr"]
                        and (b[time_key] < a[time_key] or b["psnr"] > a["psnr"]) for j, b in enumerate(rows) if j != i)]
    return sorted(front, key=lambda i: rows[i][time_key])


@dataclasses.dataclass(frozen=True)
class Candidate:
    label: str
    knob: str
    run: object  # RunConfig


CANDIDATE_SETS = ("full", "short")
"""``full``: every one-knob change (for ``tiny``: minutes per model); ``short``: the few that matter
most where a model takes an hour (``default``). Both end with the frontier and two-pass candidates,
which change only ``RunConfig.capacities`` (told apart by :func:`run_key`). New candidates go at the
end, so the indices of ``--train-only`` keep naming the same runs."""


def run_key(run) -> str:
    """The name of ``run``'s cached run directory: its :func:`~ne_jax.config_json.config_key` and a
    hash of the buffer sizes it starts with (``RunConfig.capacities``, left out of the config key), so
    candidates that differ only there (the frontier and two-pass candidates) train apart."""
    return f"{config_key(run)}-cap{config_key(run.capacities)[:6]}"


def candidates_for(run, quick: bool = False, candidate_set: str = "full") -> list[Candidate]:
    """The preset ``run`` and one-knob changes of it (``quick``: two short ones, for the smoke test;
    ``candidate_set``: see :data:`CANDIDATE_SETS`)."""
    from ne_jax.geometry.capacity import Capacities
    from ne_jax.geometry.kdtree import KDTreeConfig
    from ne_jax.render.quadrature import QuadratureConfig

    if candidate_set not in CANDIDATE_SETS:
        raise ValueError(f"candidate_set: expected one of {CANDIDATE_SETS}, found {candidate_set!r}")
    t, q, cap = run.render.kdtree, run.render.quadrature, run.capacities
    spl = tuple(q.samples_per_level)

    def with_k(k, cfg=run):
        """K = ``k``; a candidate set too narrow for it is widened to ``k``."""
        tree = cfg.render.kdtree
        wider = {"candidate_min": k} if k > tree.num_candidates else {}
        return cfg.replace(render=cfg.render.replace(kdtree=tree.replace(knn_k=k, **wider)))

    def k_label(k):
        return f"K={k}" + (f" ({k} candidates)" if k > t.num_candidates else "")

    def with_s(f, cfg=run):
        rq = cfg.render.quadrature
        return cfg.replace(render=cfg.render.replace(
            quadrature=dataclasses.replace(rq, samples_per_level=_scaled_samples(tuple(rq.samples_per_level), f))))

    narrow = cap.replace(frontier=max(2, cap.frontier // 4), first_pass_frontier=None)
    narrow_frontier = Candidate(f"frontier={narrow.frontier}", "frontier", run.replace(capacities=narrow))
    two = cap.replace(first_pass_frontier=narrow.frontier, retry_share=TWO_PASS_SHARE)
    two_pass = [] if two == cap else [  # a preset that walks this way already has no such candidate
        Candidate(f"two-pass frontier ({two.first_pass_frontier} then {cap.frontier}, "
                  f"retry share 1/{round(1 / TWO_PASS_SHARE)})", "two-pass", run.replace(capacities=two))]
    if quick:
        return [Candidate("own", "own", run), Candidate(f"K={max(1, t.knn_k // 2)}", "k", with_k(max(1, t.knn_k // 2)))]
    out = [Candidate("own", "own", run), Candidate("own, seed 1", "seed", run.replace(seed=run.seed + 1))]
    for k in (t.knn_k // 2, 2 * t.knn_k):
        if k >= 1:
            out.append(Candidate(k_label(k), "k", with_k(k)))
    if candidate_set == "short":
        out.append(Candidate("steps x0.5", "steps", run.with_schedule(steps_per_epoch=run.steps_per_epoch // 2)))
        paper_tree, paper_q = KDTreeConfig(), QuadratureConfig()
        if (t, q) != (paper_tree, paper_q):
            # walked as the paper's tree config walked before the buffer sizes left it: one pass with
            # the default frontier and slots (the preset's packing budget kept)
            paper_cap = Capacities(segments_per_ray=cap.segments_per_ray)
            paper = run.replace(render=run.render.replace(kdtree=paper_tree, quadrature=paper_q), capacities=paper_cap)
            levels = paper_tree.num_render_levels
            label = (f"paper sampling (K={paper_tree.knn_k}, {paper_tree.candidate_min} candidates, "
                     f"{levels} levels, s {paper_q.samples_per_level[:levels]})")
            out.append(Candidate(label, "paper", paper))
            out.append(Candidate("paper sampling, steps x0.25", "paper",
                                 paper.with_schedule(steps_per_epoch=max(1, run.steps_per_epoch // 4))))
        half = t.replace(candidate_min=t.num_candidates // 2, knn_k=min(t.knn_k, t.num_candidates // 2))
        if half.num_candidates < t.num_candidates:
            out.append(Candidate(f"{half.num_candidates} candidates (K={half.knn_k})", "candidates",
                                 run.replace(render=run.render.replace(kdtree=half))))
        return out + [narrow_frontier] + two_pass
    # s only downwards: part 2 found the segment integral converged at the presets' s (s x2: +0.00 dB)
    out.append(Candidate(f"s x0.5 {_scaled_samples(spl, 0.5)[:t.num_render_levels]}", "samples", with_s(0.5)))
    joint = with_s(0.5, with_k(2 * t.knn_k))
    out.append(Candidate(f"{k_label(2 * t.knn_k)}, s x0.5", "joint", joint))
    out.append(Candidate(f"{k_label(2 * t.knn_k)}, s x0.5, steps x0.5", "joint",
                         joint.with_schedule(steps_per_epoch=run.steps_per_epoch // 2)))
    for f in (0.5, 2.0):
        out.append(Candidate(f"steps x{f:g}", "steps", run.with_schedule(steps_per_epoch=int(run.steps_per_epoch * f))))
    out.append(Candidate(f"batch x2 ({2 * run.sampler.batch_size} rays)", "batch",
                         run.replace(sampler=run.sampler.replace(batch_size=2 * run.sampler.batch_size))))
    carve = run.init.carve
    out.append(Candidate(f"initial points x2 ({2 * carve.num_points})", "points",
                         run.replace(init=dataclasses.replace(run.init, carve=dataclasses.replace(
                             carve, num_points=2 * carve.num_points)))))
    return out + [narrow_frontier] + two_pass


def is_finished(run, runs: Path) -> bool:
    """Whether ``run``'s cached run in ``runs`` has trained all its epochs."""
    from ne_jax.train.model import METRICS_FILE

    metrics = Path(runs) / run_key(run) / METRICS_FILE
    return metrics.is_file() and len(json.loads(metrics.read_text())["epochs"]) >= run.epochs


SCORE_FILE = "study_score.json"
"""In a run's folder: its last test PSNR/SSIM and what they depend on (see :func:`score_key`)."""


@functools.lru_cache(maxsize=1)
def library_fingerprint() -> str:
    """A hash of the ``ne_jax`` package's source files: a kept score is stale once the library changes.
    Computed once per process (every candidate's score key uses it)."""
    import hashlib

    import ne_jax

    root = Path(ne_jax.__file__).parent
    h = hashlib.sha256()
    for f in sorted(root.rglob("*.py")):
        h.update(str(f.relative_to(root)).encode() + b"\0" + f.read_bytes())
    return h.hexdigest()[:16]


def score_key(scene_dir: Path, step: int) -> dict:
    """What a run's test score depends on besides the run: the scene's test split (path and the time its
    transforms file was written), the run's step and the library's source."""
    transforms = Path(scene_dir).resolve() / "transforms_test.json"
    return {"scene": str(transforms.parent), "transforms_mtime_ns": transforms.stat().st_mtime_ns,
            "step": int(step), "library": library_fingerprint()}


def measure_candidate(c: Candidate, scene_dir: Path, runs: Path, repeats: int, log) -> dict:
    """Train (or reuse) the candidate's run and score it on the test split."""
    import jax
    import numpy as np

    from ne_jax.atomic import atomic_write_json
    from ne_jax.data.nerf_synthetic import load_split
    from ne_jax.eval.views import evaluate_split

    run = c.run
    run_dir = runs / run_key(run)
    cached = is_finished(run, runs)
    result = cached_run(run, scene_dir, run_dir)
    split = load_split(scene_dir, "test")
    key = score_key(scene_dir, result.state.step)
    # rendered with the buffer sizes the run starts with, not the ones its training grew to (as in
    # the image study): the frontier candidates are scored and timed at their own width
    scene = result.scene.replace(capacities=run.capacities)
    kept = json.loads((run_dir / SCORE_FILE).read_text()) if (run_dir / SCORE_FILE).is_file() else {}
    score_cached = all(kept.get(k) == v for k, v in key.items())
    if not score_cached:
        report, _ = evaluate_split(run.render, result.state.params, scene, split, run.background, run.sampler.near,
                                   run.sampler.far, progress=False)
        kept = {**key, "psnr": round(report["psnr"], 4), "ssim": round(report["ssim"], 5)}
        atomic_write_json(run_dir / SCORE_FILE, kept)
    first, best = time_test_render(run, result.state.params, scene, split.cameras()[0], repeats)
    jax.clear_caches()
    row = {"label": c.label, "knob": c.knob, "run_dir": str(run_dir), "cached": bool(cached),
           "score_cached": score_cached, "psnr": kept["psnr"], "ssim": kept["ssim"],
           "train_s": round(result.recorded_seconds, 1), "ms_per_image": round(1e3 * best, 2),
           "compile_s": round(max(0.0, first - best), 3), "steps": int(result.state.step),
           "batch_size": run.sampler.batch_size, "knn_k": run.render.kdtree.knn_k,
           "samples_per_level": list(run.render.quadrature.samples_per_level),
           "initial_points": int(result.initial.get("points", 0)),
           "final_points": int(np.asarray(result.scene.points.alive).sum()),
           "capacities": {"start": dataclasses.asdict(run.capacities),  # training grows them where it lost segments
                          "end": dataclasses.asdict(result.scene.capacities)}}
    log(f"[{c.label}] PSNR {row['psnr']:.2f} dB, SSIM {row['ssim']:.4f}, train {row['train_s']:.0f} s"
        f"{' (cached run)' if cached else ''}, {row['ms_per_image']:.0f} ms per image"
        f"{' (kept score)' if score_cached else ''}")
    return row


def choose_preset(rows: list[dict], budget: float = BUDGET, noise: float | None = None) -> dict:
    """The preset rule applied to ``rows`` (row 0 the preset itself): among the candidates within
    ``budget`` x the preset's training time and time per image, the best PSNR sets the bar; the pick
    is the cheapest to train of those within the training noise of that bar (``noise``, by default
    the spread of the seed rows). A seed row is the preset itself and only measures the noise: it is
    never the pick."""
    own = rows[0]
    affordable = [i for i, r in enumerate(rows) if r["train_s"] <= budget * own["train_s"]
                  and r["ms_per_image"] <= budget * own["ms_per_image"]]
    if noise is None:
        seeds = [r["psnr"] for r in rows if r["knob"] in ("own", "seed")]
        noise = max(seeds) - min(seeds) if len(seeds) > 1 else None
    best = max(rows[i]["psnr"] for i in affordable)
    level = [i for i in affordable if rows[i]["psnr"] >= best - (noise or 0.0) and rows[i]["knob"] != "seed"]
    pick = min(level, key=lambda i: (rows[i]["train_s"], i))
    return {"pick": pick, "label": rows[pick]["label"], "gain_db": round(rows[pick]["psnr"] - own["psnr"], 3),
            "train_ratio": round(rows[pick]["train_s"] / own["train_s"], 3), "best_affordable_db": best,
            "seed_noise_db": None if noise is None else round(noise, 3), "confirmed": pick == 0,
            "budget": budget, "train_front": pareto_front(rows, time_key="train_s"),
            "render_front": pareto_front(rows)}


def summary_markdown(res: dict) -> str:
    rows, ch = res["rows"], res["choice"]
    own = rows[0]
    L = [f"### Trained settings: accuracy against time (`{res['command']}`)", "",
         f"Scene `{res['scene']}`, preset `{res['preset']}` and one-knob changes of it, each trained from "
         f"scratch and scored on the test split ({res['split']}) with its own render config. Measured on "
         f"{res['machine']['platform']}, JAX {res['jax']}; {SHARED_NOTE}. Study wall time {res['wall_s']:.0f} s "
         f"(cached runs are reused; their training time is the one recorded when they were trained).", "",
         "| candidate | PSNR | dPSNR | SSIM | train s | train / own | ms / image | image / own | points | fronts |",
         "|---|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
    for i, r in enumerate(rows):
        L.append(f"| {r['label']} | {r['psnr']:.2f} | {r['psnr'] - own['psnr']:+.2f} | {r['ssim']:.4f} | "
                 f"{r['train_s']:.0f} | {r['train_s'] / own['train_s']:.2f} | {r['ms_per_image']:.0f} | "
                 f"{r['ms_per_image'] / own['ms_per_image']:.2f} | {r['final_points']} | {_fronts(ch, i)} |")
    noise = ch["seed_noise_db"]
    L += _unfinished_lines(res)
    L += ["", f"Training noise: the preset with another seed differs by {noise:.2f} dB." if noise is not None
          else "Training noise: not measured (no second seed).", "",
          _rule_text(ch, res["preset"], f"the best PSNR ({ch['best_affordable_db']:.2f} dB)", "On this scene the"),
          "", f"Plot: `{_stem(res['preset'], Path(res['scene']).name)}.png` (next to this file).", ""]
    return "\n".join(L)


def _unfinished_lines(res: dict, why: str = "Not trained yet, so left out of this interim result") -> list[str]:
    left = res.get("unfinished")
    return ["", f"{why}: {'; '.join(left)}."] if left else []


def _fronts(ch: dict, i: int) -> str:
    return "/".join(x for x, f in (("train", ch["train_front"]), ("image", ch["render_front"])) if i in f)


def _rule_text(ch: dict, preset: str, bar: str, scope: str, name: str = "Preset rule") -> str:
    return (f"{name}: among the candidates within {ch['budget']:g}x the preset's training time and time per "
            f"image, {bar} sets the bar; the pick is the cheapest to train within the training noise of it. "
            f"Pick: **{ch['label']}** ({ch['gain_db']:+.2f} dB, {ch['train_ratio']:.2f}x the training time). "
            + (f"The `{preset}` preset is confirmed." if ch["confirmed"] else f"{scope} `{preset}` preset should "
               "change to it."))


def plot(res: dict, path: Path, axes_keys=(("train_s", "training wall time (s)"),
                                            ("ms_per_image", "ms per test image (min of repeats)")),
         title: str | None = None) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker  # noqa: F401  (matplotlib.ticker below)

    rows, ch = res["rows"], res["choice"]
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.6))
    for ax, (key, xlabel), front in zip(axes, axes_keys, (ch["train_front"], ch["render_front"])):
        for knob in dict.fromkeys(r["knob"] for r in rows):
            sel = [r for r in rows if r["knob"] == knob]
            ax.scatter([r[key] for r in sel], [r["psnr"] for r in sel], s=26, label=knob, alpha=0.85)
        f = sorted((rows[i] for i in front), key=lambda r: r[key])
        ax.step([r[key] for r in f], [r["psnr"] for r in f], where="post", color="k", lw=1, label="Pareto front")
        ax.scatter([rows[0][key]], [rows[0]["psnr"]], marker="*", s=200, color="red", zorder=5,
                   label=f"preset {res['preset']}")
        pick = rows[ch["pick"]]
        ax.scatter([pick[key]], [pick["psnr"]], marker="o", s=160, facecolors="none", edgecolors="k", zorder=6,
                   label="rule's pick")
        for r in rows:
            ax.annotate(r["label"], (r[key], r["psnr"]), fontsize=6, xytext=(3, 3), textcoords="offset points")
        ax.set_xscale("log")
        ax.xaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
        ax.xaxis.set_minor_formatter(matplotlib.ticker.ScalarFormatter())
        ax.tick_params(axis="x", which="minor", labelsize=6)
        ax.set_xlabel(xlabel + ", log")
        ax.set_ylabel(res.get("psnr_label", "test PSNR (dB)"))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6)
    fig.suptitle(title or f"{res['preset']} preset on {Path(res['scene']).name}: each point a model trained "
                 f"with that setting (noisy shared 2-core CPU)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _stem(preset: str, scene: str | None = None) -> str:
    return f"accuracy_vs_time_training_{preset}" + (f"_{scene}" if scene else "")


def _write(out_dir: Path, stem: str, res: dict, markdown: str, **plot_args) -> None:
    from ne_jax.atomic import atomic_write_json, atomic_write_text

    out_dir.mkdir(parents=True, exist_ok=True)
    plot(res, out_dir / f"{stem}.png", **plot_args)
    atomic_write_json(out_dir / f"{stem}.json", res)
    atomic_write_text(out_dir / f"{stem}.md", markdown)


def _preset_key(study: dict) -> str | None:
    """The key of the study's preset run (:func:`run_key`; older results: the name of its own run directory)."""
    first = study["rows"][0]
    return study.get("preset_key") or (Path(first["run_dir"]).name if "run_dir" in first else None)


def scene_results(out_dir: Path, preset: str, key: str | None = None) -> list[dict]:
    """Every per-scene study of ``preset`` in ``out_dir`` (sorted by scene); with ``key``, only the
    studies of that preset config (a preset re-chosen since keeps its name, not its hash)."""
    files = sorted(Path(out_dir).glob(f"{_stem(preset)}_*.json"))
    studies = [r for r in (json.loads(f.read_text()) for f in files) if r.get("preset") == preset]
    return [r for r in studies if key is None or _preset_key(r) == key]


def combine_scenes(out_dir: Path, preset: str, key: str | None = None) -> dict | None:
    """The summary over the per-scene studies in ``out_dir`` (of the preset config ``key``, if given):
    per candidate (those every scene has), the mean over scenes of its PSNR change against the
    preset and of its training and image time ratios; the rule applied to those means, with the mean
    seed difference as the noise. Writes ``accuracy_vs_time_training_<preset>.{json,md,png}``; None
    when no scene was studied.

    Raises ValueError when the studies are of different configs of the preset and no ``key`` says
    which to combine."""
    studies = scene_results(out_dir, preset, key)
    if not studies:
        return None
    keys = {_preset_key(s) for s in studies}
    if len(keys) > 1:
        found = ", ".join(f"{Path(st['scene']).name}: {_preset_key(st)}" for st in studies)
        raise ValueError(f"{out_dir}: the `{preset}` studies there are of {len(keys)} different preset configs "
                         f"({found}); re-run the older scenes or move them to another --out-dir")
    by_scene = [{r["label"]: r for r in s["rows"]} for s in studies]
    labels = [r["label"] for r in studies[0]["rows"] if all(r["label"] in b for b in by_scene)]
    rows = []
    for lab in labels:
        per = [(b[lab]["psnr"] - s["rows"][0]["psnr"], b[lab]["train_s"] / s["rows"][0]["train_s"],
                b[lab]["ms_per_image"] / s["rows"][0]["ms_per_image"]) for s, b in zip(studies, by_scene)]
        d, t, m = (sum(x) / len(per) for x in zip(*per))
        rows.append({"label": lab, "knob": by_scene[0][lab]["knob"], "psnr": round(d, 4), "train_s": round(t, 4),
                     "ms_per_image": round(m, 4), "per_scene_db": [round(p[0], 3) for p in per]})
    seeds = [r["per_scene_db"] for r in rows if r["knob"] == "seed"]
    noise = sum(abs(x) for x in seeds[0]) / len(seeds[0]) if seeds else None
    res = {"study": "training-summary", "preset": preset, "scenes": [Path(s["scene"]).name for s in studies],
           "commands": [s["command"] for s in studies], "psnr_label": "mean test PSNR change vs preset (dB)",
           "rows": rows}
    seen = dict.fromkeys(lab for s in studies for lab in [r["label"] for r in s["rows"]] + s.get("unfinished", []))
    res["unfinished"] = [lab for lab in seen if lab not in labels]  # not (yet) scored on every scene
    res["choice"] = choose_preset(rows, noise=noise)
    _write(Path(out_dir), _stem(preset), res, combined_markdown(res),
           axes_keys=(("train_s", "mean training time / preset's"), ("ms_per_image", "mean time per image / preset's")),
           title=f"{preset} preset, mean over {len(studies)} scene(s) ({', '.join(res['scenes'])}): "
                 f"each point a setting, each scene trained from scratch")
    return res


def combined_markdown(res: dict) -> str:
    rows, ch = res["rows"], res["choice"]
    scenes = res["scenes"]
    L = [f"### Trained settings over {len(scenes)} scene(s): `{res['preset']}` preset", "",
         f"Each candidate trained from scratch on each scene ({', '.join(scenes)}) and scored with its own render "
         "config; dPSNR is against the preset on the same scene, time ratios against the preset's on the same "
         "scene, then averaged over the scenes. Per-scene tables: "
         + ", ".join(f"`{_stem(res['preset'], s)}.md`" for s in scenes) + ".", "",
         "| candidate | " + " | ".join(f"d {s}" for s in scenes)
         + " | mean dPSNR | train / own | image / own | fronts |",
         "|---|" + "---:|" * (len(scenes) + 3) + "---|"]
    for i, r in enumerate(rows):
        L.append(f"| {r['label']} | " + " | ".join(f"{d:+.2f}" for d in r["per_scene_db"])
                 + f" | {r['psnr']:+.2f} | {r['train_s']:.2f} | {r['ms_per_image']:.2f} | {_fronts(ch, i)} |")
    noise = ch["seed_noise_db"]
    L += _unfinished_lines(res, "Left out of the means (not scored on every scene yet)")
    L += ["", f"Training noise: the second seed differs from the preset by {noise:.2f} dB on average over the "
          "scenes." if noise is not None else "Training noise: not measured (no second seed).", "",
          _rule_text(ch, res["preset"], f"the best mean change ({ch['best_affordable_db']:+.2f} dB)", "The",
                     name="Preset rule on the means"),
          "", f"Plot: `{_stem(res['preset'])}.png` (next to this file).", ""]
    return "\n".join(L)


def rewrite_summary(out_dir: Path, preset: str) -> dict:
    """Re-apply the rule to every per-scene JSON in ``out_dir`` and rewrite their Markdown and plots,
    then the summary over scenes (returned)."""
    studies = scene_results(out_dir, preset)
    if not studies:
        raise FileNotFoundError(f"--out-dir {out_dir}: expected {_stem(preset)}_<scene>.json from a training "
                                "study, found none")
    for res in studies:
        res["choice"] = choose_preset(res["rows"])
        _write(Path(out_dir), _stem(preset, Path(res["scene"]).name), res, summary_markdown(res))
    return combine_scenes(out_dir, preset)


def run_training(scene_dir: Path, runs: Path, out_dir: Path, command: str, preset: str = "tiny",
                 quick: bool = False, run=None, log=None, candidate_set: str = "full",
                 train_only: list[int] | None = None, finished_only: bool = False) -> dict | None:
    """Train and score every candidate, write JSON, PNG and Markdown; returns the results.

    ``run``: the base RunConfig instead of the preset ``preset`` (named by its ``name``); ``quick``
    with no ``run``: the preset cut to 2 epochs of 5 steps without rounds. ``train_only``: only train
    (or resume) the candidates at these indices, with a progress bar, and write nothing else (returns
    None): hour-long candidates train in parallel processes, then one plain call scores them all.
    ``finished_only``: score only the candidates whose runs have finished (the preset's own must have)
    and record the others under ``unfinished``."""
    import jax

    from ne_jax.data.nerf_synthetic import load_split
    from ne_jax.train.run import get_run_preset

    log = log or common_log
    scene_dir = Path(scene_dir)
    if not (scene_dir / "transforms_test.json").is_file():
        raise FileNotFoundError(f"--scene {scene_dir}: expected a scene folder with transforms_test.json, found none")
    if run is None:
        run = get_run_preset(preset)
        if quick:
            run = run.with_schedule(epochs=2, steps_per_epoch=5).replace(round_epochs=(1, 0))  # no rounds
    preset = run.name
    cands = candidates_for(run, quick, candidate_set)
    if train_only is not None:
        from ne_jax.train.loop import train

        bad = [i for i in train_only if not 0 <= i < len(cands)]
        if bad:
            raise IndexError(f"train_only: expected candidate indices in 0..{len(cands) - 1}, found {bad}")
        for i in train_only:
            run_dir = Path(runs) / run_key(cands[i].run)
            log(f"[{i}: {cands[i].label}] training in {run_dir}")
            train(cands[i].run, scene_dir, run_dir, resume=True, log=log)
        return None
    unfinished = []
    if finished_only:
        finished = [is_finished(c.run, runs) for c in cands]  # cands[0] is the preset's own run
        if not finished[0]:
            raise FileNotFoundError(f"finished_only: the preset's own run {Path(runs) / run_key(run)} has not "
                                    f"finished training; train it first (train_only=[0])")
        unfinished = [c.label for c, done in zip(cands, finished) if not done]
        cands = [c for c, done in zip(cands, finished) if done]
        if unfinished:
            log(f"not trained yet, left out: {'; '.join(unfinished)}")
    t0 = time.perf_counter()
    rows = [measure_candidate(c, scene_dir, Path(runs), 1 if quick else 3, log) for c in cands]
    split = load_split(scene_dir, "test")
    res = {"study": "training", "command": command, "preset": preset, "preset_key": run_key(run),
           "scene": str(scene_dir), "quick": quick,
           "split": f"{split.name} ({split.num_views} views, {split.width}x{split.height})",
           "machine": machine(note=SHARED_NOTE), "jax": jax.__version__, "rows": rows, "unfinished": unfinished,
           "wall_s": round(time.perf_counter() - t0, 1), "choice": choose_preset(rows)}
    _write(Path(out_dir), _stem(preset, scene_dir.name), res, summary_markdown(res))
    others = [Path(r["scene"]).name for r in scene_results(out_dir, preset) if _preset_key(r) != res["preset_key"]]
    if others:
        log(f"summary over scenes: leaving out {', '.join(others)} (studied with another `{preset}` config)")
    combine_scenes(Path(out_dir), preset, key=res["preset_key"])
    return res


PRESETS = ("tiny", "default", "paper")


def main(argv=None) -> int:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", type=Path, help="the scene folder to train on (required unless --summary-only)")
    ap.add_argument("--preset", default="tiny", choices=PRESETS, help="the preset whose candidates are trained")
    ap.add_argument("--runs", type=Path, help="folder of the cached runs (default runs/avt_training/<scene>)")
    ap.add_argument("--out-dir", type=Path, default=RESULTS)
    ap.add_argument("--quick", action="store_true", help="the preset cut to 2 epochs of 5 steps, two candidates")
    ap.add_argument("--candidates", choices=CANDIDATE_SETS,
                    help="which candidates (default: full for tiny, short for the hour-long presets)")
    ap.add_argument("--train-only", type=int, nargs="+", metavar="I",
                    help="only train these candidates (indices; parallel processes), write nothing")
    ap.add_argument("--finished-only", action="store_true",
                    help="score only the candidates whose runs have finished (an interim result)")
    ap.add_argument("--summary-only", action="store_true",
                    help="apply the rule again to the results in --out-dir and rewrite them (no training)")
    args = ap.parse_args(argv)
    if args.summary_only:
        print(combined_markdown(rewrite_summary(args.out_dir, args.preset)))
        return 0
    if args.scene is None:
        print("the study needs a scene to train on: pass --scene DIR", file=sys.stderr)
        return 2
    runs = args.runs or Path("runs") / "avt_training" / args.scene.name
    cset = args.candidates or ("full" if args.preset == "tiny" else "short")
    command = " ".join(["python -m experiments.accuracy_vs_time --scene", str(args.scene), "--preset", args.preset,
                        "--runs", str(runs), "--candidates", cset]
                       + (["--quick"] if args.quick else []) + (["--finished-only"] if args.finished_only else []))
    res = run_training(args.scene, runs, args.out_dir, command, preset=args.preset, quick=args.quick,
                       candidate_set=cset, train_only=args.train_only, finished_only=args.finished_only)
    if res is not None:
        print(summary_markdown(res))
    return 0


if __name__ == "__main__":
    entry(main)

"""What the experiment modules share: paths, provenance, the entry point, the speed benchmarks' test
scene and timing loop, and writing results."""

from __future__ import annotations

import math
import os
import platform
import re
import shlex
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
"""The repository root."""
RESULTS = ROOT / "experiments" / "results"
"""Where results files go by default."""
SHARED_NOTE = ("2 CPU cores shared with other jobs: timings are noisy (minimum over repeats, "
               "compile excluded); ratios from one process are more reliable than absolute values")
SCENE = "glossy"
"""The benchmark scene the speed benchmarks run on (specular: the models declare view-dependent colour)."""


def entry(main, huge_pages: bool = True) -> None:
    """A module's ``if __name__ == "__main__"`` block: the process set up as ``ne-jax`` sets it up
    (``ne_jax.setup``: a host device per usable core and, with ``huge_pages``, huge pages for XLA's
    scratch memory, starting the process again with them), then ``main()``, whose return value is
    the exit status. The module's imports, before it, start no JAX. (An older ``ne_jax`` without
    ``setup``, run by :func:`json_from`, set its process up at import.)"""
    import ne_jax

    if hasattr(ne_jax, "setup"):
        ne_jax.setup(huge_pages=huge_pages)
    sys.exit(main())


def log(message: str) -> None:
    """A progress line on stderr, at once."""
    print(message, file=sys.stderr, flush=True)


def machine(python: bool = False, **extra) -> dict:
    """What a results file records of the machine: its CPU count and platform (with ``python``, Python's
    version), then ``extra``."""
    return {"cpus": os.cpu_count(), "platform": platform.platform(),
            **({"python": platform.python_version()} if python else {}), **extra}


def commit(paths: tuple[str, ...] = ("ne_jax",)) -> str:
    """Short ``HEAD`` commit, with `` (<paths> modified)`` when tracked files under ``paths`` differ."""
    from ne_jax import provenance

    head = provenance.commit(short=True)
    return head + (f" ({', '.join(paths)} modified)" if provenance.modified(*paths) else "")


def command(module: str, argv: list[str] | None = None) -> str:
    """The command that re-runs ``experiments.<module>`` with ``argv`` (default: this process's)."""
    name = module.rsplit(".", 1)[-1]
    args = sys.argv[1:] if argv is None else argv
    return " ".join(["python", "-m", f"experiments.{name}", *map(shlex.quote, args)])


def best_time(fn, repeats: int) -> tuple[float, float]:
    """``(first_call_s, best_s)``: the first call (compiles) and the minimum of ``repeats`` more."""
    return best_of(fn, 1), best_of(fn, repeats)


def best_of(fn, repeats: int) -> float:
    """The minimum over ``max(1, repeats)`` calls of ``fn``, in seconds (each waited for)."""
    import jax

    best = math.inf
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - t0)
    return best


def bench_cloud(n: int, feature_dim: int, headroom: float = 1.0, spread: float | None = None):
    """The speed benchmarks' test scene: ``n`` surface samples (seed 0) of the benchmark's :data:`SCENE`
    with their normals, as a :class:`~ne_jax.geometry.points.PointState` of ``ceil(n x headroom)``
    slots. Its features are ``PointState.from_numpy``'s from key 0, or with ``spread`` ``spread x N(0,
    1)`` from key 0 with confidence logits 2 (a random model: a render costs the same whatever the
    weights)."""
    import jax
    import jax.numpy as jnp

    from ne_jax.benchmark import scenes as S
    from ne_jax.geometry.points import PointState

    smp = S.surface_samples(S.get_scene(SCENE, 1.0), n, seed=0)
    xyz, normal, capacity = smp["xyz"], smp["normal"], int(math.ceil(n * headroom))
    if spread is None:
        return PointState.from_numpy(xyz, capacity, feature_dim, normal=normal, key=jax.random.key(0))
    pts = PointState.from_numpy(xyz, capacity, feature_dim, normal=normal)
    return pts.replace(feature=spread * jax.random.normal(jax.random.key(0), pts.feature.shape),
                       conf_logit=jnp.full(pts.conf_logit.shape, 2.0))


def time_test_render(run, params, scene, camera, repeats: int, mesh=None) -> tuple[float, float]:
    """``(first_call_s, best_s)`` (:func:`best_time`) of ``run``'s render of ``camera`` at test time
    (its quadrature :func:`~ne_jax.render.quadrature.at_test_time`), on its background, near and far."""
    from ne_jax.data.nerf_synthetic import parse_background
    from ne_jax.render.driver import render_image
    from ne_jax.render.quadrature import at_test_time

    cfg = run.render.replace(quadrature=at_test_time(run.render.quadrature))
    bg, near, far = parse_background(run.background), run.sampler.near, run.sampler.far
    return best_time(lambda: render_image(cfg, params, scene, camera, bg, near, far, progress=False, mesh=mesh).rgb,
                     repeats)


def timed_steps(step, state, scene, batches) -> tuple:
    """Run the jitted training ``step`` over ``batches`` (the first compiles): ``(state after, s per
    step after the first, s of the first, lost)`` with ``lost`` what the steps lost to ``scene``'s
    capacities (:class:`~ne_jax.geometry.capacity.LostCounts`, summed over all steps). The counts are
    read after the clock stops: a read each step would wait for the device."""
    import jax

    from ne_jax.train.loop import lost_counts

    counts = []
    t0 = time.perf_counter()
    for i, batch in enumerate(batches):
        state, m = step(state, scene, batch)
        counts.append({k: v for k, v in m.items() if k.startswith("lost/")})
        if i == 0:
            jax.block_until_ready(state.params)
            first = time.perf_counter() - t0
            t0 = time.perf_counter()
    jax.block_until_ready(state.params)
    per_step = (time.perf_counter() - t0) / max(1, len(batches) - 1)
    return state, per_step, first, lost_counts(jax.device_get(counts))


def time_steps(run, model, pool, scene, steps: int) -> dict:
    """``steps`` training steps of ``run``'s config from ``model``'s parameters and cloud (``model.state``,
    ``model.scene``) on batches drawn from ``pool``, the packing budget fitted as training fits it: time
    per step and per ray, the compile, the segments lost and the first batch's segments per ray, and the
    run's projected training time (steps x time per step, no point-cloud rounds)."""
    import jax
    import numpy as np

    from ne_jax.geometry.intersect import intersect
    from ne_jax.train.sampler import sample_batch
    from ne_jax.train.state import init_train_state
    from ne_jax.train.step import make_train_step

    key = jax.random.PRNGKey(0)
    points = model.state.point_state(model.scene.points)
    state = init_train_state(run.train, run.render, points, key, total_steps=run.total_steps).replace(
        params=model.state.params)
    train_render = run.train_render
    batches = [sample_batch(run.sampler, pool, jax.random.fold_in(key, i), train_render.pixel_samples)
               for i in range(steps + 1)]
    scene = scene.fitted(train_render, batches[0].rays)  # the packing budget, as training fits it
    step = make_train_step(run.train, train_render, total_steps=run.total_steps)
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

def json_from(module: str, args: list[str], checkout, env: dict | None = None) -> dict:
    """The JSON object ``python -m experiments.<module> *args`` prints last, run in a fresh process (its
    environment ``env``, default this one's) with the ``ne_jax`` of ``checkout`` (a checkout of older
    code, or :data:`ROOT`) and this checkout's :mod:`experiments` (from a folder holding only a link to
    it, first on the path)."""
    import json
    import subprocess
    import tempfile

    env = dict(os.environ if env is None else env)
    env["PYTHONPATH"] = str(checkout) + os.pathsep + env.get("PYTHONPATH", "")
    with tempfile.TemporaryDirectory() as here:
        (Path(here) / "experiments").symlink_to(ROOT / "experiments")
        res = subprocess.run([sys.executable, "-m", f"experiments.{module}", *args], env=env, cwd=here,
                             capture_output=True, text=True)
    if res.returncode != 0:
        raise RuntimeError(f"experiments.{module} with {checkout}'s ne_jax failed:\n{res.stderr[-4000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def against_reference(measure, rounds: int) -> dict[str, list]:
    """``{"reference": [...], "new": [...]}``: ``measure(name)`` ``rounds`` times for each, the one that
    goes first alternating, so that the load of a shared machine hits both alike."""
    out = {"reference": [], "new": []}
    for i in range(rounds):
        for name in ("reference", "new")[:: -1 if i % 2 else 1]:
            out[name].append(measure(name))
            print(name, out[name][-1], flush=True)
    return out


def device_tag() -> str:
    """``cpu``, or the accelerator JAX runs on as a file-name part (``nvidia_h100_80gb_hbm3``): benchmarks
    name their results after it, so a GPU's timings never overwrite the CPU's."""
    import jax

    dev = jax.devices()[0]
    return "cpu" if dev.platform == "cpu" else re.sub(r"[^a-z0-9]+", "_", dev.device_kind.lower()).strip("_")


RENDERER_SUFFIX = {"raycast": "", "pathtrace": "_pt"}
"""The results-name suffix of each ground-truth renderer: a training preset's results on the
path-traced benchmark (``tiny_pt``) go to ``<stem>_tiny_pt``, next to the ray-cast ``<stem>_tiny``."""


def benchmark_suffix(root: Path, scenes: list[str]) -> str:
    """The results-name suffix (:data:`RENDERER_SUFFIX`) of the benchmark folder ``root``, from the
    renderer the first of ``scenes`` with a ``scene.json`` records (a ray-cast preset records none);
    ``""`` when no scene has one yet."""
    import json

    for name in scenes:
        meta = Path(root) / name / "scene.json"
        if meta.is_file():
            renderer = json.loads(meta.read_text(encoding="utf-8"))["preset"].get("renderer", "raycast")
            if renderer not in RENDERER_SUFFIX:
                raise ValueError(f"{meta}: renderer {renderer!r} has no results-name suffix; expected one of "
                                 f"{sorted(RENDERER_SUFFIX)}")
            return RENDERER_SUFFIX[renderer]
    return ""


def write_results(out_dir: Path, stem: str, res: dict, md: str, echo: bool = True) -> None:
    """``<out_dir>/<stem>.json`` and ``.md``, each written whole or not at all; ``md`` printed with ``echo``.

    ``res`` should carry ``command`` and the config key(s) it measured; ``commit`` is added if missing."""
    from ne_jax.atomic import atomic_write_json, atomic_write_text

    res.setdefault("commit", commit())
    out_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out_dir / f"{stem}.json", res)
    atomic_write_text(out_dir / f"{stem}.md", md)
    if echo:
        print(md)


def cached_run(run, scene_dir: Path, run_dir: Path):
    """The model ``run`` trains on ``scene_dir`` in ``run_dir``: trained there if not finished yet,
    else loaded at once (``train`` resumes a finished run by returning it)."""
    from ne_jax.train.loop import train

    return train(run, scene_dir, run_dir, resume=True, progress=False, log=lambda s: None)

"""How cost grows with the work: the training step, the ray pool, a test render and a point-cloud round
of the ``default`` preset on the benchmark's ``glossy`` scene (its surface samples as the cloud, an
untrained colour model), each axis (:func:`axes`) varied alone from one reference (:data:`REFERENCE`;
docs/devices.md).

    python -m experiments.cost_growth [--steps 3] [--repeats 3] [--render-repeats 2] [--scene-root DIR] [--quick]

Each axis measures its own reference row (a shared machine's load drifts); each row has the ratio of
its cost to that row's, the ratio of the work (:func:`work`) and their quotient: above 1, the cost
grows faster. Scenes as :mod:`experiments.gpu_check` makes them, in ``--scene-root``. Writes
``cost_growth.{json,md}`` (``cost_growth_<device>`` on an accelerator, ``cost_growth_quick`` with
``--quick``, a smoke test at toy sizes) to ``--out-dir``.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import os
import time
from pathlib import Path

from experiments import common
from experiments.common import SCENE, best_time, timed_steps
from experiments.gpu_check import SCENE_ROOT, peak_memory, presets, scene_dir, sizes

REFERENCE = {"batch": 2048, "image": 200, "cloud": 100_000, "depth": 17, "render": 200, "round": 100_000}


@dataclasses.dataclass(frozen=True)
class Axes:
    """The values each axis takes (the reference is :data:`REFERENCE`'s, or the first); ``images``: scene
    presets (:class:`~ne_jax.benchmark.generate.BenchmarkPreset`), one per image size."""

    batch: tuple[int, ...]
    images: tuple[object, ...]
    clouds: tuple[int, ...]
    depths: tuple[int, ...]
    grow_rays: int
    quick: bool


def axes(quick: bool) -> Axes:
    """Rays a batch; image sizes (the pool, a batch from it, a step on it, a test render); cloud sizes (a
    step, the tree's depth fitted, and a round); the tree's depth at the reference cloud."""
    from ne_jax.benchmark.generate import BenchmarkPreset

    if quick:
        tiny = sizes(True)
        return Axes(batch=(128, 256), images=(tiny.small, tiny.large), clouds=(1_500, 3_000), depths=(11, 12),
                    grow_rays=128, quick=True)
    full = sizes(False)
    mid = BenchmarkPreset("cost_growth_400", 400, 100, 1, 1, 1, 1.0, 100_000)
    return Axes(batch=(1024, 2048, 4096, 8192), images=(full.small, mid, full.large),
                clouds=(100_000, 300_000, 1_000_000), depths=(17, 18, 19, 20, 21), grow_rays=8192, quick=False)


# ---------------------------------------------------------------- memory


def _status(field: str) -> int | None:
    """``field`` of ``/proc/self/status`` in bytes (``None`` off Linux)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(field + ":"):
                    return int(line.split()[1]) * 1024
    except OSError:
        return None
    return None


class Peak:
    """The process's peak resident memory over a ``with`` block (``VmHWM``, reset through
    ``/proc/self/clear_refs``), less what it held at the start (``VmRSS``): ``.delta_mib`` (and
    ``.peak_mib``); ``None`` where Linux's counters cannot be read or reset. ``.device_peak_mib``: a
    GPU's ``peak_bytes_in_use`` so far (not reset)."""

    def __enter__(self):
        try:
            with open("/proc/self/clear_refs", "w") as f:
                f.write("5")  # resets VmHWM to the current VmRSS
            self.base = _status("VmRSS")
        except OSError:
            self.base = None
        return self

    def __exit__(self, *exc):
        peak = _status("VmHWM") if self.base is not None else None
        self.peak_mib = None if peak is None else round(peak / 2**20, 1)
        self.delta_mib = None if peak is None else round((peak - self.base) / 2**20, 1)
        device = peak_memory()["device_peak_bytes"]
        self.device_peak_mib = None if device is None else round(device / 2**20, 1)
        return False

    def record(self) -> dict:
        return {"peak_mib": self.peak_mib, "delta_mib": self.delta_mib, "device_peak_mib": self.device_peak_mib}


# ---------------------------------------------------------------- the pieces


@functools.lru_cache(maxsize=8)
def _step_fn(train, render, total_steps):
    """The jitted step on one device (a mesh of one: a plain ``jax.jit``, whose program XLA analyses)."""
    from ne_jax.devices import ray_mesh
    from ne_jax.train.step import make_train_step

    return make_train_step(train, render, ray_mesh(1), total_steps=total_steps)


def program_memory(compiled) -> dict:
    """XLA's memory analysis of a compiled program in MiB: ``program_mib`` (arguments, outputs and
    temporaries, less what outputs alias) and each part (``None`` where the backend gives none)."""
    m = compiled.memory_analysis()
    parts = ("argument", "output", "temp", "alias")
    if m is None:
        return {"program_mib": None, **{f"{k}_mib": None for k in parts}}
    mib = {k: getattr(m, f"{k}_size_in_bytes") / 2**20 for k in parts}
    total = mib["argument"] + mib["output"] + mib["temp"] - mib["alias"]
    return {"program_mib": round(total, 1), **{f"{k}_mib": round(v, 1) for k, v in mib.items()}}


def step_cost(run, points, pool, steps: int, repeats: int, compiled: dict | None = None) -> dict:
    """``run``'s training step on ``points`` with batches from ``pool``: ms per step (best of
    ``repeats`` blocks of ``steps`` after an uncounted one), the ahead-of-time compile and its program's
    memory, the tree's depth and build time, the process's memory. ``compiled``: the caller's programs
    by configs and shapes, reused and added to (a row whose step another row compiled compiles nothing)."""
    import jax

    from ne_jax.render.renderer import PointScene
    from ne_jax.train.sampler import sample_batch
    from ne_jax.train.state import init_train_state

    with Peak() as peak:
        t0 = time.perf_counter()
        scene = PointScene.build(points, run.render, run.capacities)
        build_s = time.perf_counter() - t0
        render = run.train_render
        key = jax.random.key(0)
        batches = [sample_batch(run.sampler, pool, jax.random.fold_in(key, i), render.pixel_samples)
                   for i in range(steps + 1)]
        scene = scene.fitted(render, batches[0].rays)
        state = init_train_state(run.train, run.render, points, jax.random.key(1), total_steps=run.total_steps)
        t0 = time.perf_counter()
        compiled = {} if compiled is None else compiled
        key = (run.train, run.total_steps, render, points.capacity, int(scene.tree.depth), run.sampler.batch_size,
               scene.capacities)
        if key not in compiled:
            compiled[key] = _step_fn(run.train, render, run.total_steps).lower(state, scene, batches[0]).compile()
        step = compiled[key]
        compile_s = time.perf_counter() - t0
        state, best, first, lost = timed_steps(step, state, scene, batches)
        for _ in range(repeats - 1):
            state, per, _, _ = timed_steps(step, state, scene, batches)
            best = min(best, per)
    return {"ms": round(1e3 * best, 2), "compile_s": round(compile_s, 1), "tree_depth": int(scene.tree.depth),
            "tree_build_s": round(build_s, 2), "segments_lost": lost.total, **program_memory(step),
            **peak.record()}


def pool_cost(run, scene: Path, repeats: int) -> tuple[object, dict]:
    """The ray pool of ``scene``'s training split: ``(pool, {build_s, bytes, pixels, sample_ms, memory})``."""
    import jax

    from ne_jax.data.nerf_synthetic import load_split
    from ne_jax.train.sampler import build_pool, sample_batch

    split = load_split(scene, "train")
    with Peak() as peak:
        t0 = time.perf_counter()
        pool = jax.block_until_ready(build_pool(run.sampler, split, run.background))
        build_s = time.perf_counter() - t0
    device_bytes = sum(int(a.nbytes) for a in jax.tree_util.tree_leaves(pool))
    draw = lambda: sample_batch(run.sampler, pool, jax.random.key(3), run.train_render.pixel_samples).rays.origin  # noqa: E731
    _, sample_s = best_time(draw, repeats)
    images_bytes = int(split.images.nbytes)
    del split
    return pool, {"pixels": pool.width * pool.height * int(pool.c2w.shape[0]), "foreground": pool.num_foreground,
                  "build_s": round(build_s, 2), "device_bytes": device_bytes, "images_host_bytes": images_bytes,
                  "sample_ms": round(1e3 * sample_s, 3), **peak.record()}


def render_cost(run, params, points, scene: Path, repeats: int) -> dict:
    """Test view 0 of ``scene`` rendered at test time with ``run``'s render config."""
    from ne_jax.data.nerf_synthetic import load_split
    from ne_jax.devices import ray_mesh
    from ne_jax.render.renderer import PointScene

    view = load_split(scene, "test").take([0])
    built = PointScene.build(points, run.render, run.capacities)
    with Peak() as peak:
        first, best = common.time_test_render(run, params, built, view.camera(0), repeats, mesh=ray_mesh(1))
    rays = view.width * view.height * run.render.pixel_samples ** 2
    return {"px": view.width, "rays": rays, "ms": round(1e3 * best, 1), "compile_s": round(max(0.0, first - best), 1),
            "rays_per_s": round(rays / best), **peak.record()}


def round_cost(run, params, points, pool, views, grow_rays: int) -> dict:
    """The round's stages on ``points`` (each timed on its second run; the scan's first compiles) and
    the tree rebuild."""
    import jax

    from ne_jax.pointcloud.rounds import denoise_points, grow_points, prune_points, refresh_normals
    from ne_jax.render.renderer import PointScene
    from ne_jax.train.sampler import sample_batch

    rays = sample_batch(run.sampler.replace(batch_size=grow_rays), pool, jax.random.key(5)).rays
    out = {}
    with Peak() as peak:
        t0 = time.perf_counter()
        scene = PointScene.build(points, run.render, run.capacities)
        out["tree_build_s"] = round(time.perf_counter() - t0, 2)
        stages = {"grow_s": lambda: grow_points(run.rounds, run.train_render, params, scene, rays, pool.background,
                                                views=views)[0],
                  "prune_s": lambda: prune_points(run.rounds, points)[0],
                  "denoise_s": lambda: denoise_points(run.rounds, points)[0],
                  "normals_s": lambda: refresh_normals(points, views, run.normals)}
        for name, fn in stages.items():
            out[name] = round(best_time(lambda f=fn: f().xyz, 1)[1], 2)
    out["round_s"] = round(sum(v for k, v in out.items() if k != "tree_build_s"), 2)
    return {**out, "tree_depth": int(scene.tree.depth), **peak.record()}


# ---------------------------------------------------------------- the study


def study(a: Axes, scene_root: Path, steps: int, repeats: int, render_repeats: int, log=print) -> dict:
    import jax

    from ne_jax.data.nerf_synthetic import load_split
    from ne_jax.pointcloud.init import Views
    from ne_jax.train.run import INIT_CAPACITY_HEADROOM
    from ne_jax.train.state import init_train_state

    t_start = time.perf_counter()
    run = presets(sizes(a.quick))["default"]  # the preset, or a toy one with --quick
    scenes = [scene_dir(p, scene_root, log) for p in a.images]
    ref_points = a.clouds[0]
    pts = {n: common.bench_cloud(n, run.render.shading.feature_dim, INIT_CAPACITY_HEADROOM) for n in a.clouds}
    params = init_train_state(run.train, run.render, pts[ref_points], jax.random.key(1),
                              total_steps=run.total_steps).params
    rows, compiled = [], {}

    def add(axis, value, what, **fields):
        rows.append({"axis": axis, "value": value, "what": what, **fields})
        log(f"[{time.perf_counter() - t_start:6.0f} s] {axis} {value} {what}: "
            + ", ".join(f"{k} {v}" for k, v in fields.items()))

    # image: the pools first (the 200 px one serves every other axis)
    pools = {}
    for preset, scene in zip(a.images, scenes):
        pools[preset.resolution], info = pool_cost(run, scene, repeats)
        add("image", preset.resolution, "pool", **info)
    ref_pool = pools[a.images[0].resolution]
    for px, pool in pools.items():
        add("image", px, "step", **step_cost(run, pts[ref_points], pool, steps, repeats, compiled))
    for b in a.batch:
        add("batch", b, "step", **step_cost(run.replace(sampler=run.sampler.replace(batch_size=b)), pts[ref_points],
                                            ref_pool, steps, repeats, compiled))
    for n in a.clouds:  # the reference again (compiled already): the load on a shared machine drifts
        add("cloud", n, "step", **step_cost(run, pts[n], ref_pool, steps, repeats, compiled))
    for d in a.depths:
        fixed = run.replace(render=run.render.replace(kdtree=run.render.kdtree.replace(depth=d)))
        add("depth", d, "step", **step_cost(fixed, pts[ref_points], ref_pool, steps, repeats, compiled))
    for preset, scene in zip(a.images, scenes):
        add("render", preset.resolution, "render", **render_cost(run, params, pts[ref_points], scene, render_repeats))
    views = Views.from_split(load_split(scenes[0], "train"))
    for n in a.clouds:
        add("round", n, "round", **round_cost(run, params, pts[n], ref_pool, views, a.grow_rays))
    rows = with_ratios(rows, a)
    dev = jax.devices()[0]
    return {"preset": run.name, "scene": SCENE, "steps": steps, "repeats": repeats, "render_repeats": render_repeats,
            "reference": references(a),
            "device": {"platform": dev.platform, "kind": dev.device_kind, "count": len(jax.devices())},
            "machine": common.machine(load_before=os.getloadavg()), "jax": jax.__version__, "note": common.SHARED_NOTE,
            "seconds": round(time.perf_counter() - t_start), "rows": rows}


# the field that holds each kind of row's cost
COST = {"step": "ms", "render": "ms", "pool": "device_bytes", "round": "round_s"}


def references(a: Axes) -> dict:
    """The reference value of each axis: :data:`REFERENCE`'s, or each axis's first at ``--quick``."""
    if not a.quick:
        return dict(REFERENCE)
    return {"batch": a.batch[0], "image": a.images[0].resolution, "cloud": a.clouds[0], "depth": a.depths[0],
            "render": a.images[0].resolution, "round": a.clouds[0]}


def work(row: dict, ref: dict) -> float:
    """How much more work ``row`` does than its axis's reference: rays (batch), pixels (the pool, a
    render), tree levels (depth), points (a round); a step's rays do not change with the image size
    or the cloud (1)."""
    axis, v = row["axis"], row["value"]
    if row["what"] == "step" and axis in ("image", "cloud"):
        return 1.0
    if axis in ("image", "render"):
        return (v / ref[axis]) ** 2
    return v / ref[axis]


def with_ratios(rows: list[dict], a: Axes) -> list[dict]:
    """Each row with ``ratio`` (its cost over its axis's reference row's), ``work`` (:func:`work`)
    and ``growth`` (ratio / work); a round row also has each stage's ratio."""
    ref = references(a)
    for r in rows:
        axis = r["axis"]
        base = next(x for x in rows if x["axis"] == axis and x["what"] == r["what"] and x["value"] == ref[axis])
        key = COST[r["what"]]
        r["ratio"] = round(r[key] / base[key], 3) if base[key] else None
        r["work"] = round(work(r, ref), 3)
        r["growth"] = None if r["ratio"] is None else round(r["ratio"] / r["work"], 3)
        if r["what"] == "round":
            for k in ("grow_s", "prune_s", "denoise_s", "normals_s", "tree_build_s"):
                r[k[:-2] + "_ratio"] = round(r[k] / base[k], 2) if base[k] else None
    return rows


def markdown(res: dict) -> str:
    d = res["device"]
    L = [f"How cost grows, `{res['preset']}` preset on `{res['scene']}` ({d['kind']}, {d['count']} device(s), jax "
         f"{res['jax']}, {res['machine']['cpus']} CPUs; load before {res['machine']['load_before'][0]:.1f}): commit "
         f"{res['commit']}, `{res['command']}`, {res['seconds']} s. Reference: {res['reference']['batch']} rays a "
         f"batch, {res['reference']['cloud']} points, depth {res['reference']['depth']}, "
         f"{res['reference']['image']} px. Steps: best of "
         f"{res['repeats']} blocks of {res['steps']}; renders best of {res['render_repeats']}. Memory: a step's "
         "program (XLA's memory analysis) and the process's peak resident memory over each measurement less what "
         "it held before (RSS growth; memory freed earlier and kept by the allocator hides some). ratio: cost over "
         "the axis's reference; work: the same for rays, pixels, points or levels; growth = ratio / work. "
         + res["note"] + ".",
         "", "| axis | value | what | cost | ratio | work | growth | program (MiB) | RSS growth (MiB) | notes |",
         "|---|---:|---|---:|---:|---:|---:|---:|---:|---|"]
    for r in res["rows"]:
        if r["what"] == "pool":
            cost, notes = (f"{r['device_bytes'] / 2**20:.0f} MiB on the device", f"build {r['build_s']} s, "
                           f"{r['foreground']} foreground of {r['pixels']} pixels, images "
                           f"{r['images_host_bytes'] / 2**20:.0f} MiB on the host, a batch {r['sample_ms']} ms")
        elif r["what"] == "round":
            cost = f"{r['round_s']} s"
            notes = (f"grow {r['grow_s']} s ({r['grow_ratio']}x), prune {r['prune_s']} s, denoise {r['denoise_s']} s "
                     f"({r['denoise_ratio']}x), normals {r['normals_s']} s ({r['normals_ratio']}x), tree rebuild "
                     f"{r['tree_build_s']} s ({r['tree_build_ratio']}x), depth {r['tree_depth']}")
        elif r["what"] == "render":
            cost, notes = f"{r['ms']:.0f} ms", f"{r['rays']} rays, {r['rays_per_s']} rays/s, compile {r['compile_s']} s"
        else:
            cost = f"{r['ms']:.1f} ms"
            notes = (f"depth {r['tree_depth']}, tree build {r['tree_build_s']} s, compile {r['compile_s']} s, program: "
                     f"arguments {r['argument_mib']}, outputs {r['output_mib']}, temporaries {r['temp_mib']} MiB, "
                     f"{r['segments_lost']} segments lost")
        L.append(f"| {r['axis']} | {r['value']} | {r['what']} | {cost} | {r['ratio']} | {r['work']} | {r['growth']} | "
                 f"{r.get('program_mib', '')} | {r['delta_mib']} | {notes} |")
    return "\n".join(L) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=3, help="timed steps per block")
    ap.add_argument("--repeats", type=int, default=3, help="blocks of steps (and batch draws); the best counts")
    ap.add_argument("--render-repeats", type=int, default=2, help="timed renders after a compiling one")
    ap.add_argument("--scene-root", type=Path, default=SCENE_ROOT,
                    help="where the scenes are kept (generated there if missing; needs Open3D)")
    ap.add_argument("--out-dir", type=Path, default=common.RESULTS)
    ap.add_argument("--quick", action="store_true", help="toy sizes (a smoke test)")
    args = ap.parse_args(argv)
    if min(args.steps, args.repeats, args.render_repeats) < 1:
        raise SystemExit("--steps, --repeats, --render-repeats: expected at least 1 each")
    res = study(axes(args.quick), args.scene_root, args.steps, args.repeats, args.render_repeats, log=common.log)
    res.update(command=common.command("cost_growth", argv), commit=common.commit())
    tag = common.device_tag()
    stem = "cost_growth_quick" if args.quick else ("cost_growth" if tag == "cpu" else f"cost_growth_{tag}")
    common.write_results(args.out_dir, stem, res, markdown(res))
    return 0


if __name__ == "__main__":
    common.entry(main)

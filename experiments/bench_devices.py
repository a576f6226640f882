"""One host device against one per core: the ``tiny`` preset's training step and a test-image render,
timed in one run.

    python -m experiments.bench_devices                   # 1 device, one per core, two per core
    python -m experiments.bench_devices --rounds 1 --extra 0

``ne_jax.setup()`` (called by ``ne-jax`` and by this module's entry point) gives JAX one host
device per usable core (``ne_jax/_platform.py``) and the rays split over them;
``NE_JAX_HOST_DEVICES=1`` opts out. The device count is fixed per process, so each setting runs in
its own Python process: ``1`` (``NE_JAX_HOST_DEVICES=1``), ``default`` (nothing set: what
``ne_jax.setup()`` chooses) and, with ``--extra`` (default 2), ``extra x cores``
devices. Each process builds the same randomly initialised ``tiny`` model (the preset's render,
train and sampler configs; a bumpy-sphere cloud of the preset's 20,000 points) and measures

* training: ``--steps`` jitted steps on batches of the preset's 1,024 rays, after a compiling
  step: seconds per step (best of ``--repeats`` blocks);
* rendering: a ``--res`` x ``--res`` test image (the tiny benchmark's 64 x 64 by default) with
  ``render_image``: best of ``--repeats`` after a compiling call;

with the process's CPU time over wall time while timing (how many cores it kept busy) and its
thread count (XLA:CPU's intra-op pool is per process, so more devices should not mean many more
threads). The settings run ``--rounds`` times in turn (1, default, extra, 1, default, ...), so a
change in the machine's load shows as a difference between rounds; ratios are against the ``1``
device row of the same round. Other jobs on the machine share the cores: the 1-minute load average
before each process is recorded with it. Writes ``experiments/results/bench_devices.{json,md}``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"


def worker(steps: int, res: int, repeats: int) -> dict:
    import jax
    import jax.numpy as jnp

    from ne_jax._platform import usable_cores  # the count: ne_jax.setup() in the entry point, before this
    from ne_jax.benchmark.generate import get_preset
    from ne_jax.data.cameras import orbit_cameras
    from ne_jax.data.rays import Camera, camera_rays
    from ne_jax.devices import default_mesh
    from ne_jax.geometry.points import PointState
    from ne_jax.render.driver import render_image
    from ne_jax.render.renderer import PointScene
    from ne_jax.train import init_train_state, make_train_step
    from ne_jax.train.run import INIT_CAPACITY_HEADROOM, get_run_preset
    from ne_jax.train.sampler import Batch

    run = get_run_preset("tiny")
    points = run.init.carve.num_points
    capacity = int(points * INIT_CAPACITY_HEADROOM)
    batch = run.sampler.batch_size
    rng = np.random.default_rng(0)
    x = rng.normal(size=(points, 3))
    x = 0.9 * x / np.linalg.norm(x, axis=1, keepdims=True) * (1 + 0.03 * rng.normal(size=(points, 1)))
    normal = x / np.linalg.norm(x, axis=1, keepdims=True)
    pts = PointState.from_numpy(x, capacity, run.render.shading.feature_dim, normal=normal, key=jax.random.key(0))
    scene = PointScene.build(pts, run.render, run.capacities)
    state = init_train_state(run.train, run.render, pts, jax.random.key(1))
    near, far = run.sampler.near, run.sampler.far
    test_res = get_preset("tiny").resolution
    cameras = [Camera.from_fov(jnp.asarray(c, jnp.float32), test_res, test_res, 0.7) for c in orbit_cameras(8, 25.0)]
    pool = jax.tree_util.tree_map(lambda *a: jnp.concatenate(a), *[camera_rays(c, near, far) for c in cameras])
    bg = jnp.ones(3, jnp.float32)

    def make_batch(i):
        idx = np.random.default_rng(100 + i).integers(0, pool.num_rays, batch)
        rays = jax.tree_util.tree_map(lambda a: a[idx], pool)
        target = jnp.concatenate([jnp.asarray(rng.uniform(size=(batch, 3)), jnp.float32), jnp.ones((batch, 1))], 1)
        return Batch(rays=rays.replace(target=target), pixel=jnp.asarray(idx, jnp.int32),
                     in_band=jnp.zeros(batch, bool), background=bg)

    batches = [make_batch(i) for i in range(steps)]
    train_scene = scene.fitted(run.train_render, batches[0].rays)  # the packing budget, as training fits it
    step = make_train_step(run.train, run.train_render)
    cpu_wall = []

    def timed(fn):
        t0, c0 = time.perf_counter(), time.process_time()
        jax.block_until_ready(fn())
        wall = time.perf_counter() - t0
        cpu_wall.append((time.process_time() - c0, wall))
        return wall

    holder = {"state": state}

    def train_block():
        s = holder["state"]
        for b in batches:
            s, _ = step(s, train_scene, b)
        holder["state"] = s
        return s.params

    t0 = time.perf_counter()
    jax.block_until_ready(step(state, train_scene, batches[0])[0].params)
    step_first = time.perf_counter() - t0
    step_best = min(timed(train_block) for _ in range(repeats)) / steps
    train_cpu = sum(c for c, _ in cpu_wall) / sum(w for _, w in cpu_wall)

    cpu_wall.clear()
    camera = Camera.from_fov(jnp.asarray(orbit_cameras(1, 25.0)[0], jnp.float32), res, res, 0.7)
    image = lambda: render_image(run.render, state.params, scene, camera, bg, near, far, progress=False).rgb  # noqa: E731
    t0 = time.perf_counter()
    jax.block_until_ready(image())
    render_first = time.perf_counter() - t0
    render_best = min(timed(image) for _ in range(repeats))
    render_cpu = sum(c for c, _ in cpu_wall) / sum(w for _, w in cpu_wall)
    return {
        "devices": default_mesh().devices.size, "platform": jax.devices()[0].platform, "cores": usable_cores(),
        "train_batch": batch, "train_s_per_step": round(step_best, 4), "train_compile_s": round(step_first, 1),
        "train_cpu_per_wall": round(train_cpu, 2), "render_res": res, "render_s": round(render_best, 4),
        "render_compile_s": round(render_first, 1), "render_cpu_per_wall": round(render_cpu, 2),
        "threads": len(os.listdir("/proc/self/task")) if os.path.isdir("/proc/self/task") else None,
    }


def main(argv=None) -> None:
    from ne_jax import provenance

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=10, help="training steps per timed block")
    ap.add_argument("--res", type=int, default=64, help="test-image size (default: the tiny benchmark's 64)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--rounds", type=int, default=2, help="times the settings run in turn")
    ap.add_argument("--extra", type=int, default=2, help="also run extra x cores devices (0: not)")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        print(json.dumps(worker(args.steps, args.res, args.repeats)))
        return
    from ne_jax._platform import ENV, usable_cores

    cores = usable_cores()
    settings = [("1", "1"), ("default", None)]
    if args.extra:
        settings.append((f"{args.extra}x cores", str(args.extra * cores)))
    base_env = {k: v for k, v in os.environ.items() if k not in (ENV, "XLA_FLAGS", "JAX_NUM_CPU_DEVICES")}
    base_env["JAX_PLATFORMS"] = "cpu"
    rows = []
    t_start = time.perf_counter()
    for rnd in range(1, args.rounds + 1):
        for label, count in settings:
            env = dict(base_env, **({ENV: count} if count else {}))
            load = os.getloadavg()[0]
            cmd = [sys.executable, __file__, "--worker", "--steps", str(args.steps), "--res", str(args.res),
                   "--repeats", str(args.repeats)]
            out = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
            if out.returncode != 0:
                raise SystemExit(f"worker {label!r} failed:\n{out.stderr[-3000:]}")
            row = {"round": rnd, "setting": label, "load_before": round(load, 2),
                   **json.loads(out.stdout.strip().splitlines()[-1])}
            rows.append(row)
            print(row, flush=True)
    for r in rows:
        one = next(b for b in rows if b["round"] == r["round"] and b["setting"] == "1")
        r["train_speedup"] = round(one["train_s_per_step"] / r["train_s_per_step"], 2)
        r["render_speedup"] = round(one["render_s"] / r["render_s"], 2)
    command = "python -m experiments.bench_devices " + " ".join(
        f"--{k} {v}" for k, v in vars(args).items() if k != "worker")
    modified = provenance.modified()
    dirty = bool(modified)
    report = {"what": "tiny training step and test-image render: 1 host device vs one per core (ne_jax's default)",
              "commit": provenance.commit(), "worktree_modified": modified, "command": command,
              "seconds": round(time.perf_counter() - t_start, 1), "rows": rows,
              "machine": {"usable_cores": cores, "cpu_count": os.cpu_count(), "platform": platform.platform(),
                          "python": platform.python_version()},
              "shared": "other jobs ran on the same cores; load_before: the 1-minute load average before each process"}
    RESULTS.mkdir(exist_ok=True)
    from ne_jax.atomic import atomic_write_json, atomic_write_text

    atomic_write_json(RESULTS / "bench_devices.json", report)
    lines = [f"`tiny` preset, 1 host device against one per core ({cores} usable cores, {rows[0]['platform']}): "
             f"training step of {rows[0]['train_batch']} rays and a {args.res} x {args.res} test-image render. "
             f"Commit {report['commit'][:12]}{' (work tree modified: ' + ', '.join(modified) + ')' if dirty else ''}; "
             f"re-run: `{command}`. "
             f"Other jobs shared the cores (load: the 1-minute load average before each process).", "",
             "| round | setting | devices | load | train s/step | vs 1 | train CPU/wall | render s | vs 1 | "
             "render CPU/wall | threads | compile step / render (s) |",
             "|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
    for r in rows:
        lines.append(f"| {r['round']} | {r['setting']} | {r['devices']} | {r['load_before']} | "
                     f"{r['train_s_per_step']} | {r['train_speedup']} | {r['train_cpu_per_wall']} | {r['render_s']} | "
                     f"{r['render_speedup']} | {r['render_cpu_per_wall']} | {r['threads']} | "
                     f"{r['train_compile_s']} / {r['render_compile_s']} |")
    atomic_write_text(RESULTS / "bench_devices.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    import ne_jax

    ne_jax.setup(huge_pages=True)  # as `ne-jax` does: a host device per core, huge pages (restarts)
    main()

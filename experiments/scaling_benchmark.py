"""Throughput on 1, 2 and 4 devices (rays split over a device mesh, :mod:`ne_jax.devices`), and the
memory per ray and per point.

    python -m experiments.scaling_benchmark                 # 1, 2, 4 forced host devices (CPU)
    python -m experiments.scaling_benchmark --devices 1 8   # other counts

Each device count runs in its own process (``XLA_FLAGS=--xla_force_host_platform_device_count=N``
must be set before JAX starts) on the same randomly initialised model (a tiny-preset colour model,
a bumpy-sphere cloud of ``--points`` points): render throughput (rays per second of
``render_chunked`` over an image's rays, deterministic rule) and training throughput (rays per second
of the jitted step on ``--batch`` rays), both the best of ``--repeats`` after a compiling call, plus
the single-device ratio. On a GPU machine the same script measures the real devices
(``--platform gpu``: no forcing). Memory: XLA's own memory analysis of the compiled chunk and step
(temporary buffers, per ray) and the bytes of the point state and K-D tree (per point).

Forced host devices share the machine's CPU cores: on 2 cores, 4 "devices" cannot be faster than 2;
the figures show the overhead of the sharded code path, not a speed-up a real mesh would give.
Writes ``experiments/results/scaling.{json,md}``.
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


def worker(points: int, batch: int, res: int, repeats: int) -> dict:
    import jax
    import jax.numpy as jnp

    from ne_jax.data.cameras import orbit_cameras
    from ne_jax.data.rays import Camera, camera_rays
    from ne_jax.devices import default_mesh
    from ne_jax.geometry.capacity import Capacities
    from ne_jax.geometry.kdtree import KDTreeConfig
    from ne_jax.geometry.points import PointState
    from ne_jax.render.quadrature import QuadratureConfig
    from ne_jax.render.renderer import (
        PointScene,
        RenderConfig,
        _render_chunk,
        render_chunked,
    )
    from ne_jax.train import TrainConfig, init_train_state, make_train_step
    from ne_jax.train.sampler import Batch

    rng = np.random.default_rng(0)
    x = rng.normal(size=(points, 3))
    x = 0.9 * x / np.linalg.norm(x, axis=1, keepdims=True) * (1 + 0.03 * rng.normal(size=(points, 1)))
    normal = x / np.linalg.norm(x, axis=1, keepdims=True)
    tree = KDTreeConfig(candidate_min=16, knn_k=8, num_render_levels=2)
    cfg = RenderConfig(kdtree=tree, quadrature=QuadratureConfig(samples_per_level=(4, 6, 8)), chunk=4096)
    pts = PointState.from_numpy(x, points, cfg.shading.feature_dim, normal=normal, key=jax.random.key(0))
    scene = PointScene.build(pts, cfg, Capacities(frontier=16, max_segments=16))
    tcfg = TrainConfig(total_steps=100)
    state = init_train_state(tcfg, cfg, pts, jax.random.key(1))
    cam = Camera.from_fov(jnp.asarray(orbit_cameras(1, 30.0)[0], jnp.float32), res, res, 0.7)
    rays = camera_rays(cam, 2.0, 6.0)
    bg = jnp.ones(3)
    mesh = default_mesh()

    def best(fn):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        first = time.perf_counter() - t0
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            jax.block_until_ready(fn())
            times.append(time.perf_counter() - t0)
        return first, min(times)

    r_first, r_best = best(lambda: render_chunked(cfg, state.params, scene, rays, bg).rgb)
    idx = rng.integers(0, rays.num_rays, batch)
    brays = jax.tree_util.tree_map(lambda a: a[idx], rays)
    target = jnp.concatenate([jnp.asarray(rng.uniform(size=(batch, 3)), jnp.float32), jnp.ones((batch, 1))], 1)
    b = Batch(rays=brays.replace(target=target), pixel=jnp.asarray(idx, jnp.int32), in_band=jnp.zeros(batch, bool),
              background=bg)
    step = make_train_step(tcfg, cfg)
    holder = {"state": state}

    def one_step():
        holder["state"], m = step(holder["state"], scene, b)
        return m["loss/total"]

    s_first, s_best = best(one_step)
    chunk_rays = jax.tree_util.tree_map(lambda a: a[:cfg.chunk], rays)
    mem_chunk = _render_chunk.lower(cfg, state.params, scene, chunk_rays, bg, mesh=mesh).compile().memory_analysis()
    tree_bytes = sum(int(a.nbytes) for a in jax.tree_util.tree_leaves(scene.tree))
    point_bytes = sum(int(a.nbytes) for a in jax.tree_util.tree_leaves(pts))
    return {
        "devices": len(jax.devices()), "platform": jax.devices()[0].platform, "points": points,
        "render_rays": rays.num_rays, "render_first_s": round(r_first, 2),
        "render_rays_per_s": round(rays.num_rays / r_best), "train_batch": batch,
        "train_first_s": round(s_first, 2), "train_rays_per_s": round(batch / s_best),
        "chunk": cfg.chunk,
        "chunk_temp_bytes_per_ray": None if mem_chunk is None else round(mem_chunk.temp_size_in_bytes / cfg.chunk),
        "point_state_bytes_per_point": round(point_bytes / points, 1),
        "tree_bytes_per_point": round(tree_bytes / points, 1),
    }


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--devices", type=int, nargs="+", default=[1, 2, 4])
    ap.add_argument("--platform", choices=["cpu", "gpu"], default="cpu",
                    help="cpu: forced host devices; gpu: the machine's devices as they are")
    ap.add_argument("--points", type=int, default=20000)
    ap.add_argument("--batch", type=int, default=1024)
    ap.add_argument("--res", type=int, default=128, help="image size whose rays are rendered")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        print(json.dumps(worker(args.points, args.batch, args.res, args.repeats)))
        return
    rows = []
    counts = [None] if args.platform == "gpu" else args.devices
    for n in counts:
        env = dict(os.environ)
        if n is not None:
            env["XLA_FLAGS"] = f"{env.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count={n}".strip()
            env["JAX_PLATFORMS"] = "cpu"
        cmd = [sys.executable, __file__, "--worker", "--points", str(args.points), "--batch", str(args.batch),
               "--res", str(args.res), "--repeats", str(args.repeats)]
        out = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
        if out.returncode != 0:
            raise SystemExit(f"worker with {n} devices failed:\n{out.stderr[-3000:]}")
        row = json.loads(out.stdout.strip().splitlines()[-1])
        rows.append(row)
        print(row, flush=True)
    base = rows[0]
    for r in rows:
        r["render_speedup"] = round(r["render_rays_per_s"] / base["render_rays_per_s"], 2)
        r["train_speedup"] = round(r["train_rays_per_s"] / base["train_rays_per_s"], 2)
    command = "python -m experiments.scaling_benchmark " + " ".join(
        f"--{k} {' '.join(map(str, v)) if isinstance(v, list) else v}" for k, v in vars(args).items() if k != "worker")
    report = {"what": "render and training throughput with rays split over N devices; memory per ray and point",
              "rows": rows, "command": command,
              "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version()}}
    RESULTS.mkdir(exist_ok=True)
    from ne_jax.atomic import atomic_write_json, atomic_write_text

    atomic_write_json(RESULTS / "scaling.json", report)
    lines = [f"Rays split over N devices ({rows[0]['platform']}, {os.cpu_count()} CPU cores; {args.points} points, "
             f"{rows[0]['render_rays']} rays per render, {args.batch} rays per training step). "
             f"Re-run: `{command}`.", "",
             "| devices | render rays/s | vs 1 | train rays/s | vs 1 | compile render (s) | compile step (s) |",
             "|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['devices']} | {r['render_rays_per_s']} | {r['render_speedup']} | {r['train_rays_per_s']} | "
                     f"{r['train_speedup']} | {r['render_first_s']} | {r['train_first_s']} |")
    lines += ["", f"Memory: {base['chunk_temp_bytes_per_ray']} bytes of temporaries per ray in a chunk of "
              f"{base['chunk']} rays (XLA's memory analysis of the compiled chunk on one device; with N devices each "
              f"holds 1/N of the chunk: " + ", ".join(f"{r['devices']}: {r['chunk_temp_bytes_per_ray']}" for r in rows)
              + f" bytes per chunk ray and device); {base['point_state_bytes_per_point']} bytes of point state and "
              f"{base['tree_bytes_per_point']} bytes of K-D tree per point, replicated on every device."]
    atomic_write_text(RESULTS / "scaling.md", "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    import ne_jax

    ne_jax.setup(huge_pages=True)  # as `ne-jax` does: a host device per core, huge pages (restarts)
    main()

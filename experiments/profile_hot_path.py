"""A profile of the ``default`` preset's hot path, by stage, against the machine's matmul FLOP/s
(docs/studies/profile.md: the scene, the batches and the method).

    python -m experiments.profile_hot_path [--reference-path /tmp/ne/prof_ref] [--repeats 5] [--rounds 2] [--quick]

Every stage is jitted alone on the previous stage's outputs and timed, with XLA's FLOPs
(:func:`profile_stages`). The whole render and training step are also timed in fresh processes with
the ``ne_jax`` of ``--reference-path`` (a worktree of the reference commit, which must have the API
:func:`whole_calls` calls) and of this checkout, alternating (:func:`_child`). Writes
``experiments/results/profile_hot_path.{json,md}``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

from experiments import common
from experiments.common import RESULTS, ROOT, bench_cloud, best_time, machine, write_results

CONFIG = "default"
IMAGE = 200
TRAIN_RAYS = 2048
RENDER_RAYS = 4096
POINTS = 100_000


def _commit(path: Path) -> str:
    """The short ``HEAD`` commit of the checkout at ``path``, ``+dirty`` where its ``ne_jax`` is modified."""
    from ne_jax.provenance import git

    head = git("-C", str(path), "rev-parse", "--short", "HEAD")
    dirty = head != "unknown" and git("-C", str(path), "status", "--porcelain", "--", "ne_jax")
    return head + ("+dirty" if dirty else "")


def flops_of(jitted, *args) -> float | None:
    """XLA's estimated FLOPs of the compiled ``jitted(*args)`` (None when the backend gives none)."""
    try:
        ca = jitted.lower(*args).compile().cost_analysis()
    except Exception:  # noqa: BLE001
        return None
    if isinstance(ca, (list, tuple)):
        ca = ca[0] if ca else None
    if not ca or "flops" not in ca:
        return None
    return float(ca["flops"])


def build_inputs(quick: bool, run=None):
    """The scene (:data:`POINTS` glossy surface samples, random features), a :data:`RENDER_RAYS`-ray
    render chunk through the middle of an :data:`IMAGE` px orbit view and a :data:`TRAIN_RAYS`-ray
    training batch (90% hits): ``(run, scene, render_rays, train_rays, build_s, hit_share)``; ``run``:
    a :class:`~ne_jax.train.run.RunConfig` in place of the ``default`` preset."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from ne_jax.data import cameras
    from ne_jax.data.rays import Camera, camera_rays
    from ne_jax.geometry.intersect import intersect
    from ne_jax.render.renderer import PointScene
    from ne_jax.train.run import get_run_preset

    run = get_run_preset(CONFIG) if run is None else run
    cfg = run.render
    pts = bench_cloud(20_000 if quick else POINTS, cfg.shading.feature_dim, spread=0.5)
    t0 = time.perf_counter()
    scene = PointScene.build(pts, cfg, run.capacities)
    build_s = time.perf_counter() - t0
    cam = Camera.from_fov(cameras.orbit_cameras(4)[1], IMAGE, IMAGE, cameras.CAMERA_ANGLE_X)
    rays = camera_rays(cam, cameras.NEAR, cameras.FAR)
    mid = (IMAGE * IMAGE) // 2 - RENDER_RAYS // 2  # a chunk through the middle of the image
    render_rays = rays.take(slice(mid, mid + RENDER_RAYS))
    hits = np.asarray(intersect(scene.tree, rays, cfg.kdtree, scene.capacities).num_segments) > 0
    rng = np.random.default_rng(0)
    n_hit = int(0.9 * TRAIN_RAYS)
    idx = np.concatenate([rng.choice(np.flatnonzero(hits), n_hit),
                          rng.choice(np.flatnonzero(~hits), TRAIN_RAYS - n_hit)])
    train_rays = rays.take(jnp.asarray(idx))
    target = jnp.concatenate([jax.random.uniform(jax.random.key(2), (TRAIN_RAYS, 3)), jnp.ones((TRAIN_RAYS, 1))], -1)
    train_rays = train_rays.replace(target=target)
    return run, scene, render_rays, train_rays, build_s, float(np.mean(hits))


def whole_calls(quick: bool, run=None):
    """The whole render of the render batch and the whole training step on the training batch
    (:func:`build_inputs`; ``run``: a RunConfig in place of the ``default`` preset), with whatever
    ``ne_jax`` is importable: ``(render, step, state)`` with ``render(state) -> RenderOut``,
    ``step(state) -> (state, metrics)`` and the initial state."""
    import jax
    import jax.numpy as jnp

    from ne_jax.render.renderer import render_rays
    from ne_jax.train.sampler import Batch
    from ne_jax.train.state import init_train_state
    from ne_jax.train.step import make_train_step

    run, scene, rrays, trays, _, _ = build_inputs(quick, run)
    cfg = run.train_render
    train_scene = scene.fitted(cfg, trays)  # the packing budget, as training fits it
    bg = jnp.ones(3)
    state = init_train_state(run.train, cfg, scene.points, jax.random.key(1), total_steps=run.total_steps)
    render = jax.jit(lambda p, sc, r: render_rays(run.render, p, sc, r, bg))
    step = make_train_step(run.train, cfg, total_steps=run.total_steps)
    batch = Batch(rays=trays, pixel=jnp.zeros(TRAIN_RAYS, jnp.int32), in_band=jnp.zeros(TRAIN_RAYS, bool),
                  background=bg)
    return (lambda st: render(st.params, scene, rrays)), (lambda st: step(st, train_scene, batch)), state


def measure_whole(repeats: int, quick: bool) -> dict:
    """Rays/s of the whole ``default`` render (one chunk) and training step, with whatever ``ne_jax``
    is importable (this checkout, or the reference through ``PYTHONPATH``)."""
    import ne_jax

    render, step, state = whole_calls(quick)
    t_render = best_time(lambda: render(state), repeats)[1]
    t_step = best_time(lambda: step(state)[1]["loss/total"], repeats)[1]
    out = step(state)[1]
    # segments lost to the packing budget / to the traversal's capacities
    dropped, overflow = int(out["lost/packing"]), int(out["lost/frontier"]) + int(out["lost/slots"])
    return {"ne_jax": str(Path(ne_jax.__file__).resolve().parent.parent), "render_rays_per_s": RENDER_RAYS / t_render,
            "render_ms": 1e3 * t_render, "step_rays_per_s": TRAIN_RAYS / t_step, "step_ms": 1e3 * t_step,
            "loss": float(out["loss/total"]), "dropped": dropped, "overflow": overflow}


def profile_stages(repeats: int, quick: bool, run=None) -> dict:
    """Every stage of the render and the step jitted alone, with time and XLA FLOPs (this checkout);
    ``run`` as in :func:`build_inputs`."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from ne_jax.geometry import knn as K
    from ne_jax.geometry.intersect import intersect
    from ne_jax.geometry.kdtree import KNN_EPS_FACTOR, build_tree
    from ne_jax.render.composite import composite
    from ne_jax.render.quadrature import level_samples
    from ne_jax.render.renderer import render_rays, render_rays_with_aux
    from ne_jax.render.shading import shade
    from ne_jax.render.stage import values_needed
    from ne_jax.train.sampler import Batch
    from ne_jax.train.state import init_train_state
    from ne_jax.train.step import make_train_step

    run, scene, rrays, trays, build_s, hit_share = build_inputs(quick, run)
    bg = jnp.ones(3)
    a = jnp.ones((2048, 2048), jnp.float32)
    mm = jax.jit(lambda x: x @ x)
    t_mm = best_time(lambda: mm(a), repeats)[1]
    peak = 2 * 2048**3 / t_mm
    rows = []

    def row(name, kind, rays, t, f=None, **extra):  # a stage's time and, where known, its FLOPs
        rows.append({"stage": name, "batch": kind, "rays": rays, "ms": 1e3 * t,
                     "gflop": None if f is None else f / 1e9,
                     "gflop_per_s": None if f is None else f / t / 1e9,
                     "vs_matmul": None if f is None else f / t / peak, **extra})

    def add(name, kind, rays, fn, *args):
        j = jax.jit(fn)
        t = best_time(lambda: j(*args), repeats)[1]
        f = flops_of(j, *args)
        row(name, kind, rays, t, f)
        print(f"{kind:6s} {name:36s} {1e3 * t:9.2f} ms  {'' if f is None else f'{f / t / 1e9:8.2f} GFLOP/s'}",
              flush=True)
        return j(*args)

    def one(kind, rays):  # the stages of one batch ("render" or "train")
        cfg = run.train_render if kind == "train" else run.render
        sc = scene.fitted(cfg, trays) if kind == "train" else scene  # the packing budget, as training fits it
        cap, tc, tree = sc.capacities, cfg.kdtree, sc.tree
        state = init_train_state(run.train, cfg, sc.points, jax.random.key(1), total_steps=run.total_steps)
        aux = kind == "train"
        r = rays.num_rays
        seg = add("traversal", kind, r, lambda tr, ry: intersect(tr, ry, tc, cap), tree, rays)
        m = seg.valid.shape[1]
        budget = cap.segment_budget(r)

        def pack(seg, rays, depth):
            flat = lambda x: x.reshape((r * m,) + x.shape[2:])  # noqa: E731
            (slot,) = jnp.nonzero(flat(seg.valid), size=budget, fill_value=0)
            live = jnp.arange(budget) < jnp.sum(seg.valid)
            ray = slot // m
            o, d = rays.origin[ray], rays.direction[ray]
            t, w = level_samples(cfg.quadrature, flat(seg.t_lo)[slot], flat(seg.t_hi)[slot],
                                 (depth - 1) - flat(seg.level)[slot])
            pos = o[:, None, :] + t[..., None] * d[:, None, :]
            return slot, live, d, pos, w, flat(seg.node)[slot].astype(jnp.int32)

        slot, live, d, pos, w, node = add("packing and sampling", kind, r, pack, seg, rays, tree.depth)
        eps = (KNN_EPS_FACTOR * tree.spacing).astype(jnp.float32)
        pts = sc.points
        pc, ci = add("candidate gather and KNN weights", kind, r,
                     lambda p, t_, x, n_, w_: K._per_candidate_weights(p, t_, x, n_, w_, tc.knn_k, eps)[:2],
                     pts, tree, pos, node, w)
        needed = values_needed(pts, cfg.shading.effects, aux)

        def integ(pc, ci, vals):
            return {k: jnp.einsum("bc,bcd->bd", pc, v.reshape(v.shape[0], -1)[ci]) for k, v in vals.items()}

        means = add("value gather and integration", kind, r, integ, pc, ci, needed)
        means = {k: v.reshape((v.shape[0],) + needed[k].shape[1:]) for k, v in means.items()}
        sh = add("MLPs (shade)", kind, r, lambda p, f, nrm, dd: shade(cfg.shading, p, f, nrm, dd),
                 state.params, means["feature"], means.get("normal"), d)

        def comp(sigma, rgb, seg, slot, live):
            def unpack(v):
                target = jnp.where(live, slot, r * m)
                return jnp.zeros((r * m,) + v.shape[1:], v.dtype).at[target].set(v, mode="drop").reshape(
                    (r, m) + v.shape[1:])
            keep = unpack(live)
            return composite(unpack(sigma), unpack(rgb), (seg.t_hi - seg.t_lo) / tree.spacing, keep,
                             0.5 * (seg.t_lo + seg.t_hi), bg).rgb

        add("compositing", kind, r, comp, sh.sigma, sh.rgb, seg, slot, live)
        if kind == "render":
            add("whole render", kind, r, lambda p, sc_, ry: render_rays(cfg, p, sc_, ry, bg).rgb, state.params, sc,
                rays)
            return
        add("whole forward (render with aux)", kind, r,
            lambda p, sc_, ry: render_rays_with_aux(cfg, p, sc_, ry, bg), state.params, sc, rays)

        def fwd_bwd(tr, sc_, ry):
            def f(tr):
                p = sc_.points.replace(**tr["points"])
                out, a_ = render_rays_with_aux(cfg, tr["params"], sc_.replace(points=p), ry, bg)
                return jnp.sum(out.rgb) + jnp.sum(a_.weights)
            return jax.grad(f)(tr)

        add("forward + backward (render VJP)", kind, r, fwd_bwd, state.trainables, sc, rays)
        step = make_train_step(run.train, cfg, total_steps=run.total_steps)
        batch = Batch(rays=rays, pixel=jnp.zeros(r, jnp.int32), in_band=jnp.zeros(r, bool), background=bg)
        t = best_time(lambda: step(state, sc, batch)[1]["loss/total"], repeats)[1]
        row("whole training step", kind, r, t)
        print(f"train  whole training step {1e3 * t:9.2f} ms", flush=True)
        # host side: a tree rebuild after each point round (run.round_epochs), amortised over an epoch
        t0 = time.perf_counter()
        build_tree(np.asarray(pts.xyz), np.asarray(pts.alive), tc)
        t_build = time.perf_counter() - t0
        rounds = run.round_epochs[1] - run.round_epochs[0] + 1  # after epochs first .. last, inclusive
        row("host: tree rebuild (per round)", kind, r, t_build,
            amortised_ms_per_step=1e3 * t_build * rounds / (run.epochs * run.steps_per_epoch))
    one("render", rrays)
    one("train", trays)
    return {"matmul_gflop_per_s": peak / 1e9, "matmul_ms": 1e3 * t_mm, "tree_build_s": build_s,
            "hit_share_image": hit_share, "rows": rows}


def _child(path: str | None, repeats: int, quick: bool) -> dict:
    """The whole render and step in a fresh process with the ``ne_jax`` at ``path`` (default this
    checkout's), each code started as it starts itself: this checkout with huge pages for XLA's
    scratch memory (as ``ne-jax`` does), the reference without."""
    from ne_jax._host_memory import tunables_env

    env = {k: v for k, v in os.environ.items() if k != "GLIBC_TUNABLES"}
    args = ["--whole-only", "--repeats", str(repeats)] + ["--quick"] * quick
    return common.json_from("profile_hot_path", args, path or ROOT, env if path else tunables_env(env) or env)


def _fmt(v, spec):
    return "" if v is None else format(v, spec)


def to_markdown(report: dict) -> str:
    prof = report["profile"]
    lines = [f"# Hot-path profile, `{CONFIG}` preset", "",
             f"Commit {report['commit']} (reference {report['reference_commit']}), {report['device']}, "
             f"jax {report['jax']}, {report['machine']['cpus']} CPUs.", "",
             f"Command: `{report['command']}`", "",
             f"Matmul (2048 x 2048 float32): {prof['matmul_gflop_per_s']:.1f} GFLOP/s.", "",
             "| batch | stage | ms | share of whole | GFLOP | GFLOP/s | vs matmul |",
             "|---|---|---:|---:|---:|---:|---:|"]
    for r in prof["rows"]:
        whole = next((x["ms"] for x in prof["rows"] if x["batch"] == r["batch"]
                      and x["stage"] in ("whole render", "whole training step")), None)
        share = "" if whole is None or r["stage"].startswith(("whole", "host")) else f"{100 * r['ms'] / whole:.0f}%"
        lines.append(f"| {r['batch']} ({r['rays']} rays) | {r['stage']} | {r['ms']:.1f} | {share} | "
                     f"{_fmt(r['gflop'], '.3f')} | {_fmt(r['gflop_per_s'], '.2f')} | {_fmt(r['vs_matmul'], '.1%')} |")
    lines += ["", "| code | render rays/s | train step rays/s | step loss |", "|---|---:|---:|---:|"]
    for name in ("reference", "new"):
        w = report["whole"][name]
        lines.append(f"| {name} | {w['render_rays_per_s']:.0f} | {w['step_rays_per_s']:.0f} | {w['loss']:.6f} |")
    rt = report["ratio"]
    lines += ["", f"Ratio new / reference: render {rt['render']:.2f}x, training step {rt['step']:.2f}x.", ""]
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--reference-path", default="/tmp/ne/prof_ref")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--rounds", type=int, default=2, help="whole measurements of each, the order alternating")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--whole-only", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--out-dir", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    if args.whole_only:
        print(json.dumps(measure_whole(args.repeats, args.quick)))
        return
    import jax

    paths = {"reference": args.reference_path, "new": None}
    whole = common.against_reference(lambda name: _child(paths[name], args.repeats, args.quick), args.rounds)
    best = {k: {**v[0], "render_rays_per_s": max(x["render_rays_per_s"] for x in v),
                "step_rays_per_s": max(x["step_rays_per_s"] for x in v)} for k, v in whole.items()}
    prof = profile_stages(args.repeats, args.quick)
    report = {"command": "python -m experiments.profile_hot_path" + (" --quick" if args.quick else ""),
              "commit": _commit(ROOT), "reference_commit": _commit(Path(args.reference_path)), "config": CONFIG,
              "device": str(jax.devices()[0]), "jax": jax.__version__, "machine": machine(),
              "profile": prof, "whole": best, "whole_rounds": whole,
              "ratio": {"render": best["new"]["render_rays_per_s"] / best["reference"]["render_rays_per_s"],
                        "step": best["new"]["step_rays_per_s"] / best["reference"]["step_rays_per_s"]}}
    write_results(args.out_dir, "profile_hot_path" + ("_quick" if args.quick else ""), report, to_markdown(report))


if __name__ == "__main__":
    import ne_jax

    if hasattr(ne_jax, "setup"):  # a --whole-only child may run a reference ne_jax that sets up on import
        ne_jax.setup(huge_pages="--whole-only" not in sys.argv)  # a child's environment is _child's
    main()

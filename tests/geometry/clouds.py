"""Small test clouds, including the degenerate ones of issue 3 (all float32, deterministic)."""

from __future__ import annotations

import numpy as np


def sphere(n, seed=0, radius=1.0):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, 3))
    return (radius * x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def clouds():
    """``name -> (xyz [C, 3], alive [C])``."""
    rng = np.random.default_rng(1)
    out = {}
    out["one_point"] = (np.array([[0.25, -0.5, 1.0]], np.float32), np.ones(1, bool))
    out["two_points"] = (np.array([[0.0, 0.0, 0.0], [1.0, 0.5, -0.25]], np.float32), np.ones(2, bool))
    out["identical"] = (np.tile(np.array([[0.5, 0.5, 0.5]], np.float32), (9, 1)), np.ones(9, bool))
    g = np.stack(np.meshgrid(np.arange(12), np.arange(10), indexing="ij"), -1).reshape(-1, 2) * 0.125
    out["coplanar"] = (np.concatenate([g, np.zeros((g.shape[0], 1))], 1).astype(np.float32), np.ones(g.shape[0], bool))
    t = np.linspace(-1, 1, 77)
    out["collinear"] = (np.stack([t, 0.5 * t, -t], 1).astype(np.float32), np.ones(77, bool))
    out["random_300"] = (rng.uniform(-1, 1, (300, 3)).astype(np.float32), np.ones(300, bool))
    out["sphere_700"] = (sphere(700, seed=2), np.ones(700, bool))
    xyz = sphere(600, seed=3)
    alive = np.zeros(600, bool)
    alive[rng.choice(600, 23, replace=False)] = True
    xyz[~alive] = np.nan  # dead rows may hold anything
    out["mostly_deleted"] = (xyz, alive)
    return out


CLOUDS = clouds()


def make_rays(origin, direction, near=0.0, far=1e3):
    import jax.numpy as jnp

    from ne_jax.data.rays import Rays

    o = np.asarray(origin, np.float32).reshape(-1, 3)
    d = np.asarray(direction, np.float32).reshape(-1, 3)
    r = o.shape[0]
    return Rays(
        origin=jnp.asarray(o),
        direction=jnp.asarray(d),
        near=jnp.full((r,), near, jnp.float32),
        far=jnp.full((r,), far, jnp.float32),
    )


def hard_rays(tree, xyz, alive, seed=0, n_random=24, n_boxes=6):
    """Origins/directions (float32 numpy) of the issue's hard cases for ``tree``: axis-parallel rays
    with ``0.0`` and ``-0.0`` components lying exactly in box face planes and along box edges, rays
    aimed exactly at box corners, rays starting inside boxes, rays missing everything, and random
    rays aimed at points."""
    rng = np.random.default_rng(seed)
    lo = np.asarray(tree.lo)
    hi = np.asarray(tree.hi)
    valid = np.asarray(tree.valid)
    pts = np.asarray(xyz)[np.asarray(alive)].astype(np.float64)
    ext = float(np.max(pts.max(0) - pts.min(0))) + float(tree.spacing) * 10
    center = pts.mean(0)
    r0 = 2 ** tree.render_levels[0] - 1
    boxes = [g for g in range(r0, 2**tree.depth - 1) if valid[g]]
    boxes = [boxes[i] for i in rng.choice(len(boxes), min(n_boxes, len(boxes)), replace=False)]
    o, d = [], []
    axes_dirs = []
    for a in range(3):
        for sgn in (1.0, -1.0):
            v = np.array([0.0, -0.0, 0.0]) if sgn > 0 else np.array([-0.0, 0.0, -0.0])
            v[a] = sgn
            axes_dirs.append(v)
    for g in boxes:
        c = 0.5 * (lo[g] + hi[g])
        for v in axes_dirs:
            a = int(np.flatnonzero(v)[0])
            b, e = (a + 1) % 3, (a + 2) % 3
            start = c.astype(np.float64) - v * 3 * ext
            for pb, pe in [(lo[g][b], c[e]), (hi[g][b], c[e]), (c[b], lo[g][e]), (lo[g][b], hi[g][e]), (c[b], c[e])]:
                p = start.copy()
                p[b], p[e] = pb, pe  # face plane, edge, or centre line
                o.append(p)
                d.append(v)
        corner = np.array([lo[g][0], hi[g][1], lo[g][2]], np.float64)
        for v in (np.array([1.0, -1.0, 1.0]), np.array([1.0, 2.0, 0.5]), np.array([-0.0, 1.0, 1.0])):
            v = v / np.linalg.norm(v)
            o.append(corner - v * 2 * ext)
            d.append(v)
        for _ in range(2):  # starting inside the box
            v = rng.normal(size=3)
            o.append(c.astype(np.float64))
            d.append(v / np.linalg.norm(v))
    for v in axes_dirs:  # missing everything: pointing away from the cloud
        o.append(center - v * 3 * ext)
        d.append(-v)
    for _ in range(n_random):
        tgt = pts[rng.integers(len(pts))] + rng.normal(size=3) * float(tree.spacing)
        v = rng.normal(size=3)
        v /= np.linalg.norm(v)
        o.append(tgt - v * 2 * ext)
        d.append(v)
    return np.asarray(o, np.float32), np.asarray(d, np.float32)


def padded(name, capacity=1024):
    """Cloud ``name`` in a ``capacity``-slot state (dead padding): one compiled shape for all."""
    xyz, alive = CLOUDS[name]
    out = np.zeros((capacity, 3), np.float32)
    out[: len(xyz)] = np.nan_to_num(xyz)
    al = np.zeros(capacity, bool)
    al[: len(alive)] = alive
    return out, al

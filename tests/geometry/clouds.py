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

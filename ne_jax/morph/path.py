"""Intermediate clouds of a morph: a path ``[P_0, ..., P_{T-1}]`` of indexed clouds from scene A's
cloud to scene B's.

The paper generated the intermediate clouds with a pretrained point-cloud diffusion model (latent
interpolation); its weights cannot be had offline. The stand-in here, named for what it is:

* :func:`linear_path` — **straight-line interpolation along the K-D matching**: point ``i`` moves on
  the segment from ``a[i]`` to its matched ``b[perm[i]]``, ``P_t = (1 - r_t) a + r_t b[perm]`` with
  ``r_t = t / (T - 1)``. Every intermediate cloud is indexed by construction.

Any other generator plugs in through :func:`path_from_clouds`: a list of ``[N, 3]`` arrays or PLY files
(``x, y, z`` properties), unindexed, in order from A to B; A's and B's own clouds are put at the ends
and :func:`~ne_jax.morph.matching.index_path` chains the matching through them.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ne_jax.morph.matching import index_path, kd_match


def morph_ratios(steps: int) -> np.ndarray:
    """``[T]`` evenly spaced morph ratios ``0, 1/(T-1), ..., 1``."""
    if steps < 2:
        raise ValueError(f"steps: expected at least 2 (the two ends), found {steps}")
    return np.linspace(0.0, 1.0, steps)


def linear_path(a, b, steps: int) -> list[np.ndarray]:
    """``steps`` clouds from ``a [N, 3]`` to ``b [N, 3]`` (unindexed) along the K-D matching; the
    last one is ``b`` permuted into ``a``'s indices."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)[kd_match(a, b)]
    return [(1.0 - r) * a + r * b for r in morph_ratios(steps)]


def _read_cloud(item, name: str) -> np.ndarray:
    if isinstance(item, (str, os.PathLike)):
        path = Path(item)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: expected an intermediate cloud (.ply or .npy), found nothing")
        if path.suffix.lower() == ".npy":
            return np.load(path, allow_pickle=False)
        if path.suffix.lower() == ".ply":
            from ne_jax.data.ply import read_ply

            props = read_ply(path)
            missing = [k for k in "xyz" if k not in props]
            if missing:
                raise ValueError(f"{path}: expected x, y, z vertex properties, found {sorted(props)}")
            return np.stack([props["x"], props["y"], props["z"]], axis=1)
        raise ValueError(f"{path}: expected a .ply or .npy cloud, found suffix {path.suffix!r}")
    return np.asarray(item)


def path_from_clouds(a, b, intermediate: Sequence) -> list[np.ndarray]:
    """The indexed path ``[a, *intermediate, b]`` (each intermediate cloud an ``[N, 3]`` array, a
    ``.npy`` or a ``.ply`` file, of ``a``'s size), chained by
    :func:`~ne_jax.morph.matching.index_path`."""
    names = ["scene A's cloud"] + [str(c) if isinstance(c, (str, os.PathLike)) else f"intermediate cloud {i}"
                                   for i, c in enumerate(intermediate)] + ["scene B's cloud"]
    clouds = [np.asarray(a)] + [_read_cloud(c, n) for c, n in zip(intermediate, names[1:-1])] + [np.asarray(b)]
    return index_path(clouds, names)


__all__ = ["linear_path", "morph_ratios", "path_from_clouds"]

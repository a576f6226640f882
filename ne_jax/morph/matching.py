"""K-D-tree matching of two unindexed point clouds (the paper's morphing appendix, docs/design.md facts).

Two K-D trees are built at once, one per cloud, in lockstep: every node holds the same number ``m``
of points of each cloud; its split axis is the axis of largest extent of the *union* of its two
point sets; each cloud is split at its own rank ``m // 2`` along that axis, so both children again
hold equal counts (``m // 2`` and ``m - m // 2``). Splitting both at the union's median *value*, as
the appendix puts it, would leave different counts of the two clouds on a side whenever their
shapes differ, and the leaves could not pair; the rank split is the count-preserving reading of it.
The leaves hold one point of each cloud: the pairs form a bijection that keeps relative positions
(left-bottom-front parts pair with left-bottom-front parts at every scale).

All nodes of a level are split at once (one stable sort per level and cloud, ``ceil(log2 N)`` levels), so
2^20 points match in seconds in NumPy.

Clouds of different sizes are first brought to the same size by :func:`equal_size`: the larger one
keeps its ``N_small`` points of highest priority (a model's cloud: the most confident; plain clouds: a
seeded uniform subsample), since padding with duplicates would place coincident points that the KNN
would count twice. The K-D voxels depend on every point, so a model whose cloud lost points renders
its end of the morph close to, not exactly as, its own render; with equal sizes both ends are its own.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ne_jax.geometry.points import as_cloud


def kd_match(a, b) -> np.ndarray:
    """The K-D-tree matching of ``a [N, 3]`` and ``b [N, 3]``: ``perm [N]`` (a permutation) with
    ``b[perm[i]]`` paired to ``a[i]``."""
    a, b = as_cloud(a, "a"), as_cloud(b, "b")
    if a.shape != b.shape:
        raise ValueError(f"kd_match: expected clouds of equal size, found {a.shape[0]} and {b.shape[0]} points "
                         "(bring them to one size with equal_size)")
    n = a.shape[0]
    order_a, order_b = np.arange(n), np.arange(n)
    pa, pb = a.copy(), b.copy()  # the clouds in the current order (gathers below stay cache-local)
    sizes = np.array([n])
    rows = np.arange(n)
    while sizes.max() > 1:
        starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
        seg = np.repeat(np.arange(sizes.size), sizes)
        lo = np.minimum(np.minimum.reduceat(pa, starts), np.minimum.reduceat(pb, starts))
        span = np.maximum(np.maximum.reduceat(pa, starts), np.maximum.reduceat(pb, starts)) - lo
        axis = np.argmax(span, axis=1)
        lo_ax, span = lo[np.arange(sizes.size), axis][seg], span.max(axis=1)[seg]
        axis = axis[seg]
        # one sort per level: the node index plus the coordinate scaled into [0, 0.5] within the node
        # (float64 keeps ~1e-10 of the node's extent; closer points are ties, either order pairs)
        scale = np.where(span > 0, 0.5 / np.where(span > 0, span, 1.0), 0.0)
        ia = np.argsort(seg + (pa[rows, axis] - lo_ax) * scale, kind="stable")
        ib = np.argsort(seg + (pb[rows, axis] - lo_ax) * scale, kind="stable")
        order_a, pa, order_b, pb = order_a[ia], pa[ia], order_b[ib], pb[ib]
        left = sizes // 2
        sizes = np.stack([left, sizes - left], axis=1).ravel()
        sizes = sizes[sizes > 0]
    perm = np.empty(n, np.int64)
    perm[order_a] = order_b
    return perm


def equal_size(n_a: int, n_b: int, seed: int = 0, priority_a=None, priority_b=None
               ) -> tuple[np.ndarray, np.ndarray]:
    """Rows ``(keep_a, keep_b)`` (sorted) that bring clouds of ``n_a`` and ``n_b`` points to
    ``min(n_a, n_b)`` points: all of the smaller cloud, and the larger cloud's points of highest
    ``priority`` (``[n]``, e.g. confidences), ties — and every point when no priority is given —
    broken by a seeded random order (a uniform subsample)."""
    n = min(n_a, n_b)
    rng = np.random.default_rng(seed)

    def keep(m, priority):
        if m == n:
            return np.arange(m)
        order = rng.permutation(m)
        if priority is not None:
            priority = np.asarray(priority, np.float64)
            if priority.shape != (m,):
                raise ValueError(f"equal_size: expected a priority per point [{m}], found shape {priority.shape}")
            order = order[np.argsort(-priority[order], kind="stable")]
        return np.sort(order[:n])

    return keep(n_a, priority_a), keep(n_b, priority_b)


def index_path(clouds: Sequence, names: Sequence[str] | None = None) -> list[np.ndarray]:
    """Give a sequence of unindexed clouds ``[P_0, ..., P_T]`` (each ``[N, 3]``) fixed indices:
    ``P_0`` keeps its order, and each next cloud is permuted by :func:`kd_match` against the
    previous (already permuted) one, so row ``i`` of every returned cloud is the path of point ``i``
    of ``P_0``."""
    names = list(names) if names is not None else [f"cloud {i}" for i in range(len(clouds))]
    if len(clouds) < 2:
        raise ValueError(f"index_path: expected at least two clouds, found {len(clouds)}")
    out = [as_cloud(clouds[0], names[0])]
    for cloud, name in zip(clouds[1:], names[1:]):
        cloud = as_cloud(cloud, name)
        if cloud.shape[0] != out[0].shape[0]:
            raise ValueError(f"{name}: expected {out[0].shape[0]} points (the size of {names[0]}), "
                             f"found {cloud.shape[0]}")
        out.append(cloud[kd_match(out[-1], cloud)])
    return out


__all__ = ["equal_size", "index_path", "kd_match"]

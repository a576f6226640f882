"""The flattened K-D tree behind NeuralEditor's "K-D voxels" (data flow step 1 of docs/design.md).

Layout: an implicit complete binary tree of depth ``D`` over ``P = 2**D`` point slots. Nodes are
numbered in heap order: level ``l`` holds nodes ``2**l - 1 .. 2**(l+1) - 2`` (``2**l`` of them),
the children of node ``g`` are ``2g + 1`` and ``2g + 2``, its parent ``(g - 1) // 2``. Node ``i``
(local index) of level ``l`` owns the permutation slots ``[i * 2**(D-l), (i + 1) * 2**(D-l))``.

Only alive points are placed. With ``n`` alive points and ``n <= P``, each split sends
``ceil(m/2)`` of a node's ``m`` points to the left child and ``floor(m/2)`` to the right, so the
point counts of one level differ by at most one ("voxels of one layer hold the same number of
points"); the unused slots hold the sentinel ``C`` (the state's capacity). Splits are at the median
along the widest axis of the node's points.

Box of a node = (its partition cell) ∩ (its points' bounding box grown by a margin). The margin is
``margin_factor * spacing / sqrt(3) * clip(sqrt(k * s / 2), 1, MARGIN_GROWTH_CAP)`` for a node of
``s`` slots, ``k = 1`` at and below the top rendering level and ``k = 2`` above, ``spacing`` the mean
nearest-neighbour distance — the released code's rule (its extra per-axis ``extent / sqrt(N)`` bound
and its special case for cells reaching far past the points are left out: the first makes boxes of a
planar cloud flat and unhittable). Boxes of one level are therefore disjoint up to shared faces,
and each box contains its children's.

Built on the host (numpy + ``scipy.spatial.cKDTree``), not under ``jit``: a single level's XLA
``argsort`` under jit costs more than numpy's split of that level (docs/decisions.md, the tree
build), and the candidate sets need k-NN queries, where scipy's C++ tree is faster than the JAX KNN
structures measured for docs/design.md. Building
is rare (after edits and point-cloud rounds); everything the tree feeds (``intersect``,
``knn_interpolate``) is jit-compiled.

Cost, by phase (``build_tree(..., timings=)``): ``splits`` — one ``argpartition`` per level on
rows padded to a common width (see ``_split_levels``; levels where every node holds at most one
point, below log2(n) at a fixed depth, are filled without partitions); ``index`` — ``cKDTree`` on
the points in slot order + spacing statistics; ``boxes``; ``candidates`` — a canonical set of 96
for each non-empty node of the five candidate levels (empty nodes: the sentinel, no work), built
by a cascade of certified supersets whose widths follow the data (see ``_candidate_sets``) on a
thread pool. Candidate sets are 65-80% of the build: the exact, sorted 96 nearest points of ~``n``
box centres, paid in numpy's per-element work (distances, uint64 key sorts, gathers) and scipy's
wide queries at the growing level. What the build costs against a bare ``cKDTree(points)``:
docs/decisions.md, the tree build.
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from concurrent.futures import ThreadPoolExecutor

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from scipy.spatial import cKDTree

from ne_jax.fields import require

MAX_DEPTH = 21
"""Largest tree depth (the paper's 21 levels, up to 2**21 ~ 2M points; int32 node indices)."""

MARGIN_GROWTH_CAP = 8.0
"""Upper bound of the per-level margin growth ``sqrt(k * node_size / 2)``."""

VALIDITY_STD_FACTOR = 5.0
"""Validity threshold ``lim = mean + VALIDITY_STD_FACTOR * std`` of each point's distance to its
``int(1.05 * candidates + 1.5)``-th nearest point (statistics on a subsample). A rendering-level
box is invalid (traversed, never emitted) when its candidates reach farther than ``lim`` from its
centre or its diagonal exceeds ``2 * lim``: the released code's "too spread out" rule."""

VALIDITY_FLOOR_FACTOR = 4.0
"""Lower bound of ``lim`` in units of ``spacing``: tiny clouds (fewer points than candidates)
have degenerate statistics."""

STAT_SAMPLES = 16384
"""Points sampled (seed :data:`STAT_SEED`) to estimate ``spacing`` and ``lim``; all points if fewer."""

STAT_SEED = 0
"""Seed of the statistics subsample (the build is deterministic)."""

FALLBACK_SPACING = 1e-2
"""``spacing`` (absolute units) when it cannot be measured: one point, or all points identical
and at one place. Otherwise a zero mean nearest-neighbour distance falls back to
``extent / n**(1/3)``."""

MIN_HIT_FACTOR = 1.0 / 32.0
"""A ray hits a box only if the clipped intersection is longer than ``MIN_HIT_FACTOR * spacing``
(released code: ``unit_len / 16`` with ``unit_len = spacing / 2``). Rays through edges, corners or
grazing a box are thereby misses, deterministically."""

KNN_EPS_FACTOR = 5e-4
"""Distance offset in the KNN weights, in units of ``spacing`` (released code:
``1e-3 * unit_len``): ``log(dist + eps)`` stays finite at a point."""


@dataclasses.dataclass(frozen=True)
class KDTreeConfig:
    """Static settings of the K-D tree, its traversal and the KNN interpolation (hashable: pass it
    as a static argument). The traversal's buffer sizes are not settings: they are
    :class:`~ne_jax.geometry.capacity.Capacities`, carried by the scene."""

    depth: int | None = None
    """Tree depth ``D`` (``2**D`` point slots, ``D + 1`` levels, level ``D`` = single-point leaves).
    ``None``: the smallest ``D`` with ``2**D >= alive count``, at least ``num_render_levels + 1``.
    A fixed value keeps every array shape (and so every compiled function) the same across
    rebuilds; building fails if the alive count exceeds ``2**depth``."""

    num_render_levels: int = 4
    """Rendering levels: the bottom ``num_render_levels`` non-leaf levels (``D-4 .. D-1``, nodes of
    16, 8, 4, 2 slots by default). The level just above them (``D-5``, nodes of 32 slots) is the
    growing level: it has candidate sets too, and ``intersect(..., include_grow_level=True)`` also
    emits its minimal voxels, for point growing."""

    candidate_min: int = 96
    """Candidate-set size ``max(candidate_min, 2 * node_size)`` (released code: 96); one width for all
    five candidate levels, using the largest node (``2**(num_render_levels + 1)`` slots)."""

    knn_k: int = 32
    """``K``, the neighbours per sample taken from the candidate set (paper: 32)."""

    margin_factor: float = 1.0
    """Scales the box margin (released code's ``bnd_pad_fact``)."""

    density_falloff: float | None = None
    """``None``: the KNN interpolation is normalised and nothing else. A number ``f``: the lookups
    also return the *density gate* of every sample, ``sum_k w_k c_k phi(d_k)`` with the KNN weights
    ``w``, the neighbours' confidences ``c`` and ``phi(d) = 1 - exp(-f spacing / d)`` (1 at a point,
    ``f spacing / d`` far away), and the colour model's density is multiplied by it
    (:mod:`ne_jax.geometry.knn`). Confidences then scale the density they support, as PointNeRF's
    do, and a sample far from every point is nearly empty."""

    def __post_init__(self):
        def need(cond, name, expected):
            require(self, cond, name, expected)

        need(self.num_render_levels >= 1, "num_render_levels", "an integer >= 1")
        need(self.num_render_levels + 1 <= MAX_DEPTH, "num_render_levels", f"at most {MAX_DEPTH - 1} (MAX_DEPTH - 1)")
        if self.depth is not None:
            need(
                self.num_render_levels + 1 <= self.depth <= MAX_DEPTH,
                "depth",
                f"None or an integer in [num_render_levels + 1, MAX_DEPTH] = "
                f"[{self.num_render_levels + 1}, {MAX_DEPTH}]",
            )
        need(self.candidate_min >= 1, "candidate_min", "an integer >= 1")
        need(1 <= self.knn_k <= self.num_candidates, "knn_k", f"an integer in [1, {self.num_candidates}]")
        need(self.margin_factor > 0, "margin_factor", "> 0")
        need(self.density_falloff is None or self.density_falloff > 0, "density_falloff", "None or > 0")

    @property
    def num_candidates(self) -> int:
        """Width of every candidate set: ``max(candidate_min, 2 * 2**(num_render_levels + 1))``."""
        return max(self.candidate_min, 2 * 2 ** (self.num_render_levels + 1))

    def replace(self, **changes) -> KDTreeConfig:
        return dataclasses.replace(self, **changes)


@struct.dataclass
class KDTree:
    """A built K-D tree (see the module docstring for the layout). ``P = 2**depth`` slots,
    ``2P - 1`` nodes; the candidate levels are ``depth - num_render_levels - 1 .. depth - 1``.

    Attributes:
        lo, hi: ``[2P-1, 3]`` node boxes (zeros for empty nodes).
        count: ``[2P-1]`` int32 alive points under each node.
        valid: ``[2P-1]`` bool: non-empty, and at rendering levels not "too spread out".
            Traversal descends through invalid boxes; only valid ones are emitted as segments.
        split_axis: ``[P-1]`` int32 split axis of each internal node (0, 1, 2).
        split_value: ``[P-1]`` split coordinate (midpoint between the two children's points).
        perm: ``[P]`` int32 point index (into the ``PointState``) per slot, sentinel ``capacity``.
        candidates: ``[nodes of the candidate levels, num_candidates]`` int32 point indices nearest
            the box centre, nearest first (equidistant points in slot order, i.e. by position in
            ``perm``, in a built tree), sentinel ``capacity``;
            row ``g - first_candidate_node``.
        spacing: ``[]`` mean nearest-neighbour distance of the alive points (the length unit).
        frame_rot, frame_shift: ``[2**frame_level, 3, 3]`` / ``[2**frame_level, 3]`` or ``None``.
            A tree carried through an edit (:func:`~ne_jax.geometry.carry.carry_tree`) keeps its
            boxes in the frame its points had when it was built: the subtree under node ``i`` of
            ``frame_level`` maps world positions to that frame by ``x -> frame_rot[i] @ x +
            frame_shift[i]``, and its boxes are tested there (nodes above ``frame_level`` have world
            boxes). ``None``: every box is in world coordinates (a built tree), nothing extra traced.
        depth, capacity, num_render_levels, frame_level: static ints (``frame_level`` -1 without frames).
    """

    lo: jax.Array
    hi: jax.Array
    count: jax.Array
    valid: jax.Array
    split_axis: jax.Array
    split_value: jax.Array
    perm: jax.Array
    candidates: jax.Array
    spacing: jax.Array
    depth: int = struct.field(pytree_node=False)
    capacity: int = struct.field(pytree_node=False)
    num_render_levels: int = struct.field(pytree_node=False)
    frame_rot: jax.Array | None = None
    frame_shift: jax.Array | None = None
    frame_level: int = struct.field(pytree_node=False, default=-1)

    @property
    def has_frames(self) -> bool:
        """Whether some boxes live in a carried frame (see ``frame_rot``)."""
        return self.frame_rot is not None

    @property
    def num_slots(self) -> int:
        return 2**self.depth

    @property
    def num_nodes(self) -> int:
        return 2 ** (self.depth + 1) - 1

    @property
    def render_levels(self) -> tuple[int, ...]:
        """Rendering levels, top first (``depth - num_render_levels .. depth - 1``)."""
        return tuple(range(self.depth - self.num_render_levels, self.depth))

    @property
    def grow_level(self) -> int:
        return self.depth - self.num_render_levels - 1

    @property
    def first_candidate_node(self) -> int:
        """Heap index of the first node of the growing level (row 0 of ``candidates``)."""
        return 2**self.grow_level - 1

    @staticmethod
    def level_start(level: int) -> int:
        """Heap index of the first node of ``level``."""
        return 2**level - 1

    @staticmethod
    def children(node):
        """Heap indices ``(2g + 1, 2g + 2)`` of the children of ``node`` (ints or arrays)."""
        return 2 * node + 1, 2 * node + 2

    @staticmethod
    def parent(node):
        return (node - 1) // 2

    def node_candidates(self, node: jax.Array) -> jax.Array:
        """``[..., num_candidates]`` candidate point indices of candidate-level nodes ``node``.
        Other nodes are clipped to the first / last candidate row (no error under jit): the invalid
        slots of :class:`~ne_jax.geometry.intersect.Segments` hold node 0, so their samples get
        some candidate set and must be masked by ``Segments.valid`` downstream."""
        row = jnp.clip(node - self.first_candidate_node, 0, self.candidates.shape[0] - 1)
        return self.candidates[row]


def _level_margin_growth(cfg: KDTreeConfig, slots: int) -> float:
    k = 1.0 if slots <= 2**cfg.num_render_levels else 2.0
    return float(np.clip(math.sqrt(k * slots / 2.0), 1.0, MARGIN_GROWTH_CAP))


def tree_depth(num_alive: int, cfg: KDTreeConfig) -> int:
    """The depth ``build_tree`` uses for ``num_alive`` points under ``cfg`` (raises if too many)."""
    lo = cfg.num_render_levels + 1
    if cfg.depth is not None:
        if num_alive > 2**cfg.depth:
            raise ValueError(
                f"alive: expected at most 2**depth = {2**cfg.depth} alive points for "
                f"KDTreeConfig.depth={cfg.depth}, found {num_alive}"
            )
        return cfg.depth
    d = max(lo, int(math.ceil(math.log2(max(num_alive, 1)))))
    if d > MAX_DEPTH:
        raise ValueError(
            f"alive: expected at most 2**MAX_DEPTH = {2**MAX_DEPTH} alive points (the tree's largest depth), "
            f"found {num_alive}"
        )
    return d


def _spacing_and_limit(x: np.ndarray, kd: cKDTree, cfg: KDTreeConfig) -> tuple[float, float]:
    """Mean nearest-neighbour distance and the validity threshold ``lim`` (see the config)."""
    return _spacing_stats(x, kd, cfg)[:2]


def _spacing_stats(x: np.ndarray, kd: cKDTree, cfg: KDTreeConfig) -> tuple[float, float, float]:
    """:func:`_spacing_and_limit` and the cloud's dimension as the cascade's widths see it: how the
    distance to the ``j``-th neighbour grows with ``j`` (``d_j ~ j**(1/dim)``: 2 on a surface, 3 in
    a volume; 2 where it cannot be measured), from the same sample and query."""
    n = x.shape[0]
    rng = np.random.default_rng(STAT_SEED)
    sample = x if n <= STAT_SAMPLES else x[rng.choice(n, STAT_SAMPLES, replace=False)]
    kv = min(int(1.05 * cfg.num_candidates + 1.5), n)
    kq = max(kv, 2) if n >= 2 else 1
    dist, _ = kd.query(sample, k=kq, workers=-1)
    dist = np.asarray(dist, np.float64).reshape(sample.shape[0], kq)
    spacing = float(np.mean(dist[:, 1])) if n >= 2 else 0.0
    if not spacing > 0.0:
        extent = float(np.max(x.max(axis=0) - x.min(axis=0))) if n >= 2 else 0.0
        spacing = extent / n ** (1.0 / 3.0) if extent > 0 else FALLBACK_SPACING
    dk = dist[:, kv - 1]
    lim = float(np.mean(dk) + VALIDITY_STD_FACTOR * np.std(dk))
    dim = 2.0
    j_lo, j_hi = 8, kq - 1
    if j_hi >= 4 * j_lo:
        d_lo, d_hi = float(np.median(dist[:, j_lo])), float(np.median(dist[:, j_hi]))
        if d_lo > 0 and d_hi > d_lo:
            dim = float(np.clip(math.log(j_hi / j_lo) / math.log(d_hi / d_lo), 1.0, 3.0))
    return spacing, max(lim, VALIDITY_FLOOR_FACTOR * spacing), dim


def _check_inputs(xyz, alive) -> tuple[np.ndarray, np.ndarray]:
    pts = np.asarray(xyz)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"xyz: expected shape [C, 3], found shape {pts.shape}")
    msk = np.asarray(alive)
    if msk.shape != (pts.shape[0],):
        raise ValueError(f"alive: expected shape [C={pts.shape[0]}], found shape {msk.shape}")
    if msk.dtype != np.bool_:
        raise ValueError(f"alive: expected a bool mask, found dtype {msk.dtype}")
    if not msk.any():
        raise ValueError("alive: expected at least one alive point, found none")
    bad = msk & ~np.isfinite(pts).all(axis=1)
    if bad.any():
        raise ValueError(
            f"xyz: expected finite positions for alive points, found {int(bad.sum())} with NaN/inf "
            f"(first at index {int(np.flatnonzero(bad)[0])})"
        )
    return pts, msk


def _row_reduce(f, a):
    """``f``-reduction of each row of ``a [rows, w]`` (elementwise over columns for short rows:
    numpy's axis reduction is slow there)."""
    if a.shape[1] > 16:
        return f.reduce(a, axis=1)
    r = a[:, 0].copy()
    for j in range(1, a.shape[1]):
        f(r, a[:, j], out=r)
    return r


def _split_levels(x: np.ndarray, depth: int):
    """Top-down median splits. Returns per-level ``(split_axis, split_value)`` for levels
    ``0 .. depth-1``, the leaf permutation (local indices, -1 = empty slot) and per level
    ``0 .. depth`` the nodes' point bounding boxes ``(lo, hi)`` (NaN for empty nodes) and counts.

    Each level is a ``[nodes, w]`` array of point rows padded to a common even width ``w`` with at
    most two pads per row (counts of one level differ by at most one). One ``argpartition`` at
    ``w/2 - 1`` per level splits every row: its pads are keyed ``+inf`` (sent right) or, when the
    left child needs one to fill its half, ``-inf``."""
    n = x.shape[0]
    width = 2 * ((n + 1) // 2)
    pts = np.full((3, 1, width), np.nan)
    pts[:, 0, :n] = x.T
    ids = np.full((1, width), -1, np.int64)
    ids[0, :n] = np.arange(n)
    cnt = np.array([n], np.int64)
    axes, values, los, his, counts = [], [], [], [], []
    for level in range(depth):
        nrow, w = ids.shape
        if cnt.max() <= 1:  # single points from here down (a fixed depth above log2(n))
            return _single_point_levels(x, ids, cnt, level, depth, axes, values, los, his, counts)
        half = w // 2
        lo = np.stack([_row_reduce(np.fmin, pts[a]) for a in range(3)], axis=1)
        hi = np.stack([_row_reduce(np.fmax, pts[a]) for a in range(3)], axis=1)
        los.append(lo)
        his.append(hi)
        counts.append(cnt)
        ext = np.where(cnt[:, None] > 1, hi - lo, 0.0)  # empty / single-point nodes: axis 0
        axis = np.argmax(ext, axis=1)
        rows = np.arange(nrow)
        key = pts[axis, rows]  # [nrow, w]
        np.fmin(key, np.inf, out=key)  # pads (NaN) -> +inf
        kl = (cnt + 1) // 2
        need = np.flatnonzero(kl < half)  # the left child takes one pad
        if need.size:
            key[need, np.argmax(ids[need] < 0, axis=1)] = -np.inf
        order = np.argpartition(key, half - 1, axis=1)
        lmax = key[rows, order[:, half - 1]]
        rmin = _row_reduce(np.minimum, np.take_along_axis(key, order[:, half:], axis=1))
        flat = (order + (rows * w)[:, None]).ravel()
        pts = pts.reshape(3, -1)[:, flat].reshape(3, 2 * nrow, half)
        ids = ids.ravel()[flat].reshape(2 * nrow, half)
        has_right = cnt > kl
        rmin = np.where(has_right, rmin, lmax)  # no inf - inf below
        split = np.where(has_right, 0.5 * (lmax + rmin), np.where(cnt > 0, lmax, 0.0))
        axes.append(axis.astype(np.int32))
        values.append(split)
        cnt = np.stack([kl, cnt - kl], axis=1).reshape(-1)
        if half % 2 and level < depth - 1:
            pts = np.concatenate([pts, np.full((3, 2 * nrow, 1), np.nan)], axis=2)
            ids = np.concatenate([ids, np.full((2 * nrow, 1), -1, np.int64)], axis=1)
    # Leaves: one slot each.
    leaf = ids[:, 0]
    los.append(pts[:, :, 0].T)
    his.append(pts[:, :, 0].T)
    counts.append(cnt)
    return axes, values, leaf, (los, his, counts)

def _single_point_levels(x, ids, cnt, level, depth, axes, values, los, his, counts):
    """The rest of :func:`_split_levels` from ``level`` down when every node holds at most one
    point, without partitions: what the padded-row splits give there. A point always goes left
    (``ceil(1/2) = 1``), so it sits in the leftmost node of its subtree on every level below and in
    its leftmost leaf; split axis 0 (no spread), split value its x (the left child's largest key;
    0 for empty nodes); boxes the point itself (NaN when empty)."""
    nrow = ids.shape[0]
    sid = ids.max(axis=1)  # the row's point, -1 = none
    has = sid >= 0
    pp = np.where(has[:, None], x[np.maximum(sid, 0)], np.nan)
    sv = np.where(has, pp[:, 0], 0.0)
    for lv in range(level, depth + 1):
        k = 2 ** (lv - level)
        lo = np.full((nrow * k, 3), np.nan)
        lo[::k] = pp
        c = np.zeros(nrow * k, cnt.dtype)
        c[::k] = cnt
        los.append(lo)
        his.append(lo.copy())
        counts.append(c)
        if lv < depth:
            axes.append(np.zeros(nrow * k, np.int32))
            v = np.zeros(nrow * k)
            v[::k] = sv
            values.append(v)
    leaf = np.full(2**depth, -1, ids.dtype)
    leaf[:: 2 ** (depth - level)] = sid
    return axes, values, leaf, (los, his, counts)


def _cell_boxes(cfg: KDTreeConfig, axes, values, bb_lo, bb_hi, count, depth: int, margin0: float):
    """Per level ``0 .. depth`` the boxes ``(lo, hi)`` of :func:`_split_levels`' output: top-down
    partition cells intersected with the points' bounding boxes grown by the level's margin
    (zeros for empty nodes). A subtree split on its own gives its part of the whole tree's boxes:
    margins depend on the slots per node only."""
    part_lo = np.full((1, 3), -np.inf)
    part_hi = np.full((1, 3), np.inf)
    lo_levels, hi_levels = [], []
    for level in range(depth + 1):
        m = margin0 * _level_margin_growth(cfg, 2 ** (depth - level))
        empty = (count[level] == 0)[:, None]  # NaN point boxes
        lo = np.subtract(bb_lo[level], m)  # in place from here: large fresh arrays cost page faults
        np.maximum(part_lo, lo, out=lo)
        np.copyto(lo, 0.0, where=empty)
        hi = np.add(bb_hi[level], m)
        np.minimum(part_hi, hi, out=hi)
        np.copyto(hi, 0.0, where=empty)
        lo_levels.append(lo)
        hi_levels.append(hi)
        if level == depth:
            break
        ax, sv = axes[level], values[level]
        rows = np.arange(ax.size)
        # Children's cells: the parent's, the left one's upper / the right one's lower bound on the
        # split axis clipped at the split value (only that column is touched).
        nxt_lo, nxt_hi = np.empty((ax.size, 2, 3)), np.empty((ax.size, 2, 3))  # faster than np.repeat
        nxt_lo[:] = part_lo[:, None]
        nxt_hi[:] = part_hi[:, None]
        nxt_lo, nxt_hi = nxt_lo.reshape(-1, 3), nxt_hi.reshape(-1, 3)
        nxt_hi[2 * rows, ax] = np.minimum(part_hi[rows, ax], sv)
        nxt_lo[2 * rows + 1, ax] = np.maximum(part_lo[rows, ax], sv)
        part_lo, part_hi = nxt_lo, nxt_hi
    return lo_levels, hi_levels


# Superset widths of the candidate cascade, in units of ``num_candidates``, by the points per node
# of the level (1, 4, 8, 16, 32; beyond, x1.35 per doubling): a node's superset must hold its
# children's candidates, which lie farther out the farther the children's centres are from its own,
# i.e. the larger the node. Tuned on surface clouds (1e5..2e6 points at their natural depth, ~1%
# fallbacks; 112k points at depth 21, whose nodes hold 0-2 points); raised to the power dim / 2 for
# the cloud's dimension. They change the speed, never the result (the rows are canonical).
_SUPERSET_FACTORS = ((0.0, 2.0, 3.0, 4.0, 5.0), (1.25, 1.85, 2.75, 3.75, 5.0))  # (log2 points, factor)
_SORT_NETWORK = 256  # numpy sorts rows of up to 256 uint64 keys 3-4x faster per key than wider ones
_GROW_BLOCK = 1024  # growing-level nodes per task (one scipy query, then their subtrees)
_THREADS = max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)
_CASCADE_CHUNK = 128  # growing-level nodes whose subtrees are processed together


def _superset_widths(kc: int, levels: int, points_per_node=None, dim: float = 2.0) -> list[int]:
    """Width per candidate level, top (growing) level first; the bottom level keeps ``kc``.
    ``points_per_node``: per level, top first (default: 2, 4, 8, ... from the bottom up, a tree at
    its natural depth)."""
    if points_per_node is None:
        points_per_node = [2.0 ** (levels - j) for j in range(levels)]
    lp_at, f_at = _SUPERSET_FACTORS
    out = []
    for p in points_per_node[:-1]:
        lp = math.log2(max(float(p), 1.0))
        f = float(np.interp(lp, lp_at, f_at)) if lp <= lp_at[-1] else f_at[-1] * 1.35 ** (lp - lp_at[-1])
        w = max(kc + 1, int(round(f ** (dim / 2.0) * kc)))
        out.append(_SORT_NETWORK if _SORT_NETWORK < w <= 1.1 * _SORT_NETWORK else w)
    return out + [kc]


def _aligned_empty(shape, dtype) -> np.ndarray:
    """``np.empty`` aligned to a page, so that :func:`_device_array` can hand it to JAX without a
    copy (hundreds of MB for the candidate sets of a large tree)."""
    dtype = np.dtype(dtype)
    nbytes = int(np.prod(shape)) * dtype.itemsize
    raw = np.empty(nbytes + 4096, np.uint8)
    off = (-raw.ctypes.data) % 4096
    return raw[off : off + nbytes].view(dtype).reshape(shape)


def _device_array(a: np.ndarray) -> jax.Array:
    """``jnp.asarray(a)``, without a copy where the device is the host and ``a`` is aligned (the
    array then lives in ``a``'s memory, which nothing writes afterwards)."""
    return jax.device_put(np.ascontiguousarray(a), may_alias=True)


def _candidate_sets(xo, kd, center, nonempty, first_level, depth, kc, out_index, cap, dim=2.0):
    """Candidate sets of the levels ``first_level .. depth-1`` (rows in heap order from the first
    node of ``first_level``): the ``kc`` points of ``xo`` nearest each ``centre``, nearest first,
    mapped through ``out_index`` (``[n + 1]``, entry ``n`` = the sentinel), and the distance of the
    farthest one (``radius``). Rows where ``nonempty`` is False (nodes holding no point: nothing
    reads them) are the sentinel ``cap`` with radius 0, and cost nothing.

    A cascade instead of one ``kd.query`` per node. Each growing-level node queries a superset of
    ``w_0 > kc`` points; each node's children then pick from their parent's superset, sorted by
    their own distances: the first ``kc`` are their candidates, the first ``w_(l+1)`` their own
    superset. Each superset ``S`` of a node at ``c`` carries a certified radius ``R``: every point
    closer than ``R`` to ``c`` is in ``S`` (for a query of ``w`` points, ``R`` = the ``w``-th
    distance). For a child at ``c'``, ``|c' - c| = off``, every point closer than ``R - off`` to
    ``c'`` is in ``S`` (triangle inequality), so its pick is exact when its ``kc``-th distance is
    below ``R - off`` (shrunk by a relative 1e-12 for rounding); its own radius is
    ``min(R - off, first distance left out)``. Nodes failing the test (about 1% on surface clouds,
    a third at the bottom levels of a uniform volume) fall back to a direct query. Distances are
    computed as scipy does (float64, ``dx² + dy² + dz²``) and ordered as one uint64 key per entry:
    the squared distance's bits with its low bits replaced by the entry's position in the parent's
    superset; a row whose first ``kc + 1`` keys hold two equal distance bits is sorted again exactly.

    Every row is canonical: the ``kc`` points first by squared distance, then by slot (position in
    ``xo``). Rows whose head has no tie are so by the keys; tied heads (a 2-point node's points are
    often exactly equidistant from its centre; grids, duplicates) are sorted by (distance, slot),
    scipy's rows included, and a tie group reaching past a query's width is queried wider. The
    ``kc``-th distance is below the certified radius, so the whole tie group at the ``kc``-th place
    is in the superset. The rows therefore do not depend on the superset widths
    (:func:`_superset_widths`), on which nodes fall back, or on the blocks and threads."""
    n = xo.shape[0]
    widths = _superset_widths(kc, depth - first_level, [n / 2.0**lv for lv in range(first_level, depth)], dim)
    total = center.shape[0]
    cand = _aligned_empty((total, kc), np.int32)  # every row written once, by its block below
    radius = np.zeros(total, np.float64)
    kth = min(kc, n) - 1  # the farthest candidate that exists
    xs = [np.append(xo[:, a], np.inf) for a in range(3)]  # row n: the sentinel, infinitely far
    nbits = np.uint64((max(widths) - 1).bit_length())
    low = np.uint64((1 << int(nbits)) - 1)
    high = ~low

    def key_of(d2, wp):  # sortable uint64: the squared distance's top bits, then the position
        key = d2.view(np.uint64) & high
        key |= np.arange(wp, dtype=np.uint64)
        return key
    inf_bits = np.float64(np.inf).view(np.uint64)
    ngrow = 2**first_level

    def sq_dist(c, i):  # [m, k] squared distances of the points ``i`` from ``c``, as scipy sums them
        d2 = xs[0][i] - c[:, 0, None]
        d2 *= d2
        for a in (1, 2):
            t = xs[a][i] - c[:, a, None]
            t *= t
            d2 += t
        return d2

    def query(c, w):
        """The ``w`` nearest points of ``c`` in the canonical order, and their distances: scipy's
        query, with the rows whose head (first ``kc + 1``) holds equal distances sorted again by
        (squared distance, slot). A tie group reaching past the queried width is queried wider
        first, so the ``kc``-th place goes to the lowest slot of its group."""
        k = max(w, kc + 1)
        d, i = kd.query(c, k=k, workers=1)
        d, i = np.reshape(d, (-1, k)), np.reshape(i, (-1, k))
        hd = d[:, : kc + 1]
        tie = np.flatnonzero((hd[:, 1:] == hd[:, :-1]).any(axis=1))
        if tie.size:
            ct, dt, it = c[tie], d[tie], i[tie]
            kk = k
            while kk < n:
                open_ = np.flatnonzero(np.isfinite(dt[:, kth]) & (dt[:, kth] == dt[:, -1]))
                if open_.size == 0:
                    break
                kk = min(2 * kk, n)
                dd, ii = kd.query(ct[open_], k=kk, workers=1)
                pad = ((0, 0), (0, kk - dt.shape[1]))
                dt, it = np.pad(dt, pad, constant_values=np.inf), np.pad(it, pad, constant_values=n)
                dt[open_], it[open_] = np.reshape(dd, (-1, kk)), np.reshape(ii, (-1, kk))
            d2 = sq_dist(ct, it)
            order = np.lexsort((it, d2), axis=-1)[:, :k]
            d[tie] = np.sqrt(np.take_along_axis(d2, order, axis=1))
            i[tie] = np.take_along_axis(it, order, axis=1)
        return d[:, :w], i[:, :w]

    def run_block(b0):
        b1 = min(b0 + _GROW_BLOCK, ngrow)
        for s in range(depth - first_level):  # the sentinel in the rows of the block's empty nodes
            r0 = 2 ** (first_level + s) - ngrow
            sl = slice(r0 + (b0 << s), r0 + (b1 << s))
            empty = np.flatnonzero(~nonempty[sl])
            if empty.size == sl.stop - sl.start:
                cand[sl] = cap
            elif empty.size:
                cand[sl.start + empty] = cap
        rows = b0 + np.flatnonzero(nonempty[b0:b1])  # growing-level rows holding points
        if rows.size == 0:
            return
        gd, gi = query(center[rows], widths[0])
        cand[rows] = out_index[gi[:, :kc]]
        radius[rows] = gd[:, kth]
        for j0 in range(0, rows.size, _CASCADE_CHUNK):
            j1 = min(j0 + _CASCADE_CHUNK, rows.size)
            # State per level: the non-empty nodes' local indices (within the level) and supersets.
            loc_idx, sup, rad = rows[j0:j1], gi[j0:j1], gd[j0:j1, -1]
            cp = center[loc_idx]
            for s in range(1, depth - first_level):
                w, wp = widths[s], sup.shape[1]
                npar = sup.shape[0]
                r0 = 2 ** (first_level + s) - ngrow  # row of the level's first node
                kids = (2 * loc_idx[:, None] + np.arange(2)).reshape(-1)
                full = nonempty[r0 + kids]
                if full.all():  # both children of every parent: siblings share the gathers
                    c = center[r0 + kids]
                    c3 = c.reshape(npar, 2, 3)
                    d2, t = np.empty((npar, 2, wp)), np.empty((npar, 2, wp))
                    for a in range(3):  # (dx² + dy²) + dz², as scipy sums
                        np.subtract(xs[a][sup][:, None, :], c3[:, :, a, None], out=t if a else d2)
                        if a:
                            np.multiply(t, t, out=t)
                            d2 += t
                        else:
                            np.multiply(d2, d2, out=d2)
                    m = 2 * npar
                    d2 = d2.reshape(m, wp)
                    psup = None
                    prad, pc = np.repeat(rad, 2), np.repeat(cp, 2, axis=0)
                else:
                    pi = np.repeat(np.arange(npar), 2)[full]
                    kids = kids[full]
                    c = center[r0 + kids]
                    m = kids.size
                    psup = sup[pi]
                    d2 = np.zeros((m, wp))
                    for a in range(3):
                        t = xs[a][psup] - c[:, a, None]
                        t *= t
                        d2 += t
                    prad, pc = rad[pi], cp[pi]
                key = key_of(d2, wp)
                key.sort(axis=1)  # numpy's SIMD sort: faster than a partition at w + a sort of the head
                head = key[:, : kc + 1] >> nbits
                near = np.flatnonzero((head[:, 1:] == head[:, :-1]).any(axis=1))
                if near.size:  # distances equal in their top bits: order those rows exactly
                    sub = d2[near]
                    slot = sup[near // 2] if psup is None else psup[near]
                    order = np.lexsort((slot, sub), axis=-1)  # the canonical order: distance, then slot
                    key[near] = np.take_along_axis(key_of(sub, wp), order, axis=1)
                loc = (key[:, :w] & low).view(np.int64)
                if psup is None:
                    glob = np.take_along_axis(sup, loc.reshape(npar, 2 * w), axis=1).reshape(m, w)
                else:
                    glob = np.take_along_axis(psup, loc, axis=1)
                rk = np.sqrt(d2[np.arange(m), loc[:, kth]])
                off = np.linalg.norm(c - pc, axis=1)
                rc = (prad - off) * (1.0 - 1e-12)
                far = np.minimum(key[:, kc - 1] | low, inf_bits)  # an upper bound of the kc-th
                exact = np.isinf(rc) | (np.sqrt(far.view(np.float64)) < rc)
                if w < wp:
                    rc = np.minimum(rc, np.sqrt((key[:, w] & high).view(np.float64)))
                fb = np.flatnonzero(~exact)
                if fb.size:
                    fd, fi = query(c[fb], w)
                    glob[fb], rk[fb], rc[fb] = fi, fd[:, kth], fd[:, -1]
                cand[r0 + kids] = out_index[glob[:, :kc]]
                radius[r0 + kids] = rk
                loc_idx, sup, rad, cp = kids, glob, rc, c

    threads = min(_THREADS, -(-ngrow // _GROW_BLOCK))
    if threads > 1:
        with ThreadPoolExecutor(threads) as pool:  # scipy and numpy release the GIL
            list(pool.map(run_block, range(0, ngrow, _GROW_BLOCK)))
    else:
        for b0 in range(0, ngrow, _GROW_BLOCK):
            run_block(b0)
    return cand, radius


def build_tree(xyz, alive, cfg: KDTreeConfig = KDTreeConfig(), timings: dict | None = None) -> KDTree:
    """Build the K-D tree of the alive points of ``xyz`` (host-side; see the module docstring).

    Args:
        xyz: ``[C, 3]`` positions (a ``PointState.xyz``; numpy or jax). Dead rows may hold anything.
        alive: ``[C]`` bool mask; at least one alive point, at most ``2**MAX_DEPTH``.
        cfg: static settings.
        timings: if a dict, receives the wall time in seconds of the build's phases
            (``index``: scipy tree + spacing statistics, ``splits``, ``boxes``, ``candidates``).

    Returns:
        A :class:`KDTree` whose float arrays have ``xyz``'s dtype.
    """
    clock = [time.perf_counter()]

    def lap(name):
        now = time.perf_counter()
        if timings is not None:
            timings[name] = now - clock[0]
        clock[0] = now

    pts, msk = _check_inputs(xyz, alive)
    cap = pts.shape[0]
    dtype = pts.dtype if np.issubdtype(pts.dtype, np.floating) else np.float32
    idx = np.flatnonzero(msk)
    x = pts[idx].astype(np.float64)
    n = idx.size
    depth = tree_depth(n, cfg)

    axes, values, leaf, (bb_lo, bb_hi, count) = _split_levels(x, depth)
    lap("splits")

    # The scipy tree over the points in slot order: the candidate supersets below are then
    # spatially local in memory.
    slot_pts = leaf[leaf >= 0]
    kd = cKDTree(x[slot_pts], leafsize=32, balanced_tree=False)  # builds in half the defaults' time
    spacing, lim, dim = _spacing_stats(x, kd, cfg)
    lap("index")

    margin0 = cfg.margin_factor * spacing / math.sqrt(3.0)
    lo_levels, hi_levels = _cell_boxes(cfg, axes, values, bb_lo, bb_hi, count, depth, margin0)
    lo_all = np.concatenate(lo_levels, dtype=dtype)
    hi_all = np.concatenate(hi_levels, dtype=dtype)
    count_all = np.concatenate(count).astype(np.int32)
    valid_all = count_all > 0
    lap("boxes")

    # Candidate sets of the growing + rendering levels: the points nearest each box centre.
    kc = cfg.num_candidates
    first = 2 ** (depth - cfg.num_render_levels - 1) - 1
    last = 2**depth - 1  # exclusive: the leaves have no candidate sets
    center = 0.5 * (lo_all[first:last].astype(np.float64) + hi_all[first:last].astype(np.float64))
    out_index = np.append(idx[slot_pts], cap).astype(np.int32)
    cand, radius = _candidate_sets(
        kd.data, kd, center, count_all[first:last] > 0, depth - cfg.num_render_levels - 1, depth, kc, out_index, cap,
        dim,
    )
    # Validity at the rendering levels: the released code's "too spread out" rule.
    r0 = 2 ** (depth - cfg.num_render_levels) - 1
    sl = slice(r0, last)
    diag = np.linalg.norm(hi_all[sl].astype(np.float64) - lo_all[sl].astype(np.float64), axis=1)
    too_large = (radius[r0 - first :] > lim) | (diag > 2.0 * lim)
    valid_all[sl] &= ~too_large

    perm = np.where(leaf >= 0, idx[np.maximum(leaf, 0)], cap).astype(np.int32)
    lap("candidates")
    return KDTree(
        lo=jnp.asarray(lo_all),
        hi=jnp.asarray(hi_all),
        count=jnp.asarray(count_all),
        valid=jnp.asarray(valid_all),
        split_axis=jnp.asarray(np.concatenate(axes).astype(np.int32)),
        split_value=jnp.asarray(np.concatenate(values).astype(dtype)),
        perm=jnp.asarray(perm),
        candidates=_device_array(cand),
        spacing=jnp.asarray(spacing, dtype),
        depth=depth,
        capacity=cap,
        num_render_levels=cfg.num_render_levels,
    )

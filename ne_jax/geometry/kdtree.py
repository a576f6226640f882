"""The flattened K-D tree behind NeuralEditor's "K-D voxels" (data flow step 1 of DESIGN.md).

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
``margin_factor * spacing / sqrt(3) * clip(sqrt(k * s / 2), 1, margin_growth_cap)`` for a node of
``s`` slots, ``k = 1`` at and below the top rendering level and ``k = 2`` above, ``spacing`` the mean
nearest-neighbour distance — the released code's rule (its extra per-axis ``extent / sqrt(N)`` bound
and its special case for cells reaching far past the points are left out: the first makes boxes of a
planar cloud flat and unhittable). Boxes of one level are therefore disjoint up to shared faces,
and each box contains its children's.

Built on the host (numpy + ``scipy.spatial.cKDTree``), not under ``jit``. Measured on the 2-core
CPU (``experiments/bench_geometry.py``, field ``jit_vs_host``, 2^20 surface points): numpy's split
pass over all 20 levels took 2.8 s (0.14 s a level), while a single level's XLA ``argsort`` under
jit took 0.18-0.19 s — a jitted build would be slower before even starting on the candidate sets,
which need a 96-NN query per node, where scipy's C++ tree is 10-35x faster than the JAX KNN
structures measured for DESIGN.md. Building is rare (after edits and point-cloud optimisation);
everything the tree feeds (``intersect``, ``knn_interpolate``) is jit-compiled.

Cost: the candidate sets dominate (2M points: ~2M queries of 96 neighbours, about 2/3 of the build);
the structure alone (statistics, splits, boxes) is ~10x a bare ``cKDTree`` build.
"""

from __future__ import annotations

import dataclasses
import math
import time

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from scipy.spatial import cKDTree


@dataclasses.dataclass(frozen=True)
class KDTreeConfig:
    """Static settings of the K-D tree, its traversal and the KNN interpolation (hashable: pass it
    as a static argument). Presets: :meth:`tiny`, :meth:`default`, :meth:`paper`."""

    depth: int | None = None
    """Tree depth ``D`` (``2**D`` point slots, ``D + 1`` levels, level ``D`` = single-point leaves).
    ``None``: the smallest ``D`` with ``2**D >= alive count``, at least ``num_render_levels + 1``.
    A fixed value keeps every array shape (and so every compiled function) the same across
    rebuilds; building fails if the alive count exceeds ``2**depth``."""

    max_depth: int = 21
    """Largest depth allowed (the paper: 21 levels, up to 2**21 ~ 2M points)."""

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

    margin_growth_cap: float = 8.0
    """Upper bound of the per-level margin growth ``sqrt(k * node_size / 2)``."""

    validity_std_factor: float = 5.0
    """Validity threshold ``lim = mean + validity_std_factor * std`` of each point's distance to its
    ``int(1.05 * candidates + 1.5)``-th nearest point (statistics on a subsample). A rendering-level
    box is invalid (traversed, never emitted) when its candidates reach farther than ``lim`` from its
    centre or its diagonal exceeds ``2 * lim``: the released code's "too spread out" rule."""

    validity_floor_factor: float = 4.0
    """Lower bound of ``lim`` in units of ``spacing``: tiny clouds (fewer points than candidates)
    have degenerate statistics."""

    stat_samples: int = 16384
    """Points sampled (fixed seed) to estimate ``spacing`` and ``lim``; all points if fewer."""

    fallback_spacing: float = 1e-2
    """``spacing`` (absolute units) when it cannot be measured: one point, or all points identical
    and at one place. Otherwise a zero mean nearest-neighbour distance falls back to
    ``extent / n**(1/3)``."""

    min_hit_factor: float = 1.0 / 32.0
    """A ray hits a box only if the clipped intersection is longer than ``min_hit_factor * spacing``
    (released code: ``unit_len / 16`` with ``unit_len = spacing / 2``). Rays through edges, corners or
    grazing a box are thereby misses, deterministically."""

    knn_eps_factor: float = 5e-4
    """Distance offset in the KNN weights, in units of ``spacing`` (released code:
    ``1e-3 * unit_len``): ``log(dist + eps)`` stays finite at a point."""

    frontier_capacity: int = 64
    """Nodes kept per ray and level during traversal; more are dropped and counted as overflow."""

    max_segments: int = 32
    """Segment slots per ray in :class:`~ne_jax.geometry.intersect.Segments`; more are counted."""

    exact_chunk: int = 256
    """Samples per chunk in the brute-force exact KNN mode (memory: ``chunk * C`` distances)."""

    seed: int = 0
    """Seed of the statistics subsample (the build is deterministic)."""

    def __post_init__(self):
        def need(cond, name, expected):
            if not cond:
                raise ValueError(f"KDTreeConfig.{name}: expected {expected}, found {getattr(self, name)!r}")

        need(self.num_render_levels >= 1, "num_render_levels", "an integer >= 1")
        need(self.max_depth >= self.num_render_levels + 1, "max_depth", ">= num_render_levels + 1")
        need(self.max_depth <= 30, "max_depth", "<= 30 (int32 node indices)")
        if self.depth is not None:
            need(
                self.num_render_levels + 1 <= self.depth <= self.max_depth,
                "depth",
                f"None or an integer in [num_render_levels + 1, max_depth] = "
                f"[{self.num_render_levels + 1}, {self.max_depth}]",
            )
        need(self.candidate_min >= 1, "candidate_min", "an integer >= 1")
        need(1 <= self.knn_k <= self.num_candidates, "knn_k", f"an integer in [1, {self.num_candidates}]")
        need(self.margin_factor > 0, "margin_factor", "> 0")
        need(self.margin_growth_cap >= 1, "margin_growth_cap", ">= 1")
        need(self.validity_std_factor >= 0, "validity_std_factor", ">= 0")
        need(self.validity_floor_factor > 0, "validity_floor_factor", "> 0")
        need(self.stat_samples >= 1, "stat_samples", ">= 1")
        need(self.fallback_spacing > 0, "fallback_spacing", "> 0")
        need(self.min_hit_factor >= 0, "min_hit_factor", ">= 0")
        need(self.knn_eps_factor > 0, "knn_eps_factor", "> 0")
        need(self.frontier_capacity >= 2, "frontier_capacity", "an integer >= 2")
        need(self.max_segments >= 1, "max_segments", "an integer >= 1")
        need(self.exact_chunk >= 1, "exact_chunk", "an integer >= 1")

    @property
    def num_candidates(self) -> int:
        """Width of every candidate set: ``max(candidate_min, 2 * 2**(num_render_levels + 1))``."""
        return max(self.candidate_min, 2 * 2 ** (self.num_render_levels + 1))

    def replace(self, **changes) -> "KDTreeConfig":
        return dataclasses.replace(self, **changes)

    @classmethod
    def tiny(cls, **changes) -> "KDTreeConfig":
        """Small capacities for tests and toy scenes."""
        base = cls(candidate_min=16, knn_k=8, num_render_levels=2, frontier_capacity=16, max_segments=16)
        return dataclasses.replace(base, **changes)

    @classmethod
    def default(cls, **changes) -> "KDTreeConfig":
        """The paper's settings with traversal capacities sized for surface-like clouds."""
        return dataclasses.replace(cls(), **changes)

    @classmethod
    def paper(cls, **changes) -> "KDTreeConfig":
        """The paper's appendix: 21 levels (fixed), 4 rendering levels + growing, K = 32, 96 candidates."""
        return dataclasses.replace(cls(depth=21), **changes)


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
            the box centre, nearest first, sentinel ``capacity``; row ``g - first_candidate_node``.
        spacing: ``[]`` mean nearest-neighbour distance of the alive points (the length unit).
        depth, capacity, num_render_levels: static ints.
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
    return float(np.clip(math.sqrt(k * slots / 2.0), 1.0, cfg.margin_growth_cap))


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
    if d > cfg.max_depth:
        raise ValueError(
            f"alive: expected at most 2**max_depth = {2**cfg.max_depth} alive points, found {num_alive} "
            f"(raise KDTreeConfig.max_depth)"
        )
    return d


def _spacing_and_limit(x: np.ndarray, kd: cKDTree, cfg: KDTreeConfig) -> tuple[float, float]:
    """Mean nearest-neighbour distance and the validity threshold ``lim`` (see the config)."""
    n = x.shape[0]
    rng = np.random.default_rng(cfg.seed)
    sample = x if n <= cfg.stat_samples else x[rng.choice(n, cfg.stat_samples, replace=False)]
    kv = min(int(1.05 * cfg.num_candidates + 1.5), n)
    kq = max(kv, 2) if n >= 2 else 1
    dist, _ = kd.query(sample, k=kq, workers=-1)
    dist = np.asarray(dist, np.float64).reshape(sample.shape[0], kq)
    spacing = float(np.mean(dist[:, 1])) if n >= 2 else 0.0
    if not spacing > 0.0:
        extent = float(np.max(x.max(axis=0) - x.min(axis=0))) if n >= 2 else 0.0
        spacing = extent / n ** (1.0 / 3.0) if extent > 0 else float(cfg.fallback_spacing)
    dk = dist[:, kv - 1]
    lim = float(np.mean(dk) + cfg.validity_std_factor * np.std(dk))
    return spacing, max(lim, cfg.validity_floor_factor * spacing)


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


def _split_levels(x: np.ndarray, depth: int):
    """Top-down median splits. Returns per-level ``(split_axis, split_value)`` for levels
    ``0 .. depth-1`` and the final leaf permutation (local indices, -1 = empty slot)."""
    n = x.shape[0]
    p = 2**depth
    rows = np.full((1, p), -1, np.int64)
    rows[0, :n] = np.arange(n)
    cnt = np.array([n], np.int64)
    axes, values = [], []
    for level in range(depth):
        nrow, s = rows.shape
        real = rows >= 0
        safe = np.where(real, rows, 0)
        # Widest axis of each node's points (empty / single-point nodes: axis 0).
        pts = x[safe]  # [nrow, s, 3]
        lo = np.where(real[..., None], pts, np.inf).min(axis=1)
        hi = np.where(real[..., None], pts, -np.inf).max(axis=1)
        ext = np.where(cnt[:, None] > 0, hi - lo, 0.0)
        axis = np.argmax(ext, axis=1)
        vals = np.take_along_axis(pts, axis[:, None, None], axis=2)[..., 0]
        vals = np.where(real, vals, np.inf)
        kl = (cnt + 1) // 2
        kth = np.unique(np.concatenate([kl - 1, kl, cnt - 1, cnt]))
        kth = kth[(kth >= 0) & (kth < s)]
        if kth.size:
            order = np.argpartition(vals, kth, axis=1)
            rows = np.take_along_axis(rows, order, axis=1)
            vals = np.take_along_axis(vals, order, axis=1)
        # Now each row holds its real points first, with the ceil(m/2) smallest before index kl.
        ar = np.arange(nrow)
        lmax = vals[ar, np.maximum(kl - 1, 0)]
        rmin = vals[ar, np.minimum(kl, s - 1)]
        has_right = cnt > kl
        split = np.where(has_right, 0.5 * (lmax + rmin), np.where(cnt > 0, lmax, 0.0))
        axes.append(axis.astype(np.int32))
        values.append(split)
        half = s // 2
        j = np.arange(half)[None, :]
        left = np.where(j < kl[:, None], rows[:, :half], -1)
        ridx = np.minimum(kl[:, None] + j, s - 1)
        right = np.where(j < (cnt - kl)[:, None], np.take_along_axis(rows, ridx, axis=1), -1)
        rows = np.stack([left, right], axis=1).reshape(2 * nrow, half)
        cnt = np.stack([kl, cnt - kl], axis=1).reshape(-1)
    return axes, values, rows[:, 0]


def build_tree(xyz, alive, cfg: KDTreeConfig = KDTreeConfig(), timings: dict | None = None) -> KDTree:
    """Build the K-D tree of the alive points of ``xyz`` (host-side; see the module docstring).

    Args:
        xyz: ``[C, 3]`` positions (a ``PointState.xyz``; numpy or jax). Dead rows may hold anything.
        alive: ``[C]`` bool mask; at least one alive point, at most ``2**max_depth``.
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
    p = 2**depth

    kd = cKDTree(x)
    spacing, lim = _spacing_and_limit(x, kd, cfg)
    lap("index")

    axes, values, leaf = _split_levels(x, depth)
    lap("splits")

    # Bottom-up bounding boxes and counts, per level.
    leaf_real = leaf >= 0
    leaf_pts = x[np.where(leaf_real, leaf, 0)]
    bb_lo = [None] * (depth + 1)
    bb_hi = [None] * (depth + 1)
    count = [None] * (depth + 1)
    bb_lo[depth] = np.where(leaf_real[:, None], leaf_pts, np.inf)
    bb_hi[depth] = np.where(leaf_real[:, None], leaf_pts, -np.inf)
    count[depth] = leaf_real.astype(np.int64)
    for level in range(depth - 1, -1, -1):
        bb_lo[level] = np.minimum(bb_lo[level + 1][0::2], bb_lo[level + 1][1::2])
        bb_hi[level] = np.maximum(bb_hi[level + 1][0::2], bb_hi[level + 1][1::2])
        count[level] = count[level + 1][0::2] + count[level + 1][1::2]

    # Top-down partition cells, intersected with the grown bounding boxes.
    margin0 = cfg.margin_factor * spacing / math.sqrt(3.0)
    part_lo = np.full((1, 3), -np.inf)
    part_hi = np.full((1, 3), np.inf)
    lo_levels, hi_levels = [], []
    for level in range(depth + 1):
        m = margin0 * _level_margin_growth(cfg, 2 ** (depth - level))
        nonempty = (count[level] > 0)[:, None]
        lo = np.where(nonempty, np.maximum(part_lo, bb_lo[level] - m), 0.0)
        hi = np.where(nonempty, np.minimum(part_hi, bb_hi[level] + m), 0.0)
        lo_levels.append(lo)
        hi_levels.append(hi)
        if level == depth:
            break
        ax, sv = axes[level], values[level]
        onehot = np.arange(3)[None, :] == ax[:, None]
        l_hi = np.where(onehot, np.minimum(part_hi, sv[:, None]), part_hi)
        r_lo = np.where(onehot, np.maximum(part_lo, sv[:, None]), part_lo)
        part_lo = np.stack([part_lo, r_lo], axis=1).reshape(-1, 3)
        part_hi = np.stack([l_hi, part_hi], axis=1).reshape(-1, 3)
    lo_all = np.concatenate(lo_levels).astype(dtype)
    hi_all = np.concatenate(hi_levels).astype(dtype)
    count_all = np.concatenate(count).astype(np.int32)
    valid_all = count_all > 0
    lap("boxes")

    # Candidate sets of the growing + rendering levels: the points nearest each box centre.
    kc = cfg.num_candidates
    first = 2 ** (depth - cfg.num_render_levels - 1) - 1
    last = 2**depth - 1  # exclusive: the leaves have no candidate sets
    centre = 0.5 * (lo_all[first:last].astype(np.float64) + hi_all[first:last].astype(np.float64))
    cand = np.empty((last - first, kc), np.int32)
    radius = np.empty((last - first,), np.float64)
    chunk = 1 << 15
    for s in range(0, last - first, chunk):
        d, i = kd.query(centre[s : s + chunk], k=kc, workers=-1)
        d = np.asarray(d).reshape(-1, kc)
        i = np.asarray(i).reshape(-1, kc)
        found = i < n
        cand[s : s + chunk] = np.where(found, idx[np.minimum(i, n - 1)], cap)
        radius[s : s + chunk] = np.where(found, d, 0.0).max(axis=1)
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
        candidates=jnp.asarray(cand),
        spacing=jnp.asarray(spacing, dtype),
        depth=depth,
        capacity=cap,
        num_render_levels=cfg.num_render_levels,
    )

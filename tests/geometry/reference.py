"""Slow, obvious references for the geometry core: numpy, recursive, float64.

They take the built tree's arrays (so they test traversal and interpolation, not box placement,
which ``check_tree`` checks separately against the points).
"""

from __future__ import annotations

import math

import numpy as np


def slab64(lo, hi, o, d, near, far, min_len):
    """Float64 ray-box test with the documented rule. Returns ``(t_lo, t_hi, hit, slack)`` where
    ``slack = t_hi - t_lo - min_len`` (hit iff ``slack > 0``)."""
    lo, hi, o, d = (np.asarray(a, np.float64) for a in (lo, hi, o, d))
    enter, exit_ = -math.inf, math.inf
    for a in range(3):
        if d[a] == 0.0:  # also -0.0
            if not (lo[a] <= o[a] <= hi[a]):
                return 0.0, 0.0, False, -math.inf
        else:
            t1 = (lo[a] - o[a]) / d[a]
            t2 = (hi[a] - o[a]) / d[a]
            enter = max(enter, min(t1, t2))
            exit_ = min(exit_, max(t1, t2))
    t_lo = max(enter, float(near))
    t_hi = min(exit_, float(far))
    slack = t_hi - t_lo - float(min_len)
    return t_lo, t_hi, slack > 0, slack


def minimal_voxels(tree, o, d, near, far, min_len, first_emit):
    """Recursive traversal. Returns ``(segments, min_abs_slack)``: ``segments`` a list of
    ``(node, level, t_lo, t_hi)`` sorted by ``t_lo``; ``min_abs_slack`` the smallest ``|slack|`` of
    any box tested (small = a float32 implementation may legitimately decide differently)."""
    lo = np.asarray(tree.lo, np.float64)
    hi = np.asarray(tree.hi, np.float64)
    count = np.asarray(tree.count)
    valid = np.asarray(tree.valid)
    depth = tree.depth
    out = []
    worst = [math.inf]

    def test(g):
        if count[g] == 0:
            return 0.0, 0.0, False
        t_lo, t_hi, hit, slack = slab64(lo[g], hi[g], o, d, near, far, min_len)
        worst[0] = min(worst[0], abs(slack))
        return t_lo, t_hi, hit

    def visit(g, level, t_lo, t_hi):
        if level == depth - 1:
            if valid[g] and level >= first_emit:
                out.append((g, level, t_lo, t_hi))
            return
        kids = [(c,) + test(c) for c in (2 * g + 1, 2 * g + 2)]
        hits = [k for k in kids if k[3]]
        if not hits:
            if valid[g] and level >= first_emit:
                out.append((g, level, t_lo, t_hi))
            return
        for c, a, b, _ in hits:
            visit(c, level + 1, a, b)

    t_lo, t_hi, hit = test(0)
    if hit:
        visit(0, 0, t_lo, t_hi)
    out.sort(key=lambda s: s[2])
    return out, worst[0]


def _softmax_weights(conf_logit, dist, eps):
    log_conf = -np.logaddexp(0.0, -np.asarray(conf_logit, np.float64))
    logit = log_conf - np.log(dist + eps)
    logit = logit - logit.max()
    w = np.exp(logit)
    return w / w.sum()


def knn_reference(xyz, alive, conf_logit, q, k, eps, candidates=None):
    """Float64 KNN weights of one sample ``q``: the ``k`` nearest alive points (among
    ``candidates`` if given). Returns ``(index, weight)`` (possibly fewer than ``k`` entries) and the
    distance of the ``k``-th and ``k+1``-th pool point (a tie there makes the choice ambiguous)."""
    xyz = np.asarray(xyz, np.float64)
    alive = np.asarray(alive)
    pool = np.flatnonzero(alive) if candidates is None else np.asarray(candidates)
    pool = pool[(pool < xyz.shape[0])]
    pool = pool[alive[pool]]
    dist = np.linalg.norm(xyz[pool] - np.asarray(q, np.float64), axis=1)
    order = np.argsort(dist, kind="stable")
    take = order[:k]
    gap = (dist[order[k]] - dist[order[k - 1]]) if len(order) > k else math.inf
    if take.size == 0:
        return np.zeros(0, np.int64), np.zeros(0), gap
    w = _softmax_weights(np.asarray(conf_logit, np.float64)[pool[take]], dist[take], eps)
    return pool[take], w, gap


def interpolate_reference(index, weight, values):
    v = np.asarray(values, np.float64)
    if index.size == 0:
        return np.zeros(v.shape[1:])
    return np.tensordot(weight, v[index], axes=(0, 0))


def check_tree(tree, xyz, alive, cfg):
    """Assert the structural invariants of a built tree against its points (float64)."""
    xyz = np.asarray(xyz, np.float64)
    alive = np.asarray(alive)
    lo = np.asarray(tree.lo, np.float64)
    hi = np.asarray(tree.hi, np.float64)
    count = np.asarray(tree.count)
    valid = np.asarray(tree.valid)
    perm = np.asarray(tree.perm)
    cap = xyz.shape[0]
    depth = tree.depth
    p = 2**depth
    n = int(alive.sum())
    assert tree.capacity == cap
    assert perm.shape == (p,) and lo.shape == (2 * p - 1, 3) and count.shape == (2 * p - 1,)
    # The permutation places every alive point exactly once; the rest is the sentinel.
    real = perm[perm < cap]
    assert np.all(perm[perm >= cap] == cap)
    assert sorted(real.tolist()) == sorted(np.flatnonzero(alive).tolist())
    assert count[0] == n
    axes = np.asarray(tree.split_axis)
    split = np.asarray(tree.split_value, np.float64)
    for level in range(depth + 1):
        s = 2 ** (depth - level)
        start = 2**level - 1
        rows = perm.reshape(-1, s)
        c = (rows < cap).sum(axis=1)
        np.testing.assert_array_equal(count[start : start + 2**level], c)
        assert c.max() - c.min() <= 1, f"level {level}: unbalanced counts {c.min()}..{c.max()}"
        for i in range(2**level):
            g = start + i
            pts = xyz[rows[i][rows[i] < cap]]
            if pts.size == 0:
                assert not valid[g]
                continue
            assert np.all(pts >= lo[g]) and np.all(pts <= hi[g]), f"node {g}: points outside box"
            if level > 0:
                par = (g - 1) // 2
                assert np.all(lo[g] >= lo[par]) and np.all(hi[g] <= hi[par]), f"node {g} not inside parent"
            if level < depth and pts.shape[0] >= 2:
                ax = axes[g]
                ext = pts.max(axis=0) - pts.min(axis=0)
                assert ext[ax] == ext.max(), f"node {g}: split axis {ax} not the widest {ext}"
                kids = [rows[i][: s // 2], rows[i][s // 2 :]]
                left = xyz[kids[0][kids[0] < cap], ax]
                right = xyz[kids[1][kids[1] < cap], ax]
                assert left.size == (pts.shape[0] + 1) // 2
                if right.size:
                    assert left.max() <= split[g] + 1e-6 * (1 + abs(split[g]))
                    assert right.min() >= split[g] - 1e-6 * (1 + abs(split[g]))
    # Boxes of one level have disjoint interiors.
    for level in range(1, min(depth, 8) + 1):
        start = 2**level - 1
        idx = [g for g in range(start, start + 2**level) if count[g] > 0]
        for a_i, a in enumerate(idx):
            for b in idx[a_i + 1 :]:
                overlap = np.minimum(hi[a], hi[b]) - np.maximum(lo[a], lo[b])
                assert np.any(overlap <= 1e-6 * (1 + np.abs(hi[a]).max())), f"boxes {a}, {b} overlap"


def check_candidates(tree, xyz, alive, cfg, max_nodes=400):
    """Candidate sets are the ``num_candidates`` alive points nearest each box centre (distances
    compared, so ties may pick either point); empty nodes' sets are the sentinel only."""
    xyz = np.asarray(xyz, np.float64)
    alive = np.asarray(alive)
    cand = np.asarray(tree.candidates)
    lo = np.asarray(tree.lo, np.float64)
    hi = np.asarray(tree.hi, np.float64)
    first = tree.first_candidate_node
    pool = np.flatnonzero(alive)
    kc = cfg.num_candidates
    rows = np.linspace(0, cand.shape[0] - 1, min(max_nodes, cand.shape[0])).astype(int)
    count = np.asarray(tree.count)
    for r in rows:
        g = first + r
        if count[g] == 0:  # empty node: nothing reads its row, which holds only the sentinel
            assert np.all(cand[r] == xyz.shape[0]), f"node {g}: empty, candidates {cand[r]}"
            continue
        c = 0.5 * (lo[g] + hi[g])
        d_all = np.sort(np.linalg.norm(xyz[pool] - c, axis=1))[:kc]
        got = cand[r][cand[r] < xyz.shape[0]]
        assert len(set(got.tolist())) == got.size
        assert np.all(alive[got])
        d_got = np.sort(np.linalg.norm(xyz[got] - c, axis=1))
        np.testing.assert_allclose(d_got, d_all, rtol=1e-5, atol=1e-6 * (1 + np.abs(c).max()))


# ---------------------------------------------------------------------------------------------------
# The K-D tree build as it was at commit b94223a (a verbatim copy, helpers prefixed ``_ref``): the
# reference that the optimised ``build_tree`` must reproduce bit for bit, except the candidate rows of
# empty nodes, which ``build_tree`` fills with the sentinel (``empty_sentinel=True`` does the same here).

import os  # noqa: E402
import time  # noqa: E402
from concurrent.futures import ThreadPoolExecutor  # noqa: E402

import jax.numpy as jnp  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402

from ne_jax.geometry.kdtree import (  # noqa: E402
    FALLBACK_SPACING,
    MARGIN_GROWTH_CAP,
    STAT_SAMPLES,
    STAT_SEED,
    VALIDITY_FLOOR_FACTOR,
    VALIDITY_STD_FACTOR,
    KDTree,
    KDTreeConfig,
    tree_depth,
)


def _ref_level_margin_growth(cfg: KDTreeConfig, slots: int) -> float:
    k = 1.0 if slots <= 2**cfg.num_render_levels else 2.0
    return float(np.clip(math.sqrt(k * slots / 2.0), 1.0, MARGIN_GROWTH_CAP))


def _ref_spacing_and_limit(x: np.ndarray, kd: cKDTree, cfg: KDTreeConfig) -> tuple[float, float]:
    """Mean nearest-neighbour distance and the validity threshold ``lim`` (see the config)."""
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
    return spacing, max(lim, VALIDITY_FLOOR_FACTOR * spacing)


def _ref_check_inputs(xyz, alive) -> tuple[np.ndarray, np.ndarray]:
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


def _ref_row_reduce(f, a):
    """``f``-reduction of each row of ``a [rows, w]`` (elementwise over columns for short rows:
    numpy's axis reduction is slow there)."""
    if a.shape[1] > 16:
        return f.reduce(a, axis=1)
    r = a[:, 0].copy()
    for j in range(1, a.shape[1]):
        f(r, a[:, j], out=r)
    return r


def _ref_split_levels(x: np.ndarray, depth: int):
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
        half = w // 2
        lo = np.stack([_ref_row_reduce(np.fmin, pts[a]) for a in range(3)], axis=1)
        hi = np.stack([_ref_row_reduce(np.fmax, pts[a]) for a in range(3)], axis=1)
        los.append(lo)
        his.append(hi)
        counts.append(cnt)
        ext = np.where(cnt[:, None] > 1, hi - lo, 0.0)  # empty / single-point nodes: axis 0
        axis = np.argmax(ext, axis=1)
        rows = np.arange(nrow)
        key = pts[axis, rows]  # [nrow, w]
        pad = ids < 0
        key[pad] = np.inf
        kl = (cnt + 1) // 2
        need = np.flatnonzero(kl < half)  # the left child takes one pad
        if need.size:
            key[need, np.argmax(pad[need], axis=1)] = -np.inf
        order = np.argpartition(key, half - 1, axis=1)
        flat = (order + (rows * w)[:, None]).ravel()
        key = key.ravel()[flat].reshape(nrow, w)
        pts = pts.reshape(3, -1)[:, flat].reshape(3, 2 * nrow, half)
        ids = ids.ravel()[flat].reshape(2 * nrow, half)
        lmax = key[:, half - 1]
        rmin = _ref_row_reduce(np.minimum, key[:, half:])
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

def _ref_cell_boxes(cfg: KDTreeConfig, axes, values, bb_lo, bb_hi, count, depth: int, margin0: float):
    """Per level ``0 .. depth`` the boxes ``(lo, hi)`` of :func:`_ref_split_levels`' output: top-down
    partition cells intersected with the points' bounding boxes grown by the level's margin
    (zeros for empty nodes). A subtree split on its own gives its part of the whole tree's boxes:
    margins depend on the slots per node only."""
    part_lo = np.full((1, 3), -np.inf)
    part_hi = np.full((1, 3), np.inf)
    lo_levels, hi_levels = [], []
    for level in range(depth + 1):
        m = margin0 * _ref_level_margin_growth(cfg, 2 ** (depth - level))
        nonempty = (count[level] > 0)[:, None]  # empty: NaN point boxes
        lo_levels.append(np.where(nonempty, np.maximum(part_lo, bb_lo[level] - m), 0.0))
        hi_levels.append(np.where(nonempty, np.minimum(part_hi, bb_hi[level] + m), 0.0))
        if level == depth:
            break
        ax, sv = axes[level], values[level]
        onehot = np.arange(3)[None, :] == ax[:, None]
        l_hi = np.where(onehot, np.minimum(part_hi, sv[:, None]), part_hi)
        r_lo = np.where(onehot, np.maximum(part_lo, sv[:, None]), part_lo)
        part_lo = np.stack([part_lo, r_lo], axis=1).reshape(-1, 3)
        part_hi = np.stack([l_hi, part_hi], axis=1).reshape(-1, 3)
    return lo_levels, hi_levels


# Superset widths of the candidate cascade, in units of ``num_candidates``, indexed from the bottom
# candidate level up (the bottom level keeps only its own candidates). Wider sets mean more distance
# work per node and fewer fallback queries; these were tuned on surface clouds (1e5..2e6 points,
# ~1% fallbacks). They change the speed, never the result.
_ref_SUPERSET_FACTORS = (1.0, 1.85, 2.75, 3.75, 5.0)
_ref_GROW_BLOCK = 1024  # growing-level nodes per task (one scipy query, then their subtrees)
_ref_THREADS = max(1, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)
_ref_CASCADE_CHUNK = 32  # growing-level nodes whose subtrees are processed together (cache-sized)


def _ref_superset_widths(kc: int, levels: int) -> list[int]:
    """Width per candidate level, top (growing) level first."""
    f = _ref_SUPERSET_FACTORS
    grow = [f[-1] * 1.35 ** (j - len(f) + 1) if j >= len(f) else f[j] for j in range(levels)]
    return [max(kc, int(round(v * kc))) for v in grow[::-1]]


def _ref_candidate_sets(xo, kd, center, first_level, depth, kc, out_index):
    """Candidate sets of the levels ``first_level .. depth-1`` (rows in heap order from the first
    node of ``first_level``): the ``kc`` points of ``xo`` nearest each ``centre``, nearest first,
    mapped through ``out_index`` (``[n + 1]``, entry ``n`` = the sentinel), and the distance of the
    farthest one (``radius``).

    A cascade instead of one ``kd.query`` per node. Each growing-level node queries a superset of
    ``w_0 > kc`` points; each node's children then pick from their parent's superset, sorted by
    their own distances: the first ``kc`` are their candidates, the first ``w_(l+1)`` their own
    superset. Each superset ``S`` of a node at ``c`` carries a certified radius ``R``: every point
    closer than ``R`` to ``c`` is in ``S`` (for a query of ``w`` points, ``R`` = the ``w``-th
    distance). For a child at ``c'``, ``|c' - c| = off``, every point closer than ``R - off`` to
    ``c'`` is in ``S`` (triangle inequality), so its pick is exact when its ``kc``-th distance is
    below ``R - off`` (shrunk by a relative 1e-12 for rounding); its own radius is
    ``min(R - off, first distance left out)``. Nodes failing the test (about 1% on surface clouds)
    fall back to a direct query. Distances are computed as scipy does (float64, ``dx² + dy² + dz²``)
    and sorted as one uint64 key per entry: the squared distance's bits with its low bits replaced
    by the entry's position in the parent's superset, so distances equal to ~1e-13 relative are
    ordered by that position (ties: any order is correct)."""
    n = xo.shape[0]
    widths = _ref_superset_widths(kc, depth - first_level)
    total = center.shape[0]
    cand = np.empty((total, kc), np.int32)
    radius = np.empty(total, np.float64)
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

    def query(c, k):
        d, i = kd.query(c, k=k, workers=1)
        return np.reshape(d, (-1, k)), np.reshape(i, (-1, k))

    def run_block(b0):
        b1 = min(b0 + _ref_GROW_BLOCK, ngrow)
        gd, gi = query(center[b0:b1], widths[0])
        cand[b0:b1] = out_index[gi[:, :kc]]
        radius[b0:b1] = gd[:, kth]
        for c0 in range(b0, b1, _ref_CASCADE_CHUNK):
            c1 = min(c0 + _ref_CASCADE_CHUNK, b1)
            sup, rad, cp = gi[c0 - b0 : c1 - b0], gd[c0 - b0 : c1 - b0, -1], center[c0:c1]
            for s in range(1, depth - first_level):
                w, wp = widths[s], sup.shape[1]
                npar, m = sup.shape[0], 2 * sup.shape[0]
                r0 = 2 ** (first_level + s) - ngrow + (c0 << s)
                c = center[r0 : r0 + m]
                c3 = c.reshape(npar, 2, 3)
                d2 = np.zeros((npar, 2, wp))
                for a in range(3):
                    t = xs[a][sup][:, None, :] - c3[:, :, a, None]
                    t *= t
                    d2 += t
                d2 = d2.reshape(m, wp)
                key = key_of(d2, wp)
                key.sort(axis=1)
                head = key[:, : kc + 1] >> nbits
                near = np.flatnonzero((head[:, 1:] == head[:, :-1]).any(axis=1))
                if near.size:  # distances equal in their top bits: order those rows exactly
                    sub = d2[near]
                    order = np.lexsort((np.broadcast_to(np.arange(wp), sub.shape), sub), axis=-1)
                    key[near] = np.take_along_axis(key_of(sub, wp), order, axis=1)
                loc = (key[:, :w] & low).view(np.int64)
                glob = np.take_along_axis(sup, loc.reshape(npar, 2 * w), axis=1).reshape(m, w)
                rk = np.sqrt(d2[np.arange(m), loc[:, kth]])
                off = np.linalg.norm(c - np.repeat(cp, 2, axis=0), axis=1)
                rc = (np.repeat(rad, 2) - off) * (1.0 - 1e-12)
                far = np.minimum(key[:, kc - 1] | low, inf_bits)  # an upper bound of the kc-th
                exact = np.isinf(rc) | (np.sqrt(far.view(np.float64)) < rc)
                if w < wp:
                    rc = np.minimum(rc, np.sqrt((key[:, w] & high).view(np.float64)))
                fb = np.flatnonzero(~exact)
                if fb.size:
                    fd, fi = query(c[fb], w)
                    glob[fb], rk[fb], rc[fb] = fi, fd[:, kth], fd[:, -1]
                cand[r0 : r0 + m] = out_index[glob[:, :kc]]
                radius[r0 : r0 + m] = rk
                sup, rad, cp = glob, rc, c

    threads = min(_ref_THREADS, -(-ngrow // _ref_GROW_BLOCK))
    if threads > 1:
        with ThreadPoolExecutor(threads) as pool:  # scipy and numpy release the GIL
            list(pool.map(run_block, range(0, ngrow, _ref_GROW_BLOCK)))
    else:
        for b0 in range(0, ngrow, _ref_GROW_BLOCK):
            run_block(b0)
    return cand, radius


def build_tree_reference(xyz, alive, cfg: KDTreeConfig = KDTreeConfig(), timings: dict | None = None,
                         empty_sentinel: bool = True) -> KDTree:
    """(Reference; ``empty_sentinel``: candidate rows of empty nodes hold the sentinel only.) Build
    the K-D tree of the alive points of ``xyz`` (host-side; see the module docstring).

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

    pts, msk = _ref_check_inputs(xyz, alive)
    cap = pts.shape[0]
    dtype = pts.dtype if np.issubdtype(pts.dtype, np.floating) else np.float32
    idx = np.flatnonzero(msk)
    x = pts[idx].astype(np.float64)
    n = idx.size
    depth = tree_depth(n, cfg)

    axes, values, leaf, (bb_lo, bb_hi, count) = _ref_split_levels(x, depth)
    lap("splits")

    # The scipy tree over the points in slot order: the candidate supersets below are then
    # spatially local in memory.
    slot_pts = leaf[leaf >= 0]
    kd = cKDTree(x[slot_pts])
    spacing, lim = _ref_spacing_and_limit(x, kd, cfg)
    lap("index")

    margin0 = cfg.margin_factor * spacing / math.sqrt(3.0)
    lo_levels, hi_levels = _ref_cell_boxes(cfg, axes, values, bb_lo, bb_hi, count, depth, margin0)
    lo_all = np.concatenate(lo_levels).astype(dtype)
    hi_all = np.concatenate(hi_levels).astype(dtype)
    count_all = np.concatenate(count).astype(np.int32)
    valid_all = count_all > 0
    lap("boxes")

    # Candidate sets of the growing + rendering levels: the points nearest each box centre.
    kc = cfg.num_candidates
    first = 2 ** (depth - cfg.num_render_levels - 1) - 1
    last = 2**depth - 1  # exclusive: the leaves have no candidate sets
    center = 0.5 * (lo_all[first:last].astype(np.float64) + hi_all[first:last].astype(np.float64))
    out_index = np.append(idx[slot_pts], cap).astype(np.int32)
    cand, radius = _ref_candidate_sets(
        kd.data, kd, center, depth - cfg.num_render_levels - 1, depth, kc, out_index
    )
    # Validity at the rendering levels: the released code's "too spread out" rule.
    r0 = 2 ** (depth - cfg.num_render_levels) - 1
    sl = slice(r0, last)
    diag = np.linalg.norm(hi_all[sl].astype(np.float64) - lo_all[sl].astype(np.float64), axis=1)
    too_large = (radius[r0 - first :] > lim) | (diag > 2.0 * lim)
    valid_all[sl] &= ~too_large

    perm = np.where(leaf >= 0, idx[np.maximum(leaf, 0)], cap).astype(np.int32)
    if empty_sentinel:
        cand[count_all[first:last] == 0] = cap
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


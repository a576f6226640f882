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
    compared, so ties may pick either point)."""
    xyz = np.asarray(xyz, np.float64)
    alive = np.asarray(alive)
    cand = np.asarray(tree.candidates)
    lo = np.asarray(tree.lo, np.float64)
    hi = np.asarray(tree.hi, np.float64)
    first = tree.first_candidate_node
    pool = np.flatnonzero(alive)
    kc = cfg.num_candidates
    rows = np.linspace(0, cand.shape[0] - 1, min(max_nodes, cand.shape[0])).astype(int)
    for r in rows:
        g = first + r
        c = 0.5 * (lo[g] + hi[g])
        d_all = np.sort(np.linalg.norm(xyz[pool] - c, axis=1))[:kc]
        got = cand[r][cand[r] < xyz.shape[0]]
        assert len(set(got.tolist())) == got.size
        assert np.all(alive[got])
        d_got = np.sort(np.linalg.norm(xyz[got] - c, axis=1))
        np.testing.assert_allclose(d_got, d_all, rtol=1e-5, atol=1e-6 * (1 + np.abs(c).max()))

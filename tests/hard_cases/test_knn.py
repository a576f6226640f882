"""Stage 3, KNN (``knn_interpolate``, ``knn_integrate``, jitted): random clouds (degenerate,
1e-4 .. 1e4, deleted before and after the build), confidences near 0 and 1 (logits up to +-30),
samples on the hard rays of the traversal stage and samples exactly on points, against the float64
references of ``tests/geometry/reference.py`` on the same candidate sets.

Tolerances (``common.TOL``): the neighbour sets must be equal unless the reference's K-th and
(K+1)-th distances tie within ``1e3 eps`` relative (then the chosen distances must match); weights
within ``TOL["weight"]`` absolute (float32 2e-6, float64 1e-12); interpolated and integrated values
within ``TOL["interp"]`` (float32 2e-5, float64 1e-11) times the largest ``|value|``; integrated
values only on segments without such a tie (the integration ranks its own distances, and may take
the other point of a tie). Values and the
gradients with respect to positions, confidences, features and sample points are finite.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from ne_jax.geometry import build_tree, intersect, knn_interpolate
from ne_jax.geometry.kdtree import KNN_EPS_FACTOR
from ne_jax.geometry.knn import knn_integrate

from geometry.reference import interpolate_reference, knn_reference

from .common import CAPS, CFG, CLOUD_KINDS, DTYPE, EPS, HYP, TOL, assert_finite, make_cloud, make_rays, make_state
from .test_traversal import NUM_RAYS, hard_rays

B, S = 64, 4  # fixed segment batch and samples per segment: one compilation per function


def segments_and_samples(tree, xyz, alive, rng):
    """``(points [B, S, 3], node [B], use [B])``: samples of up to 48 real segments of hard rays and
    up to 16 segments whose samples sit exactly on (or a subnormal step off) an alive point."""
    o, d = hard_rays(tree, xyz, alive, rng)
    rays = make_rays(o, d, num=NUM_RAYS)
    seg = intersect(tree, rays, CFG, CAPS)
    r, m = np.nonzero(np.asarray(seg.valid))
    pick = rng.choice(len(r), min(48, len(r)), replace=False) if len(r) else np.zeros(0, int)
    r, m = r[pick], m[pick]
    lo, hi = np.asarray(seg.t_lo, np.float64)[r, m], np.asarray(seg.t_hi, np.float64)[r, m]
    t = lo[:, None] + (hi - lo)[:, None] * np.linspace(0, 1, S)
    pts = np.asarray(rays.origin, np.float64)[r, None] + t[..., None] * np.asarray(rays.direction, np.float64)[r, None]
    node = np.asarray(seg.node)[r, m]
    # on a point: the bottom rendering node holding its slot
    perm = np.asarray(tree.perm)
    slots = np.flatnonzero(perm < len(xyz))
    k = min(B - len(node), 16, len(slots))
    sl = rng.choice(slots, k, replace=False)
    on = np.repeat(np.asarray(xyz, np.float64)[perm[sl]][:, None], S, 1)
    on[:, 1] += np.finfo(DTYPE).tiny * 4  # a normal-number step, far below the eps of the weights
    pts = np.concatenate([pts, on]).astype(DTYPE)
    node = np.concatenate([node, 2 ** (tree.depth - 1) - 1 + sl // 2])
    use = np.ones(len(node), bool)
    pad = B - len(node)
    pts = np.concatenate([pts, np.zeros((pad, S, 3), DTYPE)])
    node = np.concatenate([node, np.full(pad, tree.first_candidate_node)]).astype(np.int32)
    use = np.concatenate([use, np.zeros(pad, bool)])
    return pts, node, use


def check(state, tree, pts, node, use, vals, nb, integrated=None, weight=None):
    xyz = np.asarray(state.xyz, np.float64)
    alive = np.asarray(state.alive)
    conf = np.asarray(state.conf_logit, np.float64)
    eps = KNN_EPS_FACTOR * float(tree.spacing)
    feat = np.asarray(state.feature, np.float64)
    ist = np.asarray(state.ist, np.float64)
    idx, w, ok = (np.asarray(a) for a in (nb.index, nb.weight, nb.valid))
    got_f, got_i = np.asarray(vals["feature"], np.float64), np.asarray(vals["ist"], np.float64)
    cand_all = np.asarray(tree.candidates)
    fscale, iscale = np.abs(feat).max(), np.abs(ist).max()
    checked = 0
    for b in np.flatnonzero(use):
        cand = cand_all[node[b] - tree.first_candidate_node]
        f_int = np.zeros(feat.shape[1])
        tied = False  # a sample of the segment with a tie at its K-th distance
        for s in range(S):
            q = np.asarray(pts[b, s], np.float64)
            ri, rw, gap = knn_reference(xyz, alive, conf, q, CFG.knn_k, eps, cand)
            got = dict(zip(idx[b, s][ok[b, s]].tolist(), w[b, s][ok[b, s]].tolist()))
            dk = np.linalg.norm(xyz[ri[-1]] - q) if ri.size else 0.0
            if gap <= 1e3 * EPS * (dk + eps):  # a tie at the K-th distance: either point is right
                tied = True
                gi = np.asarray(sorted(got), np.int64)
                np.testing.assert_allclose(np.sort(np.linalg.norm(xyz[gi] - q, axis=1)),
                                           np.sort(np.linalg.norm(xyz[ri] - q, axis=1)),
                                           rtol=1e3 * EPS, atol=1e3 * EPS * eps)
                ri, rw, _ = knn_reference(xyz, alive, conf, q, CFG.knn_k, eps, gi)
            assert sorted(got) == sorted(ri.tolist()), (b, s)
            np.testing.assert_allclose([got[j] for j in ri], rw, rtol=0, atol=TOL["weight"])
            assert np.all(w[b, s][~ok[b, s]] == 0)
            f_ref = interpolate_reference(ri, rw, feat)
            np.testing.assert_allclose(got_f[b, s], f_ref, rtol=0, atol=TOL["interp"] * fscale)
            np.testing.assert_allclose(got_i[b, s], interpolate_reference(ri, rw, ist), rtol=0,
                                       atol=TOL["interp"] * iscale)
            if weight is not None:
                f_int += float(weight[b, s]) * f_ref
            checked += 1
        # The integration ranks its own float32 distances: at a tie it may pick the other point (as a
        # program compiled at another optimisation level rounds them differently), so tied segments
        # are checked per sample above only.
        if integrated is not None and not tied:
            np.testing.assert_allclose(np.asarray(integrated["feature"], np.float64)[b], f_int, rtol=0,
                                       atol=TOL["interp"] * fscale)
    return checked


@HYP.__class__(HYP, max_examples=10)
@given(st.sampled_from(CLOUD_KINDS), st.integers(1, 256), st.integers(0, 2**16),
       st.sampled_from([1e-4, 1.0, 1e4]), st.sampled_from([0.0, 0.3]), st.booleans(), st.booleans())
def test_matches_reference(kind, n, seed, scale, deleted, extreme_conf, delete_after_build):
    rng = np.random.default_rng(seed)
    xyz, alive = make_cloud(kind, n, seed, scale=scale, deleted=deleted)
    tree = build_tree(xyz, alive, CFG)
    logits = rng.choice([-30.0, -15.0, 0.0, 15.0, 30.0], size=len(xyz)) if extreme_conf else None
    state = make_state(xyz, alive, seed=seed, conf_logit=logits)
    pts, node, use = segments_and_samples(tree, xyz, alive, rng)
    if delete_after_build and alive.sum() > 1:  # deleting marks dead; the tree keeps the old points
        dead = np.flatnonzero(alive)[rng.random(int(alive.sum())) < 0.3]
        state = state.delete(jnp.asarray(dead, jnp.int32))
    weight = rng.dirichlet(np.ones(S), size=B).astype(DTYPE)
    vals, nb = knn_interpolate(state, tree, jnp.asarray(pts), jnp.asarray(node), CFG)
    values = {"feature": state.feature, "ist": state.ist.reshape(-1, 9)}
    integ = knn_integrate(state, tree, jnp.asarray(pts), jnp.asarray(node), jnp.asarray(weight), values, CFG)
    assert vals["feature"].dtype == DTYPE and integ["feature"].dtype == DTYPE
    assert_finite((vals, nb, integ))
    assert check(state, tree, pts, node, use, vals, nb, integ, weight) == use.sum() * S >= S
    # never a dead neighbour with weight
    assert not np.any(np.asarray(nb.valid) & ~np.asarray(state.alive)[np.asarray(nb.index)])

    def loss(xyz, conf_logit, feature, points):
        st_ = state.replace(xyz=xyz, conf_logit=conf_logit, feature=feature)
        v = knn_integrate(st_, tree, points, jnp.asarray(node), jnp.asarray(weight), {"feature": feature}, CFG)
        return jnp.sum(v["feature"] ** 2)

    grads = jax.grad(loss, argnums=(0, 1, 2, 3))(state.xyz, state.conf_logit, state.feature, jnp.asarray(pts))
    assert_finite(grads, "grad ")
    dead = ~np.asarray(state.alive)
    for g in grads[:3]:  # dead points receive nothing
        assert np.all(np.asarray(g)[dead] == 0)


def test_exact_mode_at_extreme_scales():
    """Brute-force mode: the global K nearest alive points at scene sizes 1e-4 and 1e4."""
    for scale in (1e-4, 1e4):
        rng = np.random.default_rng(3)
        xyz, alive = make_cloud("clusters", 200, 3, scale=scale, deleted=0.2)
        tree = build_tree(xyz, alive, CFG)
        state = make_state(xyz, alive, seed=3)
        q = (np.asarray(xyz, np.float64)[alive][:32] + rng.normal(size=(32, 3)) * float(tree.spacing)).astype(DTYPE)
        vals, nb = knn_interpolate(state, tree, jnp.asarray(q), None, CFG, exact=True)
        assert_finite((vals, nb))
        eps = KNN_EPS_FACTOR * float(tree.spacing)
        for i in range(len(q)):
            ri, rw, gap = knn_reference(np.asarray(xyz, np.float64), alive, np.asarray(state.conf_logit, np.float64),
                                        q[i].astype(np.float64), CFG.knn_k, eps)
            got = np.asarray(nb.index)[i]
            if gap > 1e3 * EPS * scale:
                assert sorted(got.tolist()) == sorted(ri.tolist())
                np.testing.assert_allclose(np.asarray(vals["feature"], np.float64)[i],
                                           interpolate_reference(ri, rw, np.asarray(state.feature, np.float64)),
                                           atol=TOL["interp"] * float(np.abs(state.feature).max()))

"""knn_interpolate: candidate-set and exact modes against float64 references, the distance-0 and
extreme-confidence cases, K above the alive count, finite gradients, no recompilation.

Tolerances (float32 implementation vs float64 reference): weights within 2e-6 absolute (they lie in
[0, 1]); interpolated values within 1e-5 + 1e-5 * max|value| absolute. Neighbour sets must be equal
except where the reference's K-th and (K+1)-th distances tie within 1e-5 relative."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ne_jax.data.rays import Rays
from ne_jax.geometry import KDTreeConfig, PointState, build_tree, intersect, knn_interpolate, knn_neighbors, knn_weights
from ne_jax.geometry.kdtree import KNN_EPS_FACTOR

from tests.mini_presets import tiny_tree

from .clouds import CLOUDS, hard_rays, make_rays, padded, sphere
from .reference import interpolate_reference, knn_reference

CFG = tiny_tree(depth=10)


def state_for(xyz, alive, seed=0, feature_dim=4):
    rng = np.random.default_rng(seed)
    c = len(xyz)
    st_ = PointState.from_numpy(np.nan_to_num(xyz), capacity=c, feature_dim=feature_dim)
    ist = np.eye(3)[None] + 0.2 * rng.normal(size=(c, 3, 3))
    return st_.replace(
        alive=jnp.asarray(alive),
        feature=jnp.asarray(rng.normal(size=(c, feature_dim)).astype(np.float32)),
        conf_logit=jnp.asarray(rng.normal(scale=2.0, size=c).astype(np.float32)),
        normal=jnp.asarray(rng.normal(size=(c, 3)).astype(np.float32)),
        ist=jnp.asarray(ist.astype(np.float32)),
    )


def samples_from_rays(tree, xyz, alive, cfg, s=5, n_boxes=3, n_random=24):
    """Sample points of real rays: ``s`` evenly spaced points per segment (end points included)."""
    o, d = hard_rays(tree, xyz, alive, n_boxes=n_boxes, n_random=n_random)
    rays = make_rays(o, d)
    seg = intersect(tree, rays, cfg)
    u = jnp.linspace(0.0, 1.0, s)
    t = seg.t_lo[..., None] + (seg.t_hi - seg.t_lo)[..., None] * u  # [R, M, s]
    pts = rays.origin[:, None, None, :] + rays.direction[:, None, None, :] * t[..., None]
    return pts, seg


def check_against_reference(state, tree, pts, node, valid, cfg, exact):
    (vals, nb) = knn_interpolate(state, tree, pts, node, cfg, exact=exact)
    xyz = np.asarray(state.xyz, np.float64)
    eps = KNN_EPS_FACTOR * float(tree.spacing)
    P = np.asarray(pts).reshape(-1, 3)
    nodes = np.broadcast_to(np.asarray(node)[..., None], pts.shape[:-1]).reshape(-1)
    use = np.broadcast_to(np.asarray(valid)[..., None], pts.shape[:-1]).reshape(-1)
    idx = np.asarray(nb.index).reshape(len(P), -1)
    w = np.asarray(nb.weight).reshape(len(P), -1)
    ok = np.asarray(nb.valid).reshape(len(P), -1)
    feat = np.asarray(vals["feature"]).reshape(len(P), -1)
    ist = np.asarray(vals["ist"]).reshape(len(P), 3, 3)
    checked = 0
    for i in np.flatnonzero(use):
        cand = None if exact else np.asarray(tree.candidates)[nodes[i] - tree.first_candidate_node]
        ri, rw, gap = knn_reference(xyz, np.asarray(state.alive), np.asarray(state.conf_logit), P[i], cfg.knn_k, eps,
                                    cand)
        dk = np.linalg.norm(xyz[ri[-1]] - P[i]) if ri.size else 0.0
        got = dict(zip(idx[i][ok[i]].tolist(), w[i][ok[i]].tolist()))
        if gap <= 1e-5 * (1 + dk):
            # A tie at the K-th distance (regular grids): either point is right. Check the chosen
            # distances, then score the chosen set with the reference weights.
            gi = np.asarray(sorted(got), np.int64)
            np.testing.assert_allclose(
                np.sort(np.linalg.norm(xyz[gi] - P[i], axis=1)), np.sort(np.linalg.norm(xyz[ri] - P[i], axis=1)),
                atol=1e-5 * (1 + dk),
            )
            ri, rw, _ = knn_reference(xyz, np.asarray(state.alive), np.asarray(state.conf_logit), P[i], cfg.knn_k, eps,
                                      gi)
        assert sorted(got) == sorted(ri.tolist()), i
        np.testing.assert_allclose([got[j] for j in ri], rw, atol=2e-6)
        assert np.all(w[i][~ok[i]] == 0)
        f_ref = interpolate_reference(ri, rw, np.asarray(state.feature))
        np.testing.assert_allclose(feat[i], f_ref, atol=1e-5 + 1e-5 * np.abs(np.asarray(state.feature)).max())
        i_ref = interpolate_reference(ri, rw, np.asarray(state.ist))
        np.testing.assert_allclose(ist[i], i_ref, atol=1e-5 + 1e-5 * np.abs(np.asarray(state.ist)).max())
        checked += 1
    assert checked == use.sum() and checked > 0
    return nb


@pytest.mark.parametrize("exact", [False, True])
@pytest.mark.parametrize("name", ["sphere_700", "coplanar", "collinear", "mostly_deleted", "two_points", "identical"])
def test_matches_reference(name, exact):
    xyz, alive = padded(name)
    tree = build_tree(xyz, alive, CFG)
    state = state_for(xyz, alive)
    pts, seg = samples_from_rays(tree, xyz, alive, CFG)
    nb = check_against_reference(state, tree, pts, seg.node, seg.valid, CFG, exact)
    n_alive = int(alive.sum())
    m = np.asarray(seg.valid)
    counts = np.asarray(nb.valid).sum(-1)[m]
    assert np.all(counts == min(CFG.knn_k, n_alive))  # K > alive count: the rest has weight 0
    np.testing.assert_allclose(np.asarray(nb.weight).sum(-1)[m], 1.0, rtol=1e-5)


def test_default_config_recall_and_reference():
    cfg = KDTreeConfig(depth=12)
    xyz = sphere(3000, seed=9)
    alive = np.ones(len(xyz), bool)
    tree = build_tree(xyz, alive, cfg)
    state = state_for(xyz, alive, feature_dim=32)
    pts, seg = samples_from_rays(tree, xyz, alive, cfg, s=4, n_boxes=1, n_random=16)
    check_against_reference(state, tree, pts, seg.node, seg.valid, cfg, exact=False)
    nb = knn_neighbors(state, tree, pts, seg.node, cfg)
    ex = knn_neighbors(state, tree, pts, None, cfg, exact=True)
    m = np.asarray(seg.valid)
    a = np.asarray(nb.index)[m].reshape(-1, cfg.knn_k)
    b = np.asarray(ex.index)[m].reshape(-1, cfg.knn_k)
    recall = np.mean([len(set(x) & set(y)) / cfg.knn_k for x, y in zip(a, b)])
    assert recall > 0.99, recall


def test_per_segment_and_per_sample_nodes_agree():
    xyz, alive = padded("sphere_700")
    tree = build_tree(xyz, alive, CFG)
    state = state_for(xyz, alive)
    pts, seg = samples_from_rays(tree, xyz, alive, CFG)
    a, _ = knn_interpolate(state, tree, pts, seg.node, CFG)
    b, _ = knn_interpolate(state, tree, pts, jnp.broadcast_to(seg.node[..., None], pts.shape[:-1]), CFG)
    for k in a:  # two summation orders (shared per-segment gather vs per-sample gather)
        np.testing.assert_allclose(np.asarray(a[k]), np.asarray(b[k]), rtol=1e-6, atol=1e-6)


def _one_node_setup(name="sphere_700"):
    xyz, alive = padded(name)
    tree = build_tree(xyz, alive, CFG)
    state = state_for(xyz, alive)
    g = 2 ** (tree.depth - 1) - 1 + int(np.flatnonzero(np.asarray(tree.valid)[2 ** (tree.depth - 1) - 1 :])[0])
    return xyz, alive, tree, state, g


def test_sample_exactly_on_a_point_and_extreme_confidences():
    xyz, alive, tree, state, g = _one_node_setup()
    cand = np.asarray(tree.candidates)[g - tree.first_candidate_node]
    p0, p1 = int(cand[0]), int(cand[1])
    logits = np.asarray(state.conf_logit).copy()
    logits[cand[2]] = 40.0  # confidence 1 - 4e-18
    logits[cand[3]] = -40.0  # confidence 4e-18
    state = state.replace(conf_logit=jnp.asarray(logits))
    pts = jnp.asarray(np.stack([xyz[p0], xyz[p1], 0.5 * (xyz[p0] + xyz[p1])]))
    node = jnp.full((3,), g, jnp.int32)

    def loss(xyz_, feat, logit, q):
        s = state.replace(xyz=xyz_, feature=feat, conf_logit=logit)
        vals, nb = knn_interpolate(s, tree, q, node, CFG)
        return jnp.sum(vals["feature"] ** 2) + jnp.sum(vals["ist"]) + jnp.sum(nb.weight * nb.dist)

    vals, nb = knn_interpolate(state, tree, pts, node, CFG)
    w = np.asarray(nb.weight)
    assert np.all(np.isfinite(w)) and np.all(np.isfinite(np.asarray(vals["feature"])))
    # on a point: that point gets almost all the weight (distance eps vs. >= spacing)
    assert np.asarray(nb.index)[0][np.argmax(w[0])] == p0 and w[0].max() > 0.99
    grads = jax.grad(loss, argnums=(0, 1, 2, 3))(state.xyz, state.feature, state.conf_logit, pts)
    for gr in grads:
        assert np.all(np.isfinite(np.asarray(gr)))
    assert float(jnp.abs(grads[0]).sum()) > 0 and float(jnp.abs(grads[2]).sum()) > 0


def test_points_deleted_after_build_are_ignored():
    xyz, alive, tree, state, g = _one_node_setup()
    cand = np.asarray(tree.candidates)[g - tree.first_candidate_node]
    q = jnp.asarray(xyz[cand[0]][None] + 0.01)
    node = jnp.asarray([g], jnp.int32)
    part = state.delete(jnp.asarray(cand[:3]))
    _, nb = knn_interpolate(part, tree, q, node, CFG)
    assert not set(np.asarray(nb.index)[0][np.asarray(nb.valid)[0]].tolist()) & set(cand[:3].tolist())
    none = state.delete(jnp.asarray(cand))  # every candidate dead: zeros, finite gradients
    vals, nb = knn_interpolate(none, tree, q, node, CFG)
    assert not np.asarray(nb.valid).any() and np.all(np.asarray(vals["feature"]) == 0)

    def feature_sum(f):
        return jnp.sum(knn_interpolate(none.replace(feature=f), tree, q, node, CFG)[0]["feature"])

    g_ = jax.grad(feature_sum)(none.feature)
    assert np.all(np.isfinite(np.asarray(g_)))


def test_identity_ist_and_custom_values():
    xyz, alive = padded("random_300")
    tree = build_tree(xyz, alive, CFG)
    state = state_for(xyz, alive)
    state = state.replace(ist=jnp.broadcast_to(jnp.eye(3), state.ist.shape))
    pts, seg = samples_from_rays(tree, xyz, alive, CFG)
    vals, nb = knn_interpolate(state, tree, pts, seg.node, CFG)
    m = np.asarray(seg.valid)
    np.testing.assert_allclose(np.asarray(vals["ist"])[m], np.broadcast_to(np.eye(3), np.asarray(vals["ist"])[m].shape),
                               atol=1e-6)
    ones, _ = knn_interpolate(state, tree, pts, seg.node, CFG, values=jnp.ones((state.capacity, 2)))
    np.testing.assert_allclose(np.asarray(ones)[m], 1.0, rtol=1e-6)
    with pytest.raises(ValueError, match=r"values: expected leaves of shape \[C=1024, \.\.\.\], found shape \(5, 2\)"):
        knn_interpolate(state, tree, pts, seg.node, CFG, values=jnp.ones((5, 2)))
    with pytest.raises(ValueError, match=r"segment_node: expected shape"):
        knn_interpolate(state, tree, pts, seg.node[:, :3], CFG)


def test_gradients_finite_through_intersect_on_every_cloud():
    def loss(origin, xyz_, feat, logit, tree, state, d):
        r = d.shape[0]
        rays = Rays(origin=origin, direction=d, near=jnp.zeros(r), far=jnp.full(r, 1e3))
        seg = intersect(tree, rays, CFG)
        t = 0.5 * (seg.t_lo + seg.t_hi)
        pts = rays.origin[:, None, None, :] + rays.direction[:, None, None, :] * t[..., None, None]
        s = state.replace(xyz=xyz_, feature=feat, conf_logit=logit)
        vals, _ = knn_interpolate(s, tree, pts, seg.node, CFG)
        f = jnp.where(seg.valid[..., None, None], vals["feature"], 0.0)
        return jnp.sum(jnp.sin(f)) + jnp.sum(jnp.where(seg.valid[..., None, None, None], vals["ist"], 0.0))

    grad = jax.jit(jax.grad(loss, argnums=(0, 1, 2, 3)))
    for name in sorted(CLOUDS):
        xyz, alive = padded(name)
        tree = build_tree(xyz, alive, CFG)
        state = state_for(xyz, alive)
        o, d = hard_rays(tree, xyz, alive, n_boxes=2, n_random=8)
        gs = grad(jnp.asarray(o), state.xyz, state.feature, state.conf_logit, tree, state, jnp.asarray(d))
        for gr in gs:
            assert np.all(np.isfinite(np.asarray(gr))), name
        assert float(jnp.abs(gs[2]).sum()) > 0, name


def test_no_recompilation():
    xyz, alive = padded("sphere_700")
    tree = build_tree(xyz, alive, CFG)
    state = state_for(xyz, alive)
    pts, seg = samples_from_rays(tree, xyz, alive, CFG)
    knn_neighbors(state, tree, pts, seg.node, CFG).weight.block_until_ready()
    size = knn_neighbors._cache_size()
    xyz2, alive2 = padded("random_300")
    tree2 = build_tree(xyz2, alive2, CFG)
    state2 = state_for(xyz2, alive2, seed=3)
    for s, t, p in ((state2, tree2, pts), (state, tree, pts + 0.01), (state.delete(jnp.arange(10)), tree2, pts)):
        knn_neighbors(s, t, p, seg.node, CFG).weight.block_until_ready()
    assert knn_neighbors._cache_size() == size


@settings(max_examples=40, deadline=None)
@given(
    st.lists(st.floats(-60, 60), min_size=6, max_size=6),
    st.lists(st.sampled_from([0.0, 1e-30, 1e-7, 0.5, 3.0, 1e20]), min_size=6, max_size=6),
    st.lists(st.booleans(), min_size=6, max_size=6),
)
def test_knn_weights_properties(logits, dists, valid):
    w = np.asarray(knn_weights(jnp.asarray(logits, jnp.float32), jnp.asarray(dists, jnp.float32), jnp.asarray(valid),
                               1e-6))
    v = np.asarray(valid)
    assert np.all(np.isfinite(w)) and np.all(w >= 0) and np.all(w[~v] == 0)
    if v.any():
        assert abs(w.sum() - 1.0) < 1e-5
    g = jax.grad(lambda lg, d: jnp.sum(knn_weights(lg, d, jnp.asarray(valid), 1e-6) * jnp.arange(6.0)), argnums=(0, 1))(
        jnp.asarray(logits, jnp.float32), jnp.asarray(dists, jnp.float32)
    )
    assert all(np.all(np.isfinite(np.asarray(x))) for x in g)

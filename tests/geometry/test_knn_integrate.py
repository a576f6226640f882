"""knn_integrate == integrating knn_interpolate (linearity), in value and gradient."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ne_jax.geometry.kdtree import build_tree
from ne_jax.geometry.knn import knn_integrate, knn_interpolate
from ne_jax.geometry.points import PointState

from tests.mini_presets import tiny_tree

from .clouds import CLOUDS


def _setup(name, seed=0, b=40, s=6, candidate_min=16):
    xyz, alive = CLOUDS[name]
    cfg = tiny_tree(candidate_min=candidate_min)
    rng = np.random.default_rng(seed)
    state = PointState.from_numpy(np.where(alive[:, None], xyz, 0.0).astype(np.float32), feature_dim=5)
    state = state.replace(alive=jnp.asarray(alive),
                          feature=jnp.asarray(rng.normal(size=state.feature.shape), jnp.float32),
                          conf_logit=jnp.asarray(rng.normal(size=state.conf_logit.shape), jnp.float32),
                          normal=jnp.asarray(rng.normal(size=state.normal.shape), jnp.float32))
    tree = build_tree(np.asarray(state.xyz), alive, cfg)
    first = tree.first_candidate_node
    node = jnp.asarray(rng.integers(first, first + tree.candidates.shape[0], b), jnp.int32)
    center = 0.5 * (tree.lo[node] + tree.hi[node])
    pts = center[:, None, :] + jnp.asarray(rng.normal(scale=0.05, size=(b, s, 3)), jnp.float32)
    pts = pts.at[0, 0].set(state.xyz[int(np.flatnonzero(alive)[0])])  # a sample exactly on a point
    w = jnp.asarray(rng.random((b, s)), jnp.float32)
    w = w / w.sum(1, keepdims=True)
    return state, tree, cfg, pts, node, w


# 16 candidates: the K nearest found by ranking; 48: by lax.top_k (knn.RANK_MAX_CANDIDATES)
@pytest.mark.parametrize("candidate_min", [16, 48])
@pytest.mark.parametrize("name", ["sphere_700", "mostly_deleted", "one_point", "collinear"])
def test_equals_integrated_interpolation(name, candidate_min):
    state, tree, cfg, pts, node, w = _setup(name, candidate_min=candidate_min)
    values = {"feature": state.feature, "normal": state.normal, "ist": state.ist}
    fused = knn_integrate(state, tree, pts, node, w, values, cfg)
    interp, _ = knn_interpolate(state, tree, pts, node, cfg, False, values)
    for key in values:
        axis = 1
        ref = jnp.sum(jnp.expand_dims(w, tuple(range(2, interp[key].ndim))) * interp[key], axis=axis)
        np.testing.assert_allclose(np.asarray(fused[key]), np.asarray(ref), rtol=1e-5, atol=1e-6, err_msg=key)
    exact = knn_integrate(state, tree, pts, node, w, values, cfg, exact=True)
    assert all(np.isfinite(np.asarray(v)).all() for v in exact.values())


def test_ties_choose_the_same_neighbors_as_top_k():
    """Samples at the centre of a cubic lattice cell (exact binary fractions): its eight corners at
    one distance, and K = 4 of them chosen. Ranking must break ties as ``lax.top_k`` does (the lower
    candidate slot)."""
    g = np.arange(6, dtype=np.float32) * 0.125
    xyz = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    cfg = tiny_tree(knn_k=4)
    state = PointState.from_numpy(xyz, feature_dim=3)
    rng = np.random.default_rng(0)
    state = state.replace(feature=jnp.asarray(rng.normal(size=state.feature.shape), jnp.float32))
    tree = build_tree(xyz, np.ones(len(xyz), bool), cfg)
    first = tree.first_candidate_node
    node = jnp.arange(first, first + tree.candidates.shape[0], dtype=jnp.int32)
    cell = np.floor(0.5 * (np.asarray(tree.lo[node]) + np.asarray(tree.hi[node])) / 0.125).clip(0, 4)
    pts = jnp.asarray((cell + 0.5) * 0.125, jnp.float32)[:, None, :]  # one sample per segment
    d = np.sort(np.linalg.norm(xyz[np.asarray(tree.candidates)[node - first]] - np.asarray(pts), axis=-1), axis=-1)
    assert (d[:, 3] == d[:, 4]).mean() > 0.5  # the fourth and fifth nearest tie: the choice matters
    w = jnp.ones(pts.shape[:2], jnp.float32)
    fused = knn_integrate(state, tree, pts, node, w, {"f": state.feature}, cfg)["f"]
    interp, _ = knn_interpolate(state, tree, pts, node, cfg, False, {"f": state.feature})
    np.testing.assert_allclose(np.asarray(fused), np.asarray(interp["f"][:, 0]), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("candidate_min", [16, 48])
def test_gradients_match_and_are_finite(candidate_min):
    state, tree, cfg, pts, node, w = _setup("sphere_700", candidate_min=candidate_min)

    def fused(xyz, feature, conf_logit, pts):
        st = state.replace(xyz=xyz, feature=feature, conf_logit=conf_logit)
        return jnp.sum(knn_integrate(st, tree, pts, node, w, {"f": st.feature}, cfg)["f"] ** 2)

    def reference(xyz, feature, conf_logit, pts):
        st = state.replace(xyz=xyz, feature=feature, conf_logit=conf_logit)
        interp, _ = knn_interpolate(st, tree, pts, node, cfg, False, {"f": st.feature})
        return jnp.sum(jnp.sum(w[..., None] * interp["f"], axis=1) ** 2)

    args = (state.xyz, state.feature, state.conf_logit, pts)
    g1 = jax.grad(fused, argnums=(0, 1, 2, 3))(*args)
    g2 = jax.grad(reference, argnums=(0, 1, 2, 3))(*args)
    for a, b in zip(g1, g2):
        assert np.isfinite(np.asarray(a)).all()
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-5)


def test_shape_errors_name_the_arguments():
    state, tree, cfg, pts, node, w = _setup("sphere_700")
    with pytest.raises(ValueError, match="sample_weight"):
        knn_integrate(state, tree, pts, node, w[:, :3], {"f": state.feature}, cfg)

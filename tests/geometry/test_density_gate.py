"""The density gate (``KDTreeConfig.density_falloff``): ``sum_k w_k c_k phi(d_k)`` against a float64
numpy loop, fused quadrature == integrated interpolation, bounds, the hard cases' gradients, and the
renderer's density multiplied by it (absent without a falloff)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ne_jax.geometry.kdtree import KNN_EPS_FACTOR
from ne_jax.geometry.knn import GATE, knn_integrate, knn_interpolate
from ne_jax.render.renderer import PointScene
from ne_jax.render.shading import init_color_model
from ne_jax.render.stage import shade_own, shade_segments

from tests.mini_presets import tiny_render

from .test_knn_integrate import _setup

FALLOFF = 2.0


def _gated(name, candidate_min=16, **kw):
    state, tree, cfg, pts, node, w = _setup(name, candidate_min=candidate_min, **kw)
    return state, tree, cfg.replace(density_falloff=FALLOFF), pts, node, w


def _reference(state, tree, cfg, pts, nb):
    """The gate and the interpolated features of every sample, for the neighbours ``nb``, in float64
    numpy, one neighbour at a time: ``(gate [B, S], feature [B, S, F])``."""
    idx, valid = np.asarray(nb.index), np.asarray(nb.valid)
    xyz = np.asarray(state.xyz, np.float64)
    conf = 1.0 / (1.0 + np.exp(-np.asarray(state.conf_logit, np.float64)))
    feature = np.asarray(state.feature, np.float64)
    spacing = float(tree.spacing)
    eps, scale = KNN_EPS_FACTOR * spacing, FALLOFF * spacing
    q = np.asarray(pts, np.float64)
    gate, values = np.zeros(idx.shape[:-1]), np.zeros(idx.shape[:-1] + feature.shape[1:])
    for b, s in np.ndindex(*idx.shape[:-1]):
        logits, terms, rows = [], [], []
        for j, ok in zip(idx[b, s], valid[b, s]):
            if not ok:
                continue
            d = np.linalg.norm(q[b, s] - xyz[j])
            logits.append(np.log(conf[j]) - np.log(d + eps))
            terms.append(conf[j] * (1.0 - np.exp(-scale / (d + eps))))
            rows.append(feature[j])
        if logits:
            w = np.exp(np.array(logits) - max(logits))
            w /= w.sum()
            gate[b, s], values[b, s] = np.dot(w, terms), w @ np.array(rows)
    return gate, values


@pytest.mark.parametrize("candidate_min", [16, 48])
@pytest.mark.parametrize("name", ["sphere_700", "mostly_deleted", "one_point", "collinear"])
def test_gate_matches_a_float64_loop_and_the_fused_quadrature(name, candidate_min):
    """The gate of the interpolation and of the fused quadrature against the float64 loop; the
    features of both are the ungated weighted means of the loop (the gate enters the density only).
    The loop reads the neighbours the interpolation returns (the search itself is checked against
    brute force in ``test_knn_integrate.py``)."""
    state, tree, cfg, pts, node, w = _gated(name, candidate_min)
    values = {"feature": state.feature}
    interp, nb = knn_interpolate(state, tree, pts, node, cfg, False, values)
    ref, ref_feature = _reference(state, tree, cfg, pts, nb)
    np.testing.assert_allclose(np.asarray(interp[GATE][..., 0]), ref, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np.asarray(interp["feature"]), ref_feature, rtol=1e-5, atol=1e-6)
    fused = knn_integrate(state, tree, pts, node, w, values, cfg)
    np.testing.assert_allclose(np.asarray(fused[GATE][:, 0]), np.sum(np.asarray(w) * ref, axis=1),
                               rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(np.asarray(fused["feature"]),  # the features are not gated
                               np.sum(np.asarray(w)[..., None] * ref_feature, axis=1), rtol=1e-5, atol=1e-6)
    if candidate_min == 16:  # the exact search ignores the candidate sets: one size checks it
        exact = knn_integrate(state, tree, pts, node, w, values, cfg, exact=True)
        assert np.isfinite(np.asarray(exact[GATE])).all()


def test_gate_bounds_a_point_and_far_away():
    """On a point the gate is (nearly) that point's confidence; it never leaves [0, 1]; far from
    every point it falls off like ``falloff * spacing / d``."""
    state, tree, cfg, pts, node, w = _gated("sphere_700", seed=1)
    state = state.replace(conf_logit=jnp.full_like(state.conf_logit, 30.0))  # confidence 1
    interp, _ = knn_interpolate(state, tree, pts, node, cfg, False, {"f": state.feature})
    g = np.asarray(interp[GATE][..., 0])
    assert np.all((g >= 0) & (g <= 1))
    on_point = knn_interpolate(state, tree, pts[:1, :1], None, cfg, True, {"f": state.feature})[0][GATE]
    assert float(on_point[0, 0, 0]) > 0.999  # pts[0, 0] sits on a point (its node's set may miss it)
    spacing = float(tree.spacing)
    far = pts.at[:, :, 0].add(1e3 * spacing)
    gf = np.asarray(knn_interpolate(state, tree, far, node, cfg, False, {"f": state.feature})[0][GATE])
    assert np.all(gf < 2.0 * FALLOFF / 1e3 * 1.01)


@pytest.mark.parametrize("name", ["sphere_700", "mostly_deleted", "one_point"])
def test_gate_gradients_are_finite_at_the_hard_cases(name):
    """Extreme confidences, a sample exactly on a point, deleted points: finite gradients of the
    gate in positions, confidences and sample positions, through both lookups."""
    state, tree, cfg, pts, node, w = _gated(name)
    logits = state.conf_logit.at[::2].set(40.0).at[1::2].set(-40.0)

    def total(xyz, conf_logit, pts):
        st = state.replace(xyz=xyz, conf_logit=conf_logit)
        fused = knn_integrate(st, tree, pts, node, w, {"f": st.feature}, cfg)[GATE]
        interp = knn_interpolate(st, tree, pts, node, cfg, False, {"f": st.feature})[0][GATE]
        return jnp.sum(fused) + jnp.sum(interp)

    grads = jax.grad(total, argnums=(0, 1, 2))(state.xyz, logits, pts)
    assert all(np.isfinite(np.asarray(g)).all() for g in grads)


def test_density_is_multiplied_by_the_gate_and_absent_without_a_falloff():
    state, tree, kcfg, pts, node, w = _gated("sphere_700")
    plain = tiny_render(kdtree=kcfg.replace(density_falloff=None))
    plain = plain.replace(shading=dataclasses.replace(plain.shading, feature_dim=state.feature.shape[-1]))
    gated = plain.replace(kdtree=kcfg)
    params = init_color_model(plain.shading, jax.random.PRNGKey(0))
    scene = PointScene(points=state, tree=tree)
    view = jnp.broadcast_to(jnp.asarray([0.0, 0.0, 1.0]), (pts.shape[0], 3))
    a = shade_segments(plain, params, scene, pts, node, w, view)
    b = shade_segments(gated, params, scene, pts, node, w, view)
    assert GATE not in a.values
    np.testing.assert_allclose(np.asarray(b.sigma), np.asarray(a.sigma * b.values[GATE][:, 0]), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(b.rgb), np.asarray(a.rgb), rtol=1e-6)
    own_view = jnp.broadcast_to(jnp.asarray([0.0, 0.0, 1.0]), (state.capacity, 3))
    o1, o2 = shade_own(plain, params, state, own_view), shade_own(gated, params, state, own_view)
    np.testing.assert_allclose(np.asarray(o2.sigma), np.asarray(o1.sigma * state.confidence), rtol=1e-6)


def test_falloff_must_be_positive():
    _, _, cfg, *_ = _setup("sphere_700")
    with pytest.raises(ValueError, match="density_falloff"):
        cfg.replace(density_falloff=0.0)


@pytest.mark.parametrize("falloff", [None, FALLOFF])
def test_only_the_gate_gives_a_lone_point_s_confidence_a_rendering_gradient(falloff):
    """One point, rays through its voxel: without a gate its weight is 1 at any confidence, so the
    render's gradient in its confidence is exactly 0; with one it is not (and every gradient is
    finite)."""
    from ne_jax.geometry.points import PointState
    from ne_jax.render.renderer import render_rays
    from ne_jax.render.shading import Effects

    from .clouds import CLOUDS, make_rays

    xyz, alive = CLOUDS["one_point"]
    cfg = tiny_render(kdtree=tiny_render().kdtree.replace(density_falloff=falloff))
    cfg = cfg.replace(shading=dataclasses.replace(cfg.shading, effects=Effects(specular=False, point_normals=False)))
    points = PointState.from_numpy(xyz, feature_dim=cfg.shading.feature_dim)
    scene = PointScene.build(points, cfg)
    offsets = np.array([[0.0, 0.0], [0.0005, -0.0003], [-0.0003, 0.0004]], np.float32)
    origin = np.concatenate([xyz[:, :2] + offsets, np.full((3, 1), -2.0, np.float32)], 1)
    rays = make_rays(origin, np.tile(np.float32([[0.0, 0.0, 1.0]]), (3, 1)))
    params = init_color_model(cfg.shading, jax.random.PRNGKey(1))

    def opacity(conf_logit, xyz):
        sc = scene.replace(points=scene.points.replace(conf_logit=conf_logit, xyz=xyz))
        out = render_rays(cfg, params, sc, rays, jnp.ones(3))
        return jnp.sum(out.opacity), out

    (total, out), (g_conf, g_xyz) = jax.jit(jax.value_and_grad(opacity, argnums=(0, 1), has_aux=True))(
        scene.points.conf_logit, scene.points.xyz)
    assert np.asarray(out.num_segments).sum() > 0 and float(total) > 0  # rays through the point's voxel
    assert np.isfinite(np.asarray(g_conf)).all() and np.isfinite(np.asarray(g_xyz)).all()
    if falloff is None:
        assert float(jnp.abs(g_conf).max()) == 0.0
    else:
        assert float(g_conf[0]) > 0  # more confidence, more density, more opacity

"""The tree-free rendering path end to end: per-level sampling -> (stand-in) per-sample features,
normals and ISTs -> integration -> shading -> compositing. Image-loss gradients w.r.t. MLP params,
point features and normals are finite, also with the hard segments, and nothing recompiles."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ne_jax.render import (
    Effects,
    QuadratureConfig,
    ShadingConfig,
    background_color,
    composite,
    init_color_model,
    integrate,
    level_samples,
    shade,
)

R, M, P, F = 4, 6, 16, 32


def _scene(seed=0):
    """Rays along +z through a blob of P 'points'; segments of mixed levels with the hard cases:
    a zero-length segment, an invalid slot with garbage, a ray with no segments, huge density."""
    rng = np.random.default_rng(seed)
    t_lo = np.sort(rng.uniform(0.5, 3.0, size=(R, M)), axis=1)
    t_hi = t_lo + rng.uniform(0.0, 0.4, size=(R, M))
    t_hi[0, 1] = t_lo[0, 1]  # zero length
    valid = np.ones((R, M), bool)
    valid[1, 4] = False
    valid[2] = False  # pure background ray
    level = rng.integers(0, 5, size=(R, M))
    origin = np.tile([[0.0, 0.0, -1.0]], (R, 1)) + rng.normal(scale=0.1, size=(R, 3))
    direction = np.tile([[0.0, 0.0, 1.0]], (R, 1)) + rng.normal(scale=0.1, size=(R, 3))
    direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
    pts = rng.normal(scale=0.5, size=(P, 3)) + [0, 0, 1.0]
    feats = rng.normal(size=(P, F))
    normals = rng.normal(size=(P, 3))
    normals[0] = 0.0  # a degenerate normal
    def f32(x):
        return jnp.asarray(x, jnp.float32)
    return dict(t_lo=f32(t_lo), t_hi=f32(t_hi), valid=jnp.asarray(valid), level=jnp.asarray(level),
                origin=f32(origin), direction=f32(direction), pts=f32(pts)), f32(feats), f32(normals)


def render(qcfg, scfg, params, scene, feats, normals, key=None):
    """A stand-in for KNN interpolation (softmax of -squared distance over all points)."""
    t, w = level_samples(qcfg, scene["t_lo"], scene["t_hi"], scene["level"], key=key)
    x = scene["origin"][:, None, None, :] + t[..., None] * scene["direction"][:, None, None, :]
    d2 = jnp.sum((x[..., None, :] - scene["pts"]) ** 2, axis=-1)
    k = jax.nn.softmax(-d2 / 0.1, axis=-1)  # [R, M, S, P]
    f_mean = integrate(k @ feats, w)
    n_mean = integrate(k @ normals, w)
    ist = jnp.broadcast_to(jnp.eye(3, dtype=feats.dtype), (*k.shape[:-1], 3, 3))
    ist_mean = integrate(ist, w, axis=-3)
    view = jnp.broadcast_to(scene["direction"][:, None, :], n_mean.shape)
    out = shade(scfg, params, f_mean, n_mean, view, ist_mean)
    length = scene["t_hi"] - scene["t_lo"]
    bg = background_color(scfg, params, scene["origin"], scene["direction"], jnp.asarray([1.0, 1.0, 1.0]))
    # huge density in one slot: transmittance underflows behind it
    sigma = out.sigma.at[3, 2].multiply(1e30)
    return composite(sigma, out.rgb, length, scene["valid"], 0.5 * (scene["t_lo"] + scene["t_hi"]), bg,
                     normals=out.pred_normal)


@pytest.mark.parametrize("rule,fx", [
    ("hermite", dict(ist=True)),
    ("stochastic", dict(ist=True, background_model="sphere", point_normals=False)),
    ("spline", dict(specular=False, color_head="traditional")),
])
def test_image_loss_gradients_finite(rule, fx):
    qcfg = QuadratureConfig(rule=rule)
    scfg = ShadingConfig(effects=Effects(**fx))
    params = init_color_model(scfg, jax.random.key(1))
    scene, feats, normals = _scene()
    key = jax.random.key(2) if rule == "stochastic" else None
    target = jnp.full((R, 3), 0.5)

    def loss_and_image(params, feats, normals):
        img = render(qcfg, scfg, params, scene, feats, normals, key)
        return jnp.mean((img.rgb - target) ** 2) + 0.01 * jnp.mean(img.normal ** 2), img

    (value, img), grads = jax.jit(jax.value_and_grad(loss_and_image, argnums=(0, 1, 2), has_aux=True))(
        params, feats, normals)
    assert np.isfinite(float(value))
    for leaf in jax.tree_util.tree_leaves(grads):
        assert np.all(np.isfinite(np.asarray(leaf)))
    assert np.any(np.asarray(grads[1]) != 0)  # features do reach the image
    if fx.get("background_model", "constant") == "constant":
        np.testing.assert_array_equal(np.asarray(img.rgb)[2], [1.0, 1.0, 1.0])  # no segments
    assert float(img.opacity[2]) == 0.0
    w = np.asarray(img.weights)
    assert w[0, 1] == 0.0 and w[1, 4] == 0.0 and np.all(w[3, 3:] == 0.0)


def test_whole_path_compiles_once():
    qcfg, scfg = QuadratureConfig(), ShadingConfig(effects=Effects(ist=True))
    params = init_color_model(scfg, jax.random.key(0))
    traces = []

    @jax.jit
    def run(params, scene, feats, normals):
        traces.append(1)
        return render(qcfg, scfg, params, scene, feats, normals).rgb

    for seed in range(3):
        scene, feats, normals = _scene(seed)
        run(params, scene, feats, normals).block_until_ready()
    assert len(traces) == 1 and run._cache_size() == 1


def test_float64_path():
    qcfg, scfg = QuadratureConfig(rule="spline"), ShadingConfig(effects=Effects(ist=True))
    with jax.enable_x64(True):
        params = init_color_model(scfg, jax.random.key(0))
        scene, feats, normals = _scene()
        scene = {k: (v.astype(jnp.float64) if v.dtype == jnp.float32 else v) for k, v in scene.items()}
        img = jax.jit(lambda p, s, f, n: render(qcfg, scfg, p, s, f, n))(
            params, scene, feats.astype(jnp.float64), normals.astype(jnp.float64))
        assert img.rgb.dtype == jnp.float64 and np.all(np.isfinite(np.asarray(img.rgb)))

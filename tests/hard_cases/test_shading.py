"""Stage 5, shading (``integrated_dir_enc``, ``shade``, under ``jit``): the IDE against scipy's
float64 spherical harmonics at the poles, on the axes, one ulp from the poles and at random, with
roughness from 0 to 1e4; the colour model with normals and view directions of magnitude 1e-25 ..
1e25 (float32; 1e-150 .. 1e150 in float64), zero normals / view directions, singular and huge IST,
features from 0 to 1e10.

Tolerances (``common.TOL``): IDE columns within ``TOL["ide"]`` times the column's attenuation
(float32 2e-5, float64 1e-11). ``shade`` has no separate float64 reference here (it is a stack of
flax layers; the end-to-end stage compares float32 and float64 renders); instead its exact
invariance is checked: scaling the normal and the view direction by any positive factor changes
the colour by at most ``TOL["shade_scale"]`` (float32 2e-5, float64 1e-12). Outputs in range,
values and gradients finite everywhere.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from ne_jax.render.ide import ide_orders, integrated_dir_enc
from ne_jax.render.shading import RGB_PADDING, Effects, ShadingConfig, init_color_model, shade

from render.test_ide import _scipy_ide

from .common import DTYPE, EPS, HYP, TOL, X64, assert_finite

N = 32
_ide = jax.jit(integrated_dir_enc)


def _hard_directions(rng):
    one_off = 1.0 - EPS  # z one ulp inside the pole
    side = np.sqrt(1.0 - one_off**2)
    special = [[0, 0, 1], [0, 0, -1], [1, 0, 0], [0, -1, 0], [-0.0, 0.0, 1.0],
               [side, 0, one_off], [0, -side, -one_off], [side / np.sqrt(2), side / np.sqrt(2), one_off]]
    v = rng.normal(size=(N - len(special), 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return np.concatenate([np.asarray(special, np.float64), v])


@HYP.__class__(HYP, max_examples=8)
@given(st.sampled_from([0.0, 1e-8, 0.05, 1.0, 30.0, 1e4]), st.integers(0, 2**16))
def test_ide_matches_scipy(roughness, seed):
    v = _hard_directions(np.random.default_rng(seed)).astype(DTYPE)
    r = np.full((N, 1), roughness, DTYPE)
    got = np.asarray(_ide(jnp.asarray(v), jnp.asarray(r)), np.float64)
    assert got.dtype == np.float64 and np.all(np.isfinite(got))
    v64 = v.astype(np.float64)
    v64 /= np.linalg.norm(v64, axis=1, keepdims=True)
    want = _scipy_ide(v64, np.full(N, float(DTYPE.type(roughness))), 5)
    att = np.array([np.exp(-0.5 * deg * (deg + 1) * float(DTYPE.type(roughness))) for deg, _ in ide_orders(5)] * 2)
    # columns whose attenuation is below the dtype's smallest normal flush to 0 (|Y| <= ~2)
    assert np.all(np.abs(got - want) <= TOL["ide"] * att + 4 * float(np.finfo(DTYPE).tiny))


def test_ide_gradients_finite_at_poles_and_zero():
    v = jnp.asarray(np.concatenate([_hard_directions(np.random.default_rng(0)), np.zeros((1, 3))]), DTYPE)
    r = jnp.linspace(0.0, 1e4, v.shape[0], dtype=DTYPE)[:, None]
    grads = jax.jit(jax.grad(lambda v, r: jnp.sum(integrated_dir_enc(v, r) ** 2), argnums=(0, 1)))(v, r)
    assert_finite(grads, "grad ")


FX = [dict(), dict(ist=True), dict(point_normals=False)]


@functools.cache
def _params(fx_items):
    cfg = ShadingConfig(effects=Effects(**dict(fx_items)))
    params = init_color_model(cfg, jax.random.key(0))
    return cfg, jax.tree_util.tree_map(lambda a: jnp.asarray(a, DTYPE), params)


@functools.partial(jax.jit, static_argnums=0)
def _shade(cfg, params, f, n, d, ist):
    out = shade(cfg, params, f, n, d, ist)
    return out.sigma, out.rgb, out.pred_normal


def _inputs(seed):
    rng = np.random.default_rng(seed)
    f = rng.normal(size=(N, 32))
    n = rng.normal(size=(N, 3))
    d = rng.normal(size=(N, 3))
    q, _ = np.linalg.qr(rng.normal(size=(N, 3, 3)))
    return f, n, d, q


SCALES = [1e-150, 1e-25, 1e-3, 1e3, 1e25, 1e150] if X64 else [1e-25, 1e-3, 1e3, 1e25]


@pytest.mark.parametrize("fx", FX, ids=["default", "ist", "pred_normals"])
def test_shade_is_invariant_to_the_length_of_normals_and_view_directions(fx):
    """Bug fixed with this suite (numerics.safe_normalize): float32 normals or view directions longer
    than ~1.8e19 or shorter than ~1e-19 shaded as if they were zero."""
    cfg, params = _params(tuple(sorted(fx.items())))
    f, n, d, q = (jnp.asarray(a, DTYPE) for a in _inputs(1))
    _, ref, _ = _shade(cfg, params, f, n, d, q)
    for s in SCALES:
        _, rgb, _ = _shade(cfg, params, f, n * s, d * s, q)
        np.testing.assert_allclose(np.asarray(rgb), np.asarray(ref), rtol=0, atol=TOL["shade_scale"], err_msg=str(s))
        _, rgb, _ = _shade(cfg, params, f, n, d, q * s)  # IST scale: only directions matter
        np.testing.assert_allclose(np.asarray(rgb), np.asarray(ref), rtol=0, atol=TOL["shade_scale"], err_msg=str(s))


@pytest.mark.parametrize("fx", FX, ids=["default", "ist", "pred_normals"])
@pytest.mark.parametrize("feature_scale", [0.0, 1e-30, 1.0, 1e4, 1e10])
def test_shade_outputs_and_gradients_finite_at_hard_inputs(fx, feature_scale):
    cfg, params = _params(tuple(sorted(fx.items())))
    f, n, d, q = _inputs(2)
    f = f * feature_scale
    n[0] = 0.0  # zero normal
    d[1] = 0.0  # zero view direction
    q[2] = 0.0  # singular IST
    q[3] *= 1e20  # huge IST
    n[4] *= 1e-30
    d[5] *= 1e30
    n[6] = d[6]  # normal along the view direction: reflection straight back
    args = [jnp.asarray(a, DTYPE) for a in (f, n, d, q)]
    sigma, rgb, pred = _shade(cfg, params, *args)
    assert_finite((sigma, rgb, pred))
    p = RGB_PADDING
    assert np.all(np.asarray(sigma) >= 0)
    assert np.all(np.asarray(rgb) >= -p - EPS) and np.all(np.asarray(rgb) <= 1 + p + 4 * EPS)
    length = np.linalg.norm(np.asarray(pred, np.float64), axis=-1)
    assert np.all((np.abs(length - 1) < 8 * EPS) | (length == 0))

    def loss(params, f, n, d, q):
        sigma, rgb, pred = _shade(cfg, params, f, n, d, q)
        return jnp.mean((rgb - 0.3) ** 2) + jnp.mean(jnp.log1p(sigma)) + jnp.mean(pred[..., 2])

    grads = jax.grad(loss, argnums=(0, 1, 2, 3, 4))(params, *args)
    assert_finite(grads, "grad ")

"""The integrated directional encoding against scipy's spherical harmonics (an independent
implementation: ``scipy.special.sph_harm_y(l, m, theta_polar, phi_azimuth)``, SciPy >= 1.15 order)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.special import sph_harm_y

from ne_jax.render.ide import ide_dim, ide_orders, integrated_dir_enc, positional_encoding


def _directions(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    special = np.array([[0, 0, 1], [0, 0, -1], [1, 0, 0], [0, -1, 0], [-1, 0, 0], [0.6, 0.8, 0]], float)
    return np.concatenate([special, v])


def _scipy_ide(v: np.ndarray, roughness: np.ndarray, degree: int) -> np.ndarray:
    theta = np.arccos(np.clip(v[:, 2], -1.0, 1.0))
    phi = np.mod(np.arctan2(v[:, 1], v[:, 0]), 2 * np.pi)
    cols = []
    for l, m in ide_orders(degree):
        att = np.exp(-0.5 * l * (l + 1) * roughness)
        cols.append(sph_harm_y(l, m, theta, phi) * att)
    y = np.stack(cols, axis=-1)
    return np.concatenate([y.real, y.imag], axis=-1)


def test_orders_and_dims():
    assert ide_dim(5) == 72
    lm = ide_orders(5)
    assert len(lm) == 36 and sorted({l for l, _ in lm}) == [1, 2, 4, 8, 16]
    assert all(0 <= m <= l for l, m in lm)
    with pytest.raises(ValueError):
        ide_orders(6)


@pytest.mark.parametrize("degree", [1, 3, 5])
def test_matches_scipy_float32(degree):
    """Every (l, m) column, roughness 0 (plain harmonics): float32 to 2e-5 absolute."""
    v = _directions(500)
    got = np.asarray(integrated_dir_enc(jnp.asarray(v, jnp.float32), jnp.zeros((len(v), 1), jnp.float32), degree))
    want = _scipy_ide(v, np.zeros(len(v)), degree)
    assert got.shape == (len(v), ide_dim(degree))
    err = np.abs(got - want).max(axis=0)
    assert err.max() < 2e-5, dict(zip([*ide_orders(degree)] * 2, err))


def test_matches_scipy_float64_every_degree():
    with jax.enable_x64(True):
        v = _directions(300, seed=1)
        r = np.random.default_rng(2).uniform(0, 0.05, size=len(v))
        got = np.asarray(integrated_dir_enc(jnp.asarray(v), jnp.asarray(r)))
        assert got.dtype == np.float64
    np.testing.assert_allclose(got, _scipy_ide(v, r, 5), atol=1e-11, rtol=0)


@pytest.mark.parametrize("roughness", [0.0, 0.003, 0.05, 0.3, 2.0])
def test_attenuation(roughness):
    """``IDE(w, r) = exp(-l(l+1)/2 r) * Y_l^m(w)`` column by column (relative to each column's scale)."""
    v = _directions(200, seed=3)
    r = np.full((len(v), 1), roughness, np.float32)
    got = np.asarray(integrated_dir_enc(jnp.asarray(v, jnp.float32), jnp.asarray(r)))
    want = _scipy_ide(v, r[:, 0].astype(np.float64), 5)
    base = _scipy_ide(v, np.zeros(len(v)), 5)
    r32 = float(np.float32(roughness))
    att = np.array([np.exp(-0.5 * l * (l + 1) * r32) for l, _ in ide_orders(5)] * 2)
    np.testing.assert_allclose(want, base * att, rtol=1e-12, atol=1e-300)
    assert np.all(np.abs(got - want) <= 2e-5 * att + 1e-30)


def test_imaginary_m0_columns_are_zero_and_roughness_shapes():
    v = jnp.asarray(_directions(10), jnp.float32)
    n = v.shape[0]
    a = integrated_dir_enc(v, jnp.full((n,), 0.1))
    b = integrated_dir_enc(v, jnp.full((n, 1), 0.1))
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    m0 = [i for i, (_, m) in enumerate(ide_orders(5)) if m == 0]
    assert np.all(np.asarray(a)[:, 36 + np.array(m0)] == 0)


def test_gradients_finite():
    v = jnp.asarray(_directions(50), jnp.float32)
    r = jnp.linspace(0.0, 3.0, v.shape[0])[:, None]
    gv, gr = jax.jit(jax.grad(lambda v, r: jnp.sum(integrated_dir_enc(v, r) ** 2), argnums=(0, 1)))(v, r)
    assert np.all(np.isfinite(np.asarray(gv))) and np.all(np.isfinite(np.asarray(gr)))
    # the zero vector (a degenerate reflected direction) stays finite too
    g0 = jax.jit(jax.grad(lambda v: jnp.sum(integrated_dir_enc(v, jnp.zeros((1, 1))))))(jnp.zeros((1, 3)))
    assert np.all(np.isfinite(np.asarray(g0)))


def test_positional_encoding_layout():
    x = jnp.asarray([[0.25, -0.5, 1.0]])
    pe = np.asarray(positional_encoding(x, 2))
    assert pe.shape == (1, 3 + 12)
    np.testing.assert_allclose(pe[0, :3], [0.25, -0.5, 1.0])
    arg = np.pi * np.array([1, 1, 1, 2, 2, 2]) * np.tile([0.25, -0.5, 1.0], 2)
    np.testing.assert_allclose(pe[0, 3:9], np.sin(arg), atol=1e-6)
    np.testing.assert_allclose(pe[0, 9:], np.cos(arg), atol=1e-6)

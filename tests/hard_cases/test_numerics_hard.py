"""Stage 0, safe numerics: the helpers at the extremes of the dtype's range (values and gradients)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from ne_jax.numerics import safe_norm, safe_normalize

from .common import DTYPE, HYP, assert_finite

# Magnitudes from far below sqrt(tiny) to far above sqrt(max): a plain sum of squares flushes the
# first to 0 and overflows the second to inf (float32: |x| < ~1e-19 or > ~1.8e19).
_F = np.finfo(DTYPE)
MAGNITUDES = [float(_F.tiny) * 64, float(np.sqrt(_F.tiny)) / 8, 1e-3, 1.0, 1e3,
              float(np.sqrt(_F.max)) * 8, float(_F.max) / 8]


@pytest.mark.parametrize("mag", MAGNITUDES)
def test_safe_norm_and_normalize_over_the_whole_range(mag):
    """Bug fixed with this suite: ``safe_norm`` returned ``inf`` above ~1.8e19 and 0 below ~1e-19
    (float32), so ``safe_normalize`` gave the zero vector for huge or tiny normals."""
    v = np.array([[3.0, 4.0, 0.0], [0.0, -1.0, 0.0], [1.0, 1.0, 1.0]]) / 4.0 * mag / 1.25
    x = jnp.asarray(v, DTYPE)
    want = np.linalg.norm(v.astype(np.longdouble), axis=1)
    got = np.asarray(safe_norm(x), np.longdouble)
    np.testing.assert_allclose(got.astype(np.float64), want.astype(np.float64), rtol=4 * _F.eps)
    unit = np.asarray(safe_normalize(x), np.float64)
    np.testing.assert_allclose(unit, (v / want[:, None]).astype(np.float64), rtol=4 * _F.eps, atol=4 * _F.eps)
    g = jax.vmap(jax.grad(safe_norm))(x)
    assert_finite(g)
    np.testing.assert_allclose(np.asarray(g, np.float64), unit, atol=4 * _F.eps)
    gn = jax.vmap(jax.jacfwd(safe_normalize))(x)
    assert_finite(gn)


def test_safe_norm_zero_inf_nan():
    x = jnp.asarray([[0.0, 0.0, 0.0], [-0.0, 0.0, -0.0], [np.inf, 1.0, 0.0], [np.nan, 1.0, 0.0]], DTYPE)
    got = np.asarray(safe_norm(x))
    assert got[0] == 0 and got[1] == 0 and got[2] == np.inf and np.isnan(got[3])
    g = jax.vmap(jax.grad(safe_norm))(x[:2])
    np.testing.assert_array_equal(np.asarray(g), 0.0)
    np.testing.assert_array_equal(np.asarray(safe_normalize(x[:2])), 0.0)


@HYP
@given(st.lists(st.floats(-1e6, 1e6, allow_subnormal=False), min_size=3, max_size=3),
       st.sampled_from([1e-24, 1.0, 1e24]))
def test_safe_normalize_is_scale_invariant(v, s):
    x = np.asarray(v, DTYPE).astype(np.float64)
    if np.abs(x).max() < 1e-6:  # x * 1e-24 must stay a normal number for the comparison
        return
    a = np.asarray(safe_normalize(jnp.asarray(x, DTYPE)), np.float64)
    b = np.asarray(safe_normalize(jnp.asarray(x * s, DTYPE)), np.float64)
    assert np.all(np.isfinite(a)) and abs(np.linalg.norm(a) - 1) < 8 * _F.eps
    np.testing.assert_allclose(a, b, atol=8 * _F.eps)

"""Tests for the safe numerics helpers added with the geometry core (``safe_reciprocal``)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ne_jax.numerics import safe_reciprocal, stable_ranks, tiny


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float16])
def test_safe_reciprocal_values(dtype):
    t = tiny(dtype)
    x = jnp.asarray([2.0, -4.0, 0.0, -0.0, t, -t, t / 4, 1e-3], dtype)
    got = np.asarray(safe_reciprocal(x), np.float64)
    xs = np.asarray(x, np.float64)
    assert np.all(np.isfinite(got))
    ok = np.abs(xs) >= t
    np.testing.assert_allclose(got[ok], 1.0 / xs[ok], rtol=1e-3)
    assert np.all(got[~ok] == 0.0)
    assert float(safe_reciprocal(jnp.asarray(0.0, dtype), fallback=7.0)) == 7.0


def test_safe_reciprocal_grad_finite():
    g = jax.vmap(jax.grad(lambda v: safe_reciprocal(v)))(jnp.asarray([0.0, -0.0, 1e-40, 0.5, -2.0]))
    g = np.asarray(g)
    assert np.all(np.isfinite(g))
    np.testing.assert_allclose(g, [0.0, 0.0, 0.0, -4.0, -0.25], rtol=1e-6)


def test_stable_ranks_equal_a_stable_argsort_with_ties_and_infinities():
    rng = np.random.default_rng(0)
    key = rng.integers(0, 5, (50, 32)).astype(np.float32)  # many ties
    key[rng.random(key.shape) < 0.2] = np.inf
    ranks = np.asarray(stable_ranks(jnp.asarray(key)))
    expected = np.empty_like(ranks)
    np.put_along_axis(expected, np.argsort(key, axis=-1, kind="stable"), np.arange(32)[None, :], axis=-1)
    np.testing.assert_array_equal(ranks, expected)

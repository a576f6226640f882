"""Tests for the safe numerics added with the rendering pieces (``safe_sqrt``)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ne_jax.numerics import safe_sqrt, tiny


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float16])
def test_safe_sqrt_values(dtype):
    t = tiny(dtype)
    x = jnp.asarray([4.0, 0.25, 0.0, -0.0, -1.0, t / 4, 2 * t], dtype)
    got = np.asarray(safe_sqrt(x), np.float64)
    xs = np.asarray(x, np.float64)
    ok = xs > t
    np.testing.assert_allclose(got[ok], np.sqrt(xs[ok]), rtol=1e-3)
    assert np.all(got[~ok] == 0.0)


def test_safe_sqrt_grad_finite():
    g = np.asarray(jax.vmap(jax.grad(safe_sqrt))(jnp.asarray([0.0, -0.0, -3.0, 1e-40, 4.0], jnp.float32)))
    assert np.all(np.isfinite(g))
    np.testing.assert_allclose(g, [0.0, 0.0, 0.0, 0.0, 0.25], rtol=1e-6)

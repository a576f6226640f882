"""Stage 4, integration (``level_samples``, ``integrate``, under ``jit``): segments at distances and
lengths from 1e-4 to 1e4 (and zero-length), mixed levels, every deterministic rule; values spanning
1e-30 .. 1e30 — against float64 numpy (positions ``t_lo + u L``, weights from
``quadrature_weights``, means ``w . y``).

Tolerances (``common.TOL``): positions within ``TOL["t_rel"]`` times ``max(|t_lo|, |t_hi|)`` (float32
1e-5, float64 1e-12), both end points exact, never outside the segment, nondecreasing; weights of a
level sum to 1 within 8 eps; means within ``TOL["quad"] * sum_s |w_s y_s|`` (float32 2e-6, float64
1e-13). Gradients with respect to the end points and the values are finite.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from ne_jax.render.quadrature import DETERMINISTIC_RULES, QuadratureConfig, integrate, level_samples, level_table

from .common import DTYPE, EPS, HYP, TOL, assert_finite

B, D = 64, 5


@functools.partial(jax.jit, static_argnums=0)
def _sample_and_integrate(cfg, t_lo, t_hi, level, values):
    t, w = level_samples(cfg, t_lo, t_hi, level)
    return t, w, integrate(values, w)


def _segments(rng, magnitude, rel_length):
    t_lo = rng.uniform(0.5, 2.0, B) * magnitude
    length = t_lo * rel_length * rng.uniform(0, 1, B)
    length[:4] = 0.0  # zero-length segments
    t_hi = t_lo + length
    level = rng.integers(0, 5, B)
    level[4] = -3  # out of range: clipped
    level[5] = 99
    return t_lo.astype(DTYPE), t_hi.astype(DTYPE), level.astype(np.int32)


@HYP.__class__(HYP, max_examples=12)
@given(st.sampled_from(DETERMINISTIC_RULES), st.sampled_from([1e-4, 1.0, 1e4]),
       st.sampled_from([1e-4, 1e-2, 1.0]), st.sampled_from([1e-30, 1.0, 1e30]), st.integers(0, 2**16))
def test_positions_weights_and_means(rule, magnitude, rel_length, value_scale, seed):
    rng = np.random.default_rng(seed)
    cfg = QuadratureConfig(rule=rule)
    t_lo, t_hi, level = _segments(rng, magnitude, rel_length)
    y = (rng.normal(size=(B, cfg.max_samples, D)) * value_scale).astype(DTYPE)
    t, w, mean = _sample_and_integrate(cfg, jnp.asarray(t_lo), jnp.asarray(t_hi), jnp.asarray(level), jnp.asarray(y))
    assert t.dtype == w.dtype == mean.dtype == DTYPE
    assert_finite((t, w, mean))
    t, w, mean = (np.asarray(a, np.float64) for a in (t, w, mean))
    u_tab, w_tab = level_table(cfg)
    li = np.clip(level, 0, len(cfg.samples_per_level) - 1)
    lo, hi = t_lo.astype(np.float64), t_hi.astype(np.float64)
    want_t = lo[:, None] + u_tab[li] * (hi - lo)[:, None]
    err = np.abs(t - want_t) / np.maximum(np.abs(lo), np.abs(hi))[:, None]
    assert err.max() <= TOL["t_rel"], err.max()
    assert np.all(t >= lo[:, None]) and np.all(t <= hi[:, None])
    assert np.all(np.diff(t, axis=1) >= 0)
    s = np.asarray(cfg.samples_per_level)[li]
    np.testing.assert_array_equal(t[:, 0], lo)
    np.testing.assert_array_equal(t[np.arange(B), s - 1], hi)
    np.testing.assert_allclose(w, w_tab[li], rtol=EPS, atol=0)
    np.testing.assert_allclose(w.sum(1), 1.0, atol=8 * EPS)
    want = np.einsum("bs,bsd->bd", w_tab[li], y.astype(np.float64))
    bound = np.einsum("bs,bsd->bd", np.abs(w_tab[li]), np.abs(y.astype(np.float64)))
    err = np.abs(mean - want) / np.maximum(bound, 1e-300)
    assert err.max() <= TOL["quad"], err.max()


@pytest.mark.parametrize("rule", ["hermite", "spline"])
def test_gradients_finite_at_zero_length_and_huge_segments(rule):
    cfg = QuadratureConfig(rule=rule)
    rng = np.random.default_rng(0)
    t_lo, t_hi, level = _segments(rng, 1e4, 1.0)
    big = float(np.finfo(DTYPE).max) ** 0.5
    t_hi[6], t_lo[6] = big, big / 2  # a segment far out
    y = rng.normal(size=(B, cfg.max_samples, D)).astype(DTYPE)

    def loss(t_lo, t_hi, y):
        t, w, mean = _sample_and_integrate(cfg, t_lo, t_hi, jnp.asarray(level), y)
        return jnp.sum(mean ** 2) + jnp.sum(w * t / big)

    grads = jax.grad(loss, argnums=(0, 1, 2))(jnp.asarray(t_lo), jnp.asarray(t_hi), jnp.asarray(y))
    assert_finite(grads, "grad ")

"""Quadrature rules against float64 references: exactness degrees, fitted convergence orders,
slow loop implementations of the interpolants, and the fixed-shape per-level tables."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ne_jax.render.quadrature import (
    DETERMINISTIC_RULES,
    EXACT_DEGREE,
    RULES,
    QuadratureConfig,
    integrate,
    level_samples,
    level_table,
    quadrature_weights,
    sample_fractions,
    sample_positions,
)

LEVEL_S = (8, 11, 16, 22)
EXPECTED_ORDER = {"hermite": 3, "hermite_o4": 4, "spline": 4, "spline_natural": 3, "trapezoid": 2}


# ---- slow references (numpy loops, float64) ----------------------------------------------------


def hermite_mean_loop(y: np.ndarray, end_stencil: str) -> float:
    """Mean over [0, 1] of the piecewise cubic Hermite interpolant through ``y`` at
    ``linspace(0, 1, s)``, integrated piece by piece; node derivatives as in the released code
    (average of the neighbouring secants), ends by the given one-sided stencil."""
    s = len(y)
    h = 1.0 / (s - 1)
    m = np.zeros(s)
    for i in range(1, s - 1):
        m[i] = 0.5 * ((y[i] - y[i - 1]) / h + (y[i + 1] - y[i]) / h)
    if end_stencil == "secant":
        m[0] = (y[1] - y[0]) / h
        m[-1] = (y[-1] - y[-2]) / h
    else:
        m[0] = (-3 * y[0] + 4 * y[1] - y[2]) / (2 * h)
        m[-1] = (3 * y[-1] - 4 * y[-2] + y[-3]) / (2 * h)
    total = 0.0
    for i in range(s - 1):
        # integral of the Hermite basis over one piece: h/2 (y0 + y1) + h^2/12 (m0 - m1)
        total += h * (y[i] + y[i + 1]) / 2 + h * h * (m[i] - m[i + 1]) / 12
    return total


def natural_spline_mean_loop(y: np.ndarray) -> float:
    """Mean of the natural cubic spline: solve for the knot second derivatives (Thomas algorithm),
    then integrate each piece: h/2 (y0 + y1) - h^3/24 (M0 + M1)."""
    s = len(y)
    h = 1.0 / (s - 1)
    n = s - 2
    big_m = np.zeros(s)
    if n > 0:
        a = np.full(n, 1.0)
        b = np.full(n, 4.0)
        c = np.full(n, 1.0)
        d = np.array([6.0 / h**2 * (y[i + 2] - 2 * y[i + 1] + y[i]) for i in range(n)])
        for i in range(1, n):
            w = a[i] / b[i - 1]
            b[i] -= w * c[i - 1]
            d[i] -= w * d[i - 1]
        x = np.zeros(n)
        x[-1] = d[-1] / b[-1]
        for i in range(n - 2, -1, -1):
            x[i] = (d[i] - c[i] * x[i + 1]) / b[i]
        big_m[1:-1] = x
    return sum(h * (y[i] + y[i + 1]) / 2 - h**3 * (big_m[i] + big_m[i + 1]) / 24 for i in range(s - 1))


def smooth_field(t: np.ndarray) -> np.ndarray:
    return np.exp(0.7 * t) * np.sin(3.0 * t)


def smooth_mean(lo: float, hi: float) -> float:
    a, b = 3.0, 0.7
    def anti(t):
        return np.exp(b * t) * (b * np.sin(a * t) - a * np.cos(a * t)) / (a * a + b * b)
    return (anti(hi) - anti(lo)) / (hi - lo)


# ---- weights ------------------------------------------------------------------------------------


@pytest.mark.parametrize("rule", RULES)
@pytest.mark.parametrize("s", [1, 2, 3, 4, 8, 11, 16, 22])
def test_weights_sum_to_one_and_are_cached_readonly(rule, s):
    w = quadrature_weights(s, rule)
    assert w.shape == (s,) and w.dtype == np.float64
    assert abs(w.sum() - 1.0) < 1e-14
    assert quadrature_weights(s, rule) is w
    with pytest.raises(ValueError):
        w[0] = 0.0


def test_released_hermite_weights_closed_form():
    s = 8
    h = 1.0 / (s - 1)
    expected = h * np.array([5 / 12, 13 / 12, 1, 1, 1, 1, 13 / 12, 5 / 12])
    np.testing.assert_allclose(quadrature_weights(s, "hermite"), expected, rtol=1e-14)
    # three samples: the second-order end correction is Simpson's rule
    np.testing.assert_allclose(quadrature_weights(3, "hermite_o4"), [1 / 6, 4 / 6, 1 / 6], rtol=1e-14)


@pytest.mark.parametrize("s", [3, 4, 8, 11, 16, 22])
def test_hermite_weights_match_loop_over_interpolant(s):
    rng = np.random.default_rng(s)
    for _ in range(5):
        y = rng.normal(size=s)
        assert abs(quadrature_weights(s, "hermite") @ y - hermite_mean_loop(y, "secant")) < 1e-12
        assert abs(quadrature_weights(s, "hermite_o4") @ y - hermite_mean_loop(y, "three_point")) < 1e-12


@pytest.mark.parametrize("s", [3, 4, 8, 11, 16, 22])
def test_natural_spline_weights_match_thomas_loop(s):
    rng = np.random.default_rng(100 + s)
    for _ in range(5):
        y = rng.normal(size=s)
        assert abs(quadrature_weights(s, "spline_natural") @ y - natural_spline_mean_loop(y)) < 1e-12


def test_unknown_rule_and_bad_s_raise():
    with pytest.raises(ValueError):
        quadrature_weights(8, "simpson")
    with pytest.raises(ValueError):
        quadrature_weights(0, "hermite")
    with pytest.raises(ValueError):
        QuadratureConfig(rule="nope")


# ---- exactness (float32 end to end) -------------------------------------------------------------


@pytest.mark.parametrize("rule", DETERMINISTIC_RULES)
@pytest.mark.parametrize("s", LEVEL_S)
def test_exact_on_polynomials_up_to_degree_float32(rule, s):
    """Random polynomials of every degree the rule integrates exactly, on random segments, through
    ``sample_positions`` + ``integrate`` in float32: the analytic mean to float32 accuracy."""
    rng = np.random.default_rng(7)
    deg = EXACT_DEGREE[rule]
    lo = rng.uniform(-2, 1, size=16)
    hi = lo + rng.uniform(0.1, 3, size=16)
    t = np.asarray(sample_positions(jnp.asarray(lo, jnp.float32), jnp.asarray(hi, jnp.float32), s, rule))
    t64 = lo[:, None] + np.linspace(0, 1, s) * (hi - lo)[:, None]
    np.testing.assert_allclose(t, t64, rtol=1e-6, atol=1e-6)
    w = quadrature_weights(s, rule)
    for k in range(deg + 1):
        coef = rng.normal(size=k + 1)
        vals = np.polyval(coef, t64)  # samples exact in float64, rounded once to float32
        got = np.asarray(integrate(jnp.asarray(vals[..., None], jnp.float32), w))[:, 0]
        anti = np.polyint(coef)
        want = (np.polyval(anti, hi) - np.polyval(anti, lo)) / (hi - lo)
        scale = np.abs(vals).max(axis=1) + 1.0
        assert np.all(np.abs(got - want) <= 4e-6 * scale), (rule, s, k, np.abs(got - want).max())
    # and the next degree is *not* integrated exactly (the claimed degree is tight), in float64
    x = np.linspace(0, 1, s)
    assert abs(w @ x ** (deg + 1) - 1 / (deg + 2)) > 1e-9


# ---- convergence order --------------------------------------------------------------------------


def _fit_order(hs, errs):
    return float(np.polyfit(np.log(hs), np.log(errs), 1)[0])


@pytest.mark.parametrize("rule", DETERMINISTIC_RULES)
def test_convergence_order_on_smooth_field(rule):
    """Error of the segment mean of ``exp(0.7 t) sin(3 t)`` on ``[0.2, 2.3]`` (analytic mean) as ``s``
    doubles; the fitted slope of log error vs log h matches the rule's order within 0.35."""
    lo, hi = 0.2, 2.3
    want = smooth_mean(lo, hi)
    ss = np.array([17, 33, 65, 129, 257])
    errs = []
    for s in ss:
        t = lo + np.linspace(0, 1, s) * (hi - lo)
        errs.append(abs(quadrature_weights(int(s), rule) @ smooth_field(t) - want))
    order = _fit_order(1.0 / (ss - 1), np.array(errs))
    assert abs(order - EXPECTED_ORDER[rule]) < 0.35, (rule, order, errs)


def test_stochastic_rms_error_order():
    """Stratified sampling: unbiased, RMS error ~ s^-1.5 on a smooth field."""
    lo, hi = 0.2, 2.3
    want = smooth_mean(lo, hi)
    ss = np.array([4, 8, 16, 32, 64])
    rms, bias = [], []
    for i, s in enumerate(ss):
        n = 4000
        t = np.asarray(sample_positions(jnp.full((n,), lo, jnp.float32), jnp.full((n,), hi, jnp.float32),
                                        int(s), "stochastic", key=jax.random.key(i)), np.float64)
        assert np.all(np.diff(t, axis=-1) >= 0) and t.min() >= lo - 1e-6 and t.max() <= hi + 1e-6
        est = smooth_field(t) @ quadrature_weights(int(s), "stochastic")
        rms.append(np.sqrt(np.mean((est - want) ** 2)))
        bias.append(abs(est.mean() - want))
    order = -_fit_order(ss, np.array(rms))
    assert abs(order - 1.5) < 0.3, (order, rms)
    assert all(b < 4 * r / np.sqrt(4000) + 1e-6 for b, r in zip(bias, rms)), (bias, rms)


def test_stochastic_needs_key_and_differs_per_key():
    with pytest.raises(ValueError):
        sample_fractions(8, "stochastic")
    a = sample_fractions(8, "stochastic", jax.random.key(0), (3,))
    b = sample_fractions(8, "stochastic", jax.random.key(1), (3,))
    assert a.shape == (3, 8) and not np.array_equal(np.asarray(a), np.asarray(b))


# ---- integrate: shapes and hard cases -------------------------------------------------------------


def _loop_integrate(values: np.ndarray, w: np.ndarray) -> np.ndarray:
    """values [R, M, s, ...] -> [R, M, ...] by explicit loops in float64."""
    r, m, s = values.shape[:3]
    out = np.zeros((r, m) + values.shape[3:])
    for i in range(r):
        for j in range(m):
            for k in range(s):
                out[i, j] += w[k] * values[i, j, k]
    return out


@pytest.mark.parametrize("trailing,axis", [((32,), -2), ((3,), -2), ((3, 3), -3)])
def test_integrate_features_normals_ist(trailing, axis):
    rng = np.random.default_rng(3)
    vals = rng.normal(size=(4, 5, 11) + trailing)
    w = quadrature_weights(11, "hermite")
    got = integrate(jnp.asarray(vals, jnp.float32), w, axis=axis)
    assert got.shape == (4, 5) + trailing and got.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(got), _loop_integrate(vals, w), atol=2e-6)


def test_integrate_per_segment_level_weights():
    cfg = QuadratureConfig(rule="spline", samples_per_level=(8, 11, 16, 22, 22))
    rng = np.random.default_rng(4)
    level = rng.integers(0, 5, size=(6, 7))
    lo = rng.uniform(0, 1, size=(6, 7))
    hi = lo + rng.uniform(0, 1, size=(6, 7))
    t, w = level_samples(cfg, jnp.asarray(lo, jnp.float32), jnp.asarray(hi, jnp.float32), jnp.asarray(level))
    assert t.shape == w.shape == (6, 7, 22)
    vals = rng.normal(size=(6, 7, 22, 5))
    got = np.asarray(integrate(jnp.asarray(vals, jnp.float32), w))
    for i in range(6):
        for j in range(7):
            s = cfg.samples_per_level[level[i, j]]
            ref = quadrature_weights(s, "spline") @ vals[i, j, :s]
            np.testing.assert_allclose(got[i, j], ref, atol=3e-6)
            np.testing.assert_allclose(np.asarray(t)[i, j, :s], lo[i, j] + np.linspace(0, 1, s) * (hi - lo)[i, j],
                                       rtol=1e-6, atol=1e-6)
            assert np.asarray(t)[i, j, 0] == np.float32(lo[i, j])
            assert np.asarray(t)[i, j, s - 1] == np.float32(hi[i, j])
            assert np.all(np.asarray(w)[i, j, s:] == 0)


def test_level_samples_stochastic_and_clipped_levels():
    cfg = QuadratureConfig(rule="stochastic", samples_per_level=(3, 5))
    lo = jnp.zeros((4,))
    hi = jnp.ones((4,))
    t, w = level_samples(cfg, lo, hi, jnp.asarray([0, 1, -1, 9]), key=jax.random.key(0))
    t, w = np.asarray(t), np.asarray(w)
    np.testing.assert_allclose(w.sum(-1), 1.0, rtol=1e-6)
    np.testing.assert_allclose(w[0], [1 / 3] * 3 + [0, 0], rtol=1e-6)
    np.testing.assert_allclose(w[2], w[0]) and np.testing.assert_allclose(w[3], w[1])
    assert np.all((t >= 0) & (t <= 1)) and np.all(np.diff(t, axis=-1) >= 0)
    with pytest.raises(ValueError):
        level_samples(cfg, lo, hi, jnp.zeros((4,), int))


def test_level_table_padding():
    u, w = level_table(QuadratureConfig())
    assert u.shape == w.shape == (5, 22)
    for i, s in enumerate((8, 11, 16, 22, 22)):
        np.testing.assert_array_equal(u[i, :s], np.linspace(0, 1, s))
        assert np.all(u[i, s:] == 1) and np.all(w[i, s:] == 0)
        np.testing.assert_array_equal(w[i, :s], quadrature_weights(s, "hermite"))


@pytest.mark.parametrize("rule", RULES)
def test_zero_length_segments(rule):
    """A zero-length segment samples one point s times; its mean is that value (weights sum to 1)
    and gradients w.r.t. the samples are the (finite) weights."""
    s = 16
    key = jax.random.key(0) if rule == "stochastic" else None
    t = sample_positions(jnp.asarray([1.5, 0.0]), jnp.asarray([1.5, 0.0]), s, rule, key=key)
    assert np.all(np.asarray(t)[0] == 1.5) and np.all(np.asarray(t)[1] == 0.0)
    vals = jnp.broadcast_to(jnp.asarray([3.25, -1.0, 7.0], jnp.float32), (2, s, 3))
    got = integrate(vals, quadrature_weights(s, rule))
    np.testing.assert_allclose(np.asarray(got), [[3.25, -1.0, 7.0]] * 2, rtol=2e-6)
    g = jax.grad(lambda v: integrate(v, quadrature_weights(s, rule)).sum())(vals)
    assert np.all(np.isfinite(np.asarray(g)))


def test_integrate_float64():
    with jax.enable_x64(True):
        vals = jnp.asarray(np.random.default_rng(0).normal(size=(3, 22, 4)))
        w = quadrature_weights(22, "spline")
        got = integrate(vals, w)
        assert got.dtype == jnp.float64
        np.testing.assert_allclose(np.asarray(got), np.einsum("rsd,s->rd", np.asarray(vals), w), rtol=1e-13)


def test_integrate_rejects_mismatched_weights():
    with pytest.raises(ValueError):
        integrate(jnp.zeros((2, 8, 3)), quadrature_weights(11, "hermite"))

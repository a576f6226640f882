"""Stage 6, compositing (``composite``, ``clip_overlaps``, under ``jit``): random rays of slots with
densities from 0 through 1e-30 .. 1e30 to the dtype's max, lengths from 0 to 1e10 (so
``sigma * len`` overflows), random validity — against a float64 reference in log space.

The reference here is not ``tests/render/test_composite.composite_loop``: that loop forms the
opacity as ``1 - T`` (float64 cancellation: a relative error of ``1e-16 / opacity``, i.e. useless
below ~1e-10), while ``composite`` is accurate there (``-expm1``); this one uses ``expm1`` too.

Tolerances (``common.TOL``): rgb, opacity, transmittance, weights within ``comp_rtol`` relative plus
``comp_atol`` absolute (float32 2e-5 / 2e-6, float64 1e-11 / 1e-13); the depth where the reference
opacity exceeds ``1e3 sqrt(tiny)`` (below, ``composite`` reports 0 by design), relative to the
largest ``t``. Gradients with respect to density, colour, lengths and ``t`` are finite: of rgb and
opacity for densities up to 1e30, of the depth for densities up to 1e8 (beyond, its true derivative
with respect to a length, ``sigma * t / opacity``, exceeds float32's range).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from ne_jax.render.composite import TAU_MAX, clip_overlaps, composite

from .common import DTYPE, HYP, TOL, assert_finite

R, M = 16, 12
_composite = jax.jit(composite)


def reference(sigma, rgb, lengths, valid, t_mid, bg):
    sigma, lengths = sigma.astype(np.float64), lengths.astype(np.float64)
    with np.errstate(over="ignore"):
        tau = np.where(valid, np.minimum(sigma * lengths, TAU_MAX), 0.0)
    excl = np.cumsum(tau, axis=1) - tau
    w = np.where(valid, np.exp(-excl) * -np.expm1(-tau), 0.0)
    total = tau.sum(1)
    opacity = -np.expm1(-total)
    trans = np.exp(-total)
    out = np.einsum("rm,rmc->rc", w, np.where(valid[..., None], rgb, 0.0)) + trans[:, None] * bg
    with np.errstate(invalid="ignore", divide="ignore"):
        depth = np.where(opacity > 0, (w * np.where(valid, t_mid, 0.0)).sum(1) / opacity, 0.0)
    return out, opacity, depth, w, trans


SIGMAS = [0.0, 1e-30, 1e-8, 1e-3, 1.0, 30.0, 1e8, 1e30]


@HYP.__class__(HYP, max_examples=15)
@given(st.integers(0, 2**16), st.sampled_from([0.0, 0.2, 0.9]), st.booleans())
def test_matches_float64_reference(seed, p_invalid, extreme):
    rng = np.random.default_rng(seed)
    if extreme:
        sigma = rng.choice(SIGMAS + [float(np.finfo(DTYPE).max) / 2], size=(R, M))
        lengths = rng.choice([0.0, 1e-30, 1e-3, 1.0, 1e10], size=(R, M))
    else:
        sigma = rng.gamma(0.5, 2.0, size=(R, M))
        lengths = rng.uniform(0, 2, size=(R, M))
    valid = rng.random((R, M)) >= p_invalid
    valid[0] = False  # an empty ray
    t_mid = np.cumsum(rng.uniform(0, 3, size=(R, M)), axis=1) * rng.choice([1e-4, 1.0, 1e4])
    rgb = rng.random((R, M, 3))
    bg = rng.random((R, 3))
    args = [a.astype(DTYPE) for a in (sigma, rgb, lengths)] + [valid] + [a.astype(DTYPE) for a in (t_mid, bg)]
    got = _composite(*(jnp.asarray(a) for a in args))
    assert got.rgb.dtype == DTYPE
    assert_finite(got)
    want = reference(*(np.asarray(a, np.float64) if a.dtype != bool else a for a in args))
    rt, at = TOL["comp_rtol"], TOL["comp_atol"]
    for name, g, w in zip(("rgb", "opacity", "weights", "transmittance"),
                          (got.rgb, got.opacity, got.weights, got.transmittance),
                          (want[0], want[1], want[3], want[4])):
        np.testing.assert_allclose(np.asarray(g, np.float64), w, rtol=rt, atol=at, err_msg=name)
    seen = want[1] > 1e3 * np.sqrt(np.finfo(DTYPE).tiny)
    tmax = np.abs(args[4].astype(np.float64)).max()
    np.testing.assert_allclose(np.asarray(got.depth, np.float64)[seen], want[2][seen], rtol=0, atol=rt * tmax)
    np.testing.assert_array_equal(np.asarray(got.rgb)[0], args[5][0])  # empty ray: the background

    def loss(sigma, rgb, lengths, t_mid):
        o = composite(sigma, rgb, lengths, jnp.asarray(valid), t_mid, jnp.asarray(args[5]))
        # depth through densities <= 1e8 only: d depth / d len = sigma * d depth / d tau, and the
        # latter reaches t / opacity, so at sigma = 1e30 the true derivative exceeds float32's range
        od = composite(jnp.minimum(sigma, 1e8), rgb, lengths, jnp.asarray(valid), t_mid, jnp.asarray(args[5]))
        return jnp.sum(o.rgb) + jnp.sum(o.opacity) + jnp.sum(od.depth) / tmax

    # Gradients: densities up to 1e30 (d tau / d len = sigma is itself ~max at sigma = max / 2).
    sig = jnp.asarray(np.minimum(args[0], 1e30).astype(DTYPE))
    grads = jax.jit(jax.grad(loss, argnums=(0, 1, 2, 3)))(sig, *(jnp.asarray(args[i]) for i in (1, 2, 4)))
    assert_finite(grads, "grad ")


@HYP.__class__(HYP, max_examples=10)
@given(st.integers(0, 2**16), st.sampled_from([1e-4, 1.0, 1e4]))
def test_clip_overlaps_against_a_loop(seed, scale):
    """Random overlapping, nested, identical and zero-length segments at 1e-4 .. 1e4: every stretch
    counted once (float64 loop), lengths never negative."""
    rng = np.random.default_rng(seed)
    lo = np.sort(rng.uniform(0, 10, (R, M)), axis=1)
    hi = lo + rng.choice([0.0, 0.1, 1.0, 5.0], size=(R, M))
    lo[:, 3], hi[:, 3] = lo[:, 2], hi[:, 2]  # identical
    lo, hi = (lo * scale).astype(DTYPE), (hi * scale).astype(DTYPE)
    valid = rng.random((R, M)) < 0.8
    new_lo, new_hi = jax.jit(clip_overlaps)(jnp.asarray(lo), jnp.asarray(hi), jnp.asarray(valid))
    new_lo, new_hi = np.asarray(new_lo), np.asarray(new_hi)
    for r in range(R):
        reach = -np.inf
        for m in range(M):
            if not valid[r, m]:
                assert new_lo[r, m] == lo[r, m]
                continue
            want = min(max(lo[r, m], reach), hi[r, m])
            assert new_lo[r, m] == want and new_hi[r, m] >= new_lo[r, m]
            reach = max(reach, hi[r, m])


def test_opaque_slot_after_thin_ones_keeps_its_weight():
    """Bug fixed with this suite: the exclusive transmittance sum was ``cumsum(tau) - tau``, which
    for a huge ``tau_i`` (a surface: clamped at 1e3) carries the inclusive sum's rounding, ulp(1e3) =
    6e-5 in float32, into ``T_i`` — the weight of the very slot that stops the ray was off by ~5e-5."""
    tau = np.array([[0.3, 1e30, 0.2], [1e-3, 0.123, 1e8]])
    ones = np.ones_like(tau)
    out = _composite(jnp.asarray(tau, DTYPE), jnp.ones((2, 3, 3), DTYPE), jnp.asarray(ones, DTYPE),
                     jnp.ones((2, 3), bool), jnp.asarray(ones, DTYPE), jnp.zeros(3, DTYPE))
    w = np.asarray(out.weights, np.float64)
    np.testing.assert_allclose(w[0, 1], np.exp(-0.3), rtol=4 * np.finfo(DTYPE).eps)
    np.testing.assert_allclose(w[1, 2], np.exp(-0.124), rtol=4 * np.finfo(DTYPE).eps)

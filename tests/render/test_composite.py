"""Compositing against a float64 numpy loop, float32 accuracy on thin and deep stacks, and the
hard cases: zero-length and overlapping segments, empty rays, underflowing transmittance, zero
density, garbage in invalid slots; finite gradients; one compilation."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ne_jax.render.composite import clip_overlaps, composite


def composite_loop(sigma, rgb, lengths, valid, t_mid, background, normals=None):
    """Slow float64 reference: walk each ray's slots in order."""
    r, m = sigma.shape
    out = np.zeros((r, 3))
    opacity = np.zeros(r)
    depth = np.zeros(r)
    weights = np.zeros((r, m))
    normal = np.zeros((r, 3))
    bg = np.broadcast_to(background, (r, 3))
    for i in range(r):
        trans = 1.0
        acc_t = 0.0
        for j in range(m):
            if not valid[i, j]:
                continue
            tau = min(float(sigma[i, j]) * float(lengths[i, j]), 1e3)
            alpha = -np.expm1(-tau)
            weights[i, j] = trans * alpha
            out[i] += weights[i, j] * rgb[i, j]
            if normals is not None:
                normal[i] += weights[i, j] * normals[i, j]
            acc_t += weights[i, j] * t_mid[i, j]
            trans *= np.exp(-tau)
        opacity[i] = 1.0 - trans
        out[i] += trans * bg[i]
        depth[i] = acc_t / opacity[i] if opacity[i] > 0 else 0.0
    return out, opacity, depth, weights, normal


def _random_rays(seed, r=6, m=12):
    rng = np.random.default_rng(seed)
    sigma = rng.gamma(0.7, 2.0, size=(r, m))
    lengths = rng.uniform(0, 1.5, size=(r, m))
    lengths[0, 2] = 0.0  # zero-length segment
    sigma[1, :4] = 0.0  # zero density
    valid = rng.random((r, m)) < 0.8
    valid[2] = False  # a ray with no segments
    t_lo = np.cumsum(lengths + 0.1, axis=1)
    t_mid = t_lo + lengths / 2
    rgb = rng.random((r, m, 3))
    normals = rng.normal(size=(r, m, 3))
    background = rng.random((r, 3))
    return sigma, rgb, lengths, valid, t_mid, background, normals


def _jnp32(*xs):
    return [jnp.asarray(x, jnp.float32) if x.dtype != bool else jnp.asarray(x) for x in xs]


def test_matches_float64_loop():
    sigma, rgb, lengths, valid, t_mid, bg, normals = _random_rays(0)
    got = composite(*_jnp32(sigma, rgb, lengths, valid, t_mid, bg), normals=jnp.asarray(normals, jnp.float32))
    want = composite_loop(sigma, rgb, lengths, valid, t_mid, bg, normals)
    for g, w in zip((got.rgb, got.opacity, got.depth, got.weights, got.normal), want):
        np.testing.assert_allclose(np.asarray(g), w, rtol=2e-5, atol=2e-6)
    np.testing.assert_allclose(np.asarray(got.transmittance), 1 - want[1], atol=1e-6)
    np.testing.assert_array_equal(np.asarray(got.rgb)[2], np.float32(bg[2]))  # empty ray: background


def test_float32_accuracy_thin_and_deep_stacks():
    """512 thin slots (tau 1e-4 each) and 512 deep slots (tau up to 40 in total): every weight keeps
    its float64 value to 1e-4 relative (a difference of transmittances would lose it)."""
    m = 512
    for tau in (1e-4, 0.08):
        sigma = np.full((1, m), tau)
        rgb = np.ones((1, m, 3))
        lengths = np.ones((1, m))
        valid = np.ones((1, m), bool)
        t_mid = np.arange(m, dtype=np.float64)[None]
        bg = np.zeros(3)
        got = composite(*_jnp32(sigma, rgb, lengths, valid, t_mid, bg))
        want = composite_loop(sigma, rgb, lengths, valid, t_mid, bg)
        w = np.asarray(got.weights, np.float64)
        keep = want[3] > 1e-30
        np.testing.assert_allclose(w[keep], want[3][keep], rtol=1e-4)
        np.testing.assert_allclose(float(got.opacity[0]), want[1][0], rtol=1e-5)


def test_huge_density_underflows_cleanly_with_finite_grads():
    sigma = np.array([[0.5, 1e30, 3.0, 1e38]])
    lengths = np.array([[1.0, 1e10, 1.0, 1.0]])  # sigma * len overflows float32
    valid = np.ones((1, 4), bool)
    rgb = np.random.default_rng(1).random((1, 4, 3))
    args = _jnp32(sigma, rgb, lengths, valid, np.array([[1.0, 2, 3, 4]]), np.array([0.2, 0.4, 0.6]))
    out = composite(*args)
    w = np.asarray(out.weights)[0]
    np.testing.assert_allclose(w[:2], [1 - np.exp(-0.5), np.exp(-0.5)], rtol=1e-6)
    assert w[2] == 0.0 and w[3] == 0.0 and float(out.transmittance[0]) == 0.0
    assert float(out.opacity[0]) == 1.0

    def loss(sigma, rgb, lengths):
        o = composite(sigma, rgb, lengths, *args[3:])
        return jnp.sum(o.rgb) + jnp.sum(o.depth) + jnp.sum(o.opacity)

    for g in jax.grad(loss, argnums=(0, 1, 2))(*args[:3]):
        assert np.all(np.isfinite(np.asarray(g)))


def test_zero_density_is_pure_background():
    r, m = 3, 5
    bg = jnp.asarray([0.1, 0.7, 1.0])
    out = composite(jnp.zeros((r, m)), jnp.ones((r, m, 3)), jnp.ones((r, m)), jnp.ones((r, m), bool),
                    jnp.ones((r, m)), bg)
    np.testing.assert_array_equal(np.asarray(out.rgb), np.tile(np.asarray(bg), (r, 1)))
    assert np.all(np.asarray(out.opacity) == 0) and np.all(np.asarray(out.depth) == 0)
    assert np.all(np.asarray(out.weights) == 0)


def test_invalid_slots_with_garbage_contribute_nothing_and_grads_stay_finite():
    """A ray with no segments (all slots invalid, NaN/inf garbage in them): pure background."""
    sigma = jnp.asarray([[jnp.nan, jnp.inf, 1.0], [2.0, jnp.nan, 1.0]])
    rgb = jnp.full((2, 3, 3), jnp.nan).at[1, 0].set(0.5).at[1, 2].set(0.25)
    lengths = jnp.asarray([[jnp.inf, 1.0, jnp.nan], [1.0, 1.0, 0.5]])
    valid = jnp.asarray([[False, False, False], [True, False, True]])
    t_mid = jnp.asarray([[jnp.nan, 0.0, 0.0], [1.0, jnp.nan, 3.0]])
    bg = jnp.asarray([0.3, 0.3, 0.3])
    out = composite(sigma, rgb, lengths, valid, t_mid, bg)
    np.testing.assert_array_equal(np.asarray(out.rgb)[0], np.asarray(bg))
    clean = composite(jnp.asarray([[2.0, 1.0]]), jnp.asarray([[[0.5] * 3, [0.25] * 3]]),
                      jnp.asarray([[1.0, 0.5]]), jnp.ones((1, 2), bool), jnp.asarray([[1.0, 3.0]]), bg)
    np.testing.assert_allclose(np.asarray(out.rgb)[1], np.asarray(clean.rgb)[0], rtol=1e-6)
    np.testing.assert_allclose(float(out.depth[1]), float(clean.depth[0]), rtol=1e-6)
    grads = jax.grad(lambda s, c, ln: jnp.sum(composite(s, c, ln, valid, t_mid, bg).rgb), argnums=(0, 1, 2))(
        sigma, rgb, lengths)
    for g in grads:
        assert np.all(np.isfinite(np.asarray(g)))


def test_zero_length_slot_changes_nothing():
    sigma, rgb, lengths, valid, t_mid, bg, _ = _random_rays(2, r=3, m=6)
    sigma, rgb, lengths, valid, t_mid, bg = sigma[:1], rgb[:1], lengths[:1], valid[:1], t_mid[:1], bg[:1]
    valid[:] = True
    with_zero = lengths.copy()
    with_zero[0, 3] = 0.0
    a = composite(*_jnp32(sigma, rgb, with_zero, valid, t_mid, bg))
    drop = np.delete(np.arange(6), 3)
    b = composite(*_jnp32(sigma[:, drop], rgb[:, drop], lengths[:, drop], valid[:, drop], t_mid[:, drop], bg))
    assert float(a.weights[0, 3]) == 0.0
    np.testing.assert_allclose(np.asarray(a.rgb), np.asarray(b.rgb), rtol=1e-6, atol=1e-7)


def test_split_segment_equals_whole_no_double_counting():
    """Each slot counts once: a segment cut into two contiguous halves with the same density and
    colour composites like the whole (Beer-Lambert is multiplicative over the cut)."""
    bg = jnp.asarray([0.0, 0.0, 1.0])
    whole = composite(jnp.asarray([[0.3, 1.7]]), jnp.asarray([[[1.0, 0, 0], [0, 1.0, 0]]]),
                      jnp.asarray([[2.0, 1.0]]), jnp.ones((1, 2), bool), jnp.asarray([[1.0, 3.5]]), bg)
    split = composite(jnp.asarray([[0.3, 0.3, 1.7]]), jnp.asarray([[[1.0, 0, 0], [1.0, 0, 0], [0, 1.0, 0]]]),
                      jnp.asarray([[1.0, 1.0, 1.0]]), jnp.ones((1, 3), bool), jnp.asarray([[0.5, 1.5, 3.5]]), bg)
    np.testing.assert_allclose(np.asarray(split.rgb), np.asarray(whole.rgb), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(split.opacity), np.asarray(whole.opacity), rtol=1e-6)
    # (the depth map is not split-invariant: it reports each slot at its own t_mid)


def _clip_loop(t_lo, t_hi, valid):
    lo = t_lo.copy()
    for i in range(t_lo.shape[0]):
        reach = -np.inf
        for j in range(t_lo.shape[1]):
            if valid[i, j]:
                lo[i, j] = min(max(t_lo[i, j], reach), t_hi[i, j])
                reach = max(reach, t_hi[i, j])
    return lo


def test_clip_overlaps_counts_every_stretch_once():
    t_lo = np.array([[0.0, 1.0, 1.5, 5.0, 5.5], [0.0, 0.5, 2.0, 2.2, 9.0]])
    t_hi = np.array([[2.0, 3.0, 2.5, 6.0, 5.8], [1.0, 4.0, 3.0, 2.4, 9.5]])
    valid = np.array([[True, True, True, True, True], [True, False, True, True, True]])
    lo, hi = clip_overlaps(jnp.asarray(t_lo), jnp.asarray(t_hi), jnp.asarray(valid))
    np.testing.assert_allclose(np.asarray(lo), _clip_loop(t_lo, t_hi, valid), rtol=1e-7)
    np.testing.assert_allclose(np.asarray(hi), t_hi, rtol=1e-7)
    length = np.asarray(hi - lo)
    assert np.all(length >= 0)
    np.testing.assert_allclose(length[0], [2.0, 1.0, 0.0, 1.0, 0.0], atol=1e-6)  # union [0,3] u [5,6]
    np.testing.assert_allclose(length[1][valid[1]], [1.0, 1.0, 0.0, 0.5], atol=1e-6)  # invalid slot trims nothing
    # overlapping padded boxes of equal density composite like their union
    sigma = np.full((1, 5), 0.8)
    rgb = np.ones((1, 5, 3))
    over = composite(*_jnp32(sigma, rgb, length[:1], valid[:1], t_lo[:1], np.zeros(3)))
    union = composite(*_jnp32(sigma[:, :2], rgb[:, :2], np.array([[3.0, 1.0]]), np.ones((1, 2), bool),
                              np.array([[0.0, 5.0]]), np.zeros(3)))
    np.testing.assert_allclose(np.asarray(over.opacity), np.asarray(union.opacity), rtol=1e-6)


def test_background_shapes_and_float64():
    sigma, rgb, lengths, valid, t_mid, bg, _ = _random_rays(3)
    a = composite(*_jnp32(sigma, rgb, lengths, valid, t_mid, bg[0]))
    b = composite(*_jnp32(sigma, rgb, lengths, valid, t_mid, np.tile(bg[0], (len(sigma), 1))))
    np.testing.assert_array_equal(np.asarray(a.rgb), np.asarray(b.rgb))
    with jax.enable_x64(True):
        out = composite(jnp.asarray(sigma), jnp.asarray(rgb), jnp.asarray(lengths), jnp.asarray(valid),
                        jnp.asarray(t_mid), jnp.asarray(bg))
        assert out.rgb.dtype == jnp.float64
        want = composite_loop(sigma, rgb, lengths, valid, t_mid, bg)
        np.testing.assert_allclose(np.asarray(out.rgb), want[0], rtol=1e-12)


def test_no_recompilation():
    traces = []

    @jax.jit
    def run(*a):
        traces.append(1)
        return composite(*a).rgb

    for seed in range(3):
        run(*_jnp32(*_random_rays(seed)[:6])).block_until_ready()
    assert len(traces) == 1 and run._cache_size() == 1


def test_depth_gradient_finite_for_vanishing_density():
    """Opacity ~1e-30: depth is 0 and its gradient finite (opacity^2 underflows in float32)."""
    t_mid = jnp.array([[2.0, 3.0]])

    def depth(log_sigma):
        sigma = jnp.exp(log_sigma) * jnp.ones((1, 2))
        out = composite(sigma, jnp.zeros((1, 2, 3)), jnp.ones((1, 2)), jnp.ones((1, 2), bool), t_mid,
                        jnp.zeros(3))
        return out.depth[0]

    for log_sigma in (-69.0, -45.0, -20.0, 0.0):  # sigma from 1e-30 to 1
        g = jax.grad(depth)(jnp.float32(log_sigma))
        assert np.isfinite(float(g)), log_sigma
    assert float(depth(jnp.float32(-69.0))) == 0.0
    assert 2.0 < float(depth(jnp.float32(0.0))) < 3.0

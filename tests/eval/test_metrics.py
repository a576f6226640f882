"""PSNR and SSIM against obvious references: known values, skimage's SSIM, float64 numpy loops."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from skimage.metrics import structural_similarity

from ne_jax.eval.metrics import MSE_FLOOR, gaussian_window, psnr, ssim

_psnr_grad = jax.jit(jax.grad(psnr))  # one compilation per shape for all gradient cases
_ssim_grad = jax.jit(jax.grad(ssim))
SKIMAGE = {"channel_axis": -1, "data_range": 1.0, "gaussian_weights": True, "sigma": 1.5,
           "use_sample_covariance": False}


def _random_pair(shape, noise, seed=0):
    rng = np.random.default_rng(seed)
    a = rng.uniform(size=shape)
    return a, np.clip(a + noise * rng.normal(size=shape), 0.0, 1.0)


def _smooth_pair(shape):
    h, w = shape[:2]
    yy, xx = np.mgrid[:h, :w] / max(h, w)
    a = np.stack([0.5 + 0.4 * np.sin(3 * xx + c) * np.cos(2 * yy + 0.5 * c) for c in range(3)], -1)
    b = np.clip(0.9 * a + 0.05 * np.sin(9 * xx + 4 * yy)[..., None] + 0.08, 0.0, 1.0)
    return a, b


def _ssim_reference(a, b, max_val=1.0):
    """Float64 SSIM, straight from the definition: a 2-D Gaussian window at every valid position."""
    win = np.outer(gaussian_window(), gaussian_window())
    n = win.shape[0]
    h, w, c = a.shape
    c1, c2 = (0.01 * max_val) ** 2, (0.03 * max_val) ** 2
    vals = []
    for ch in range(c):
        for i in range(h - n + 1):
            for j in range(w - n + 1):
                x, y = a[i : i + n, j : j + n, ch], b[i : i + n, j : j + n, ch]
                mx, my = np.sum(win * x), np.sum(win * y)
                vx, vy = np.sum(win * (x - mx) ** 2), np.sum(win * (y - my) ** 2)
                vxy = np.sum(win * (x - mx) * (y - my))
                vals.append((2 * mx * my + c1) * (2 * vxy + c2) / ((mx**2 + my**2 + c1) * (vx + vy + c2)))
    return float(np.mean(vals))


# ----------------------------------------------------------------------------------------- PSNR


@pytest.mark.parametrize("mse", [1e-2, 1e-3, 0.25])
def test_psnr_known_values(mse):
    target = np.zeros((4, 5, 3), np.float32)
    pred = np.full_like(target, np.sqrt(mse))
    np.testing.assert_allclose(float(psnr(pred, target)), -10 * np.log10(mse), atol=1e-4)
    np.testing.assert_allclose(float(psnr(2 * pred, 2 * target, max_val=2.0)), -10 * np.log10(mse), atol=1e-4)


def test_psnr_identical_images_are_finite_and_batched():
    a, b = _random_pair((2, 3, 8, 8, 3), 0.1)
    same = psnr(a, a)
    assert same.shape == (2, 3)
    np.testing.assert_allclose(np.asarray(same), -10 * np.log10(MSE_FLOOR), atol=1e-4)  # 100 dB
    per = np.asarray(psnr(a, b))
    ref = -10 * np.log10(np.mean((a - b) ** 2, axis=(-3, -2, -1)))
    np.testing.assert_allclose(per, ref, atol=1e-4)
    assert per.dtype == np.float32


def test_psnr_gradient_finite():
    a, b = _random_pair((8, 8, 3), 0.1)
    for target in (b, a):  # different, identical (the floored MSE)
        g = _psnr_grad(jnp.asarray(a, jnp.float32), target)
        assert np.all(np.isfinite(np.asarray(g)))


# ----------------------------------------------------------------------------------------- SSIM


@pytest.mark.parametrize("shape", [(11, 11, 3), (24, 37, 3), (48, 48, 3)])
@pytest.mark.parametrize("kind", ["random", "smooth"])
def test_ssim_matches_skimage(shape, kind):
    a, b = _random_pair(shape, 0.1) if kind == "random" else _smooth_pair(shape)
    expected = structural_similarity(a, b, **SKIMAGE)
    got = float(ssim(a.astype(np.float32), b.astype(np.float32)))
    assert abs(got - expected) < 1e-5, (got, expected)


def test_ssim_matches_definition_and_is_batched():
    a, b = _random_pair((2, 14, 13, 3), 0.2, seed=1)
    got = np.asarray(jax.jit(ssim)(a, b))
    assert got.shape == (2,)
    for k in range(2):
        np.testing.assert_allclose(got[k], _ssim_reference(a[k], b[k]), atol=1e-5)


def test_ssim_identical_and_constant_images():
    a, _ = _random_pair((16, 16, 3), 0.1)
    np.testing.assert_allclose(float(ssim(a, a)), 1.0, atol=1e-6)
    c = np.full((16, 16, 3), 0.3)
    np.testing.assert_allclose(float(ssim(c, c)), 1.0, atol=1e-6)
    d = np.full((16, 16, 3), 0.6)
    expected = structural_similarity(c, d, **SKIMAGE)
    np.testing.assert_allclose(float(ssim(c, d)), expected, atol=1e-5)


@pytest.mark.parametrize("case", ["different", "identical", "constant", "constant_vs_random"])
def test_ssim_gradient_finite(case):
    a, b = _random_pair((16, 16, 3), 0.1)
    c = np.full((16, 16, 3), 0.5)
    pred, target = {"different": (a, b), "identical": (a, a), "constant": (c, c), "constant_vs_random": (c, a)}[case]
    g = np.asarray(_ssim_grad(jnp.asarray(pred, jnp.float32), jnp.asarray(target, jnp.float32)))
    assert np.all(np.isfinite(g))
    if case in ("identical", "constant"):  # a maximum: the gradient vanishes
        np.testing.assert_allclose(g, 0.0, atol=1e-5)


# ---------------------------------------------------------------------------------------- errors


@pytest.mark.parametrize("metric", [psnr, ssim])
def test_shape_mismatch_names_both_shapes(metric):
    with pytest.raises(ValueError, match=r"\(16, 16, 3\).*\(16, 15, 3\)"):
        metric(np.zeros((16, 16, 3)), np.zeros((16, 15, 3)))


@pytest.mark.parametrize("metric", [psnr, ssim])
def test_rgba_rejected(metric):
    with pytest.raises(ValueError, match=r"\[\.\.\., H, W, 3\].*\(16, 16, 4\)"):
        metric(np.zeros((16, 16, 4)), np.zeros((16, 16, 4)))


def test_ssim_image_smaller_than_window():
    with pytest.raises(ValueError, match=r"12x10 \(WxH\).*11x11 window"):
        ssim(np.zeros((10, 12, 3)), np.zeros((10, 12, 3)))

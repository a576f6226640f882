"""Downscaling, compositing and background parsing."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ne_jax.data.nerf_synthetic import DataError, composite, downscale_rgba, parse_background


def _reference_downscale(img, f):
    """Slow loops in float64: premultiplied block mean, then un-premultiplied."""
    h, w = img.shape[0] // f, img.shape[1] // f
    out = np.zeros((h, w, 4))
    for j in range(h):
        for i in range(w):
            block = img[j * f : (j + 1) * f, i * f : (i + 1) * f].reshape(-1, 4).astype(np.float64)
            a = block[:, 3].sum()
            out[j, i, 3] = a / (f * f)
            out[j, i, :3] = (block[:, :3] * block[:, 3:]).sum(0) / a if a > 0 else block[:, :3].mean(0)
    return out


@pytest.mark.parametrize("factor", [1, 2, 3, 4])
def test_constant_image_stays_constant(factor):
    img = np.broadcast_to(np.array([0.2, 0.6, 0.9, 0.5], np.float32), (2, 12, 12, 4))
    out = downscale_rgba(img, factor)
    assert out.shape == (2, 12 // factor, 12 // factor, 4) and out.dtype == np.float32
    np.testing.assert_allclose(out, np.broadcast_to(img[0, 0, 0], out.shape), atol=1e-6)


def test_color_is_alpha_weighted_no_dark_fringe():
    img = np.zeros((2, 2, 4), np.float32)
    img[0, 0] = [1.0, 0.0, 0.0, 1.0]  # one opaque red pixel
    img[0, 1] = [0.0, 0.0, 1.0, 0.0]  # transparent pixels carry arbitrary colour
    out = downscale_rgba(img, 2)
    np.testing.assert_allclose(out[0, 0], [1.0, 0.0, 0.0, 0.25], atol=1e-7)
    # half-transparent mix: (0.5 * red + 1.0 * green) / 1.5
    img[1, 1] = [0.0, 1.0, 0.0, 0.5]
    out = downscale_rgba(img, 2)
    np.testing.assert_allclose(out[0, 0], [1 / 1.5, 0.5 / 1.5, 0.0, 0.375], atol=1e-6)
    # fully transparent block: plain colour mean, alpha 0
    empty = np.zeros((2, 2, 4), np.float32)
    empty[..., 1] = 0.4
    np.testing.assert_allclose(downscale_rgba(empty, 2)[0, 0], [0.0, 0.4, 0.0, 0.0], atol=1e-7)


@pytest.mark.parametrize("shape, factor", [((7, 9), 2), ((10, 5), 3), ((8, 8), 4)])
def test_downscale_matches_loop_reference_and_crops(shape, factor):
    rng = np.random.default_rng(factor)
    img = rng.random((*shape, 4)).astype(np.float32)
    img[0, 0, 3] = 0.0
    out = downscale_rgba(img, factor)
    assert out.shape == (shape[0] // factor, shape[1] // factor, 4)
    np.testing.assert_allclose(out, _reference_downscale(img, factor), atol=1e-6)


def test_downscale_rejects_non_rgba():
    with pytest.raises(DataError, match="RGBA"):
        downscale_rgba(np.zeros((4, 4, 3), np.float32), 2)


def test_composite_black_white_custom():
    rgba = np.array([[0.2, 0.4, 0.6, 1.0], [0.2, 0.4, 0.6, 0.25], [0.9, 0.9, 0.9, 0.0]], np.float32)
    np.testing.assert_allclose(composite(rgba, "black"), [[0.2, 0.4, 0.6], [0.05, 0.1, 0.15], [0, 0, 0]], atol=1e-7)
    np.testing.assert_allclose(
        composite(rgba, "white"), [[0.2, 0.4, 0.6], [0.8, 0.85, 0.9], [1, 1, 1]], atol=1e-7
    )
    bg = (0.0, 0.5, 1.0)
    np.testing.assert_allclose(
        composite(rgba, bg), [[0.2, 0.4, 0.6], [0.05, 0.475, 0.9], [0.0, 0.5, 1.0]], atol=1e-7
    )
    np.testing.assert_allclose(composite(rgba, "0,128,255"), composite(rgba, (0.0, 128 / 255, 1.0)), atol=1e-7)


def test_composite_on_device_and_per_pixel_background():
    rgba = jnp.asarray(np.random.default_rng(0).random((5, 4)), jnp.float32)
    bg = jnp.asarray(np.random.default_rng(1).random((5, 3)), jnp.float32)
    out = jax.jit(composite)(rgba, bg)
    expected = np.asarray(rgba[:, :3] * rgba[:, 3:] + bg * (1 - rgba[:, 3:]))
    np.testing.assert_allclose(np.asarray(out), expected, atol=1e-6)
    assert out.dtype == jnp.float32


@pytest.mark.parametrize(
    "value, expected",
    [
        ("black", [0, 0, 0]),
        ("white", [1, 1, 1]),
        (" White ", [1, 1, 1]),
        ("255,128,0", [1.0, 128 / 255, 0.0]),
        ("1,1,1", [1 / 255] * 3),  # integers are 0-255 levels
        ("1.0, 0.5, 0", [1.0, 0.5, 0.0]),  # any '.' -> fractions
        ((0.25, 0.5, 0.75), [0.25, 0.5, 0.75]),
        ((255, 0, 51), [1.0, 0.0, 0.2]),
        ([0, 0.0, 1], [0.0, 0.0, 1.0]),  # mixed -> fractions
        (np.array([0.1, 0.2, 0.3]), [0.1, 0.2, 0.3]),
        (np.array([10, 20, 30]), [10 / 255, 20 / 255, 30 / 255]),
    ],
)
def test_parse_background_accepts(value, expected):
    out = parse_background(value)
    assert out.shape == (3,) and out.dtype == np.float32
    np.testing.assert_allclose(out, expected, atol=1e-7)


@pytest.mark.parametrize(
    "value, match",
    [
        ("gray", "found 1 component"),
        ("1,2", "found 2 component"),
        ("a,b,c", "three numbers"),
        ("256,0,0", "0-255"),
        ("-1,0,0", "0-255"),
        ("1.5,0,0", r"\[0, 1\]"),
        ((1.0, 0.0), "3 numbers"),
        ((0.1, float("nan"), 0.2), r"\[0, 1\]"),
        ((True, 0, 0), "3 numbers"),
        (("0", "0", "0"), "3 numbers"),
        (None, "expected 'black'"),
        (0.5, "expected 'black'"),
        (np.zeros((2, 3)), "shape"),
    ],
)
def test_parse_background_rejects(value, match):
    with pytest.raises(DataError, match=match):
        parse_background(value)

"""Rays of a loaded split against a pinhole camera computed by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ne_jax.data.nerf_synthetic import load_split, split_rays, view_rays, write_split

# W = 4, H = 2, camera_angle_x = pi/2  ->  f = 0.5 * 4 / tan(pi/4) = 2, cx = 2, cy = 1.
W, H, ANGLE = 4, 2, math.pi / 2
IDENTITY_AT_Z4 = np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4], [0, 0, 0, 1]], np.float32)
# Rotation by +90 degrees about world y (camera -z -> world -x), camera at (1, 2, 3).
ROT_Y90 = np.array([[0, 0, 1, 1], [0, 1, 0, 2], [-1, 0, 0, 3], [0, 0, 0, 1]], np.float32)


@pytest.fixture
def split(tmp_path):
    images = np.zeros((2, H, W, 4), np.float32)
    images[..., 0] = np.arange(H * W).reshape(H, W) / 10.0  # red encodes the pixel index
    images[1, ..., 1] = 1.0  # green marks view 1
    images[..., 3] = 1.0
    images[0, 1, 3, 3] = 0.2
    write_split(tmp_path, "train", images, np.stack([IDENTITY_AT_Z4, ROT_Y90]), ANGLE, bit_depth=16)
    return load_split(tmp_path, "train")


def test_hand_computed_directions(split):
    rays = split_rays(split, near=2.0, far=6.0)
    assert rays.origin.shape == (2 * H * W, 3) and rays.target.shape == (2 * H * W, 4)
    s = math.sqrt(1.625)
    # view 0, pixel (i=0, j=0): centre (0.5, 0.5) -> x = (0.5 - 2)/2 = -0.75, y = -(0.5 - 1)/2 = 0.25
    np.testing.assert_allclose(rays.direction[0], [-0.75 / s, 0.25 / s, -1 / s], atol=1e-6)
    np.testing.assert_allclose(rays.origin[0], [0, 0, 4], atol=0)
    # view 0, pixel (i=3, j=1): centre (3.5, 1.5) -> x = 0.75, y = -0.25; index j * W + i = 7
    np.testing.assert_allclose(rays.direction[7], [0.75 / s, -0.25 / s, -1 / s], atol=1e-6)
    # view 0, pixel (i=2, j=0): centre (2.5, 0.5) -> x = 0.25, y = 0.25
    s2 = math.sqrt(1.125)
    np.testing.assert_allclose(rays.direction[2], [0.25 / s2, 0.25 / s2, -1 / s2], atol=1e-6)
    # view 1 (rotated): R @ (x, y, -1) = (-1, y, -x); pixel (0, 0) is ray 8
    np.testing.assert_allclose(rays.direction[8], [-1 / s, 0.25 / s, 0.75 / s], atol=1e-6)
    np.testing.assert_allclose(rays.origin[8], [1, 2, 3], atol=0)
    np.testing.assert_allclose(rays.direction[15], [-1 / s, -0.25 / s, -0.75 / s], atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(rays.direction, axis=-1), 1.0, atol=1e-6)
    np.testing.assert_array_equal(rays.near, 2.0)
    np.testing.assert_array_equal(rays.far, 6.0)


def test_target_order_is_view_major_row_major(split):
    rays = split_rays(split, 2.0, 6.0)
    t = np.asarray(rays.target)
    np.testing.assert_allclose(t[:8, 0], np.arange(8) / 10.0, atol=1e-4)
    np.testing.assert_allclose(t[8:, 0], np.arange(8) / 10.0, atol=1e-4)
    np.testing.assert_array_equal(t[:8, 1], 0.0)
    np.testing.assert_array_equal(t[8:, 1], 1.0)
    assert t[7, 3] == pytest.approx(0.2, abs=1e-4)


def test_view_rays_match_split_rays(split):
    all_rays = split_rays(split, 2.0, 6.0, background="white")
    one = view_rays(split, 1, 2.0, 6.0, background="white")
    for a, b in zip((one.origin, one.direction, one.target), (all_rays.origin, all_rays.direction, all_rays.target)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b[H * W :]))


def test_background_target_is_composited_and_opaque(split):
    straight = np.asarray(split_rays(split, 2.0, 6.0).target)
    on_white = np.asarray(split_rays(split, 2.0, 6.0, background="white").target)
    on_black = np.asarray(split_rays(split, 2.0, 6.0, background=(0.0, 0.0, 0.0)).target)
    np.testing.assert_array_equal(on_white[:, 3], 1.0)
    a = straight[7, 3]
    np.testing.assert_allclose(on_white[7, :3], straight[7, :3] * a + (1 - a), atol=1e-6)
    np.testing.assert_allclose(on_black[7, :3], straight[7, :3] * a, atol=1e-6)
    # opaque pixels are unchanged by the background
    np.testing.assert_allclose(on_white[0, :3], straight[0, :3], atol=1e-6)


def test_downscaled_camera_looks_through_block_centers(tmp_path):
    rng = np.random.default_rng(0)
    c2w = ROT_Y90[None]
    write_split(tmp_path, "train", rng.random((1, 6, 8, 4)), c2w, 0.9)
    full = load_split(tmp_path, "train")
    half = load_split(tmp_path, "train", downscale=2)
    assert (half.width, half.height, half.downscale) == (4, 3, 2)
    assert (half.fx, half.cx, half.cy) == pytest.approx((full.fx / 2, full.cx / 2, full.cy / 2))
    # pixel (i, j) of the half image is centred on the corner (2i + 1, 2j + 1) of the full one
    from ne_jax.data.rays import pixel_rays

    small = view_rays(half, 0, 1.0, 5.0)
    corners = np.array([[2 * i + 1, 2 * j + 1] for j in range(3) for i in range(4)], np.float32)
    big = pixel_rays(full.camera(0), corners, 1.0, 5.0)
    np.testing.assert_allclose(small.direction, big.direction, atol=1e-6)


def test_subpixel_grid_is_centred_in_each_pixel():
    from ne_jax.data.rays import pixel_centers, subpixel_offsets

    np.testing.assert_array_equal(subpixel_offsets(1), [[0.5, 0.5]])
    np.testing.assert_array_equal(subpixel_offsets(2), [[0.25, 0.25], [0.75, 0.25], [0.25, 0.75], [0.75, 0.75]])
    grid = pixel_centers(W, H, 3).reshape(H * W, 9, 2)
    np.testing.assert_allclose(grid.mean(1), pixel_centers(W, H), atol=1e-6)  # each pixel's 9 rays, consecutive
    assert (np.floor(grid) == np.floor(pixel_centers(W, H))[:, None]).all()  # inside their own pixel
    with pytest.raises(ValueError, match="n >= 1"):
        subpixel_offsets(0)

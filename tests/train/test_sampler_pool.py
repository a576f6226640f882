"""build_pool's targets and what it holds on the host while it builds: the targets are composited at
the pool's pixels only, exactly as compositing the whole split would give them."""

from __future__ import annotations

import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from ne_jax.data.nerf_synthetic import SceneSplit, composite
from ne_jax.train import SamplerConfig, band_mask, build_pool


def _split(n: int, size: int, seed: int = 0) -> SceneSplit:
    """``n`` views of ``size`` px: a random soft-edged disc on transparent black, random colours."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:size, :size] / size
    images = np.zeros((n, size, size, 4), np.float32)
    for v in range(n):
        r = np.hypot(xx - rng.uniform(0.3, 0.7), yy - rng.uniform(0.3, 0.7))
        images[v, ..., 3] = np.clip((0.15 - r) * size / 2, 0, 1)
        images[v, ..., :3] = rng.uniform(size=(size, size, 3))
    return SceneSplit(name="toy", images=images, c2w=np.tile(np.eye(4, dtype=np.float32), (n, 1, 1)),
                      fx=float(size), fy=float(size), cx=size / 2, cy=size / 2, camera_angle_x=1.0,
                      file_paths=tuple(str(i) for i in range(n)), image_paths=tuple(Path(str(i)) for i in range(n)))


@pytest.mark.parametrize("background", ["white", "black", (0.2, 0.5, 0.9)])
@pytest.mark.parametrize("band_width", [0, 2])
def test_targets_are_the_composited_split_at_the_pools_pixels(background, band_width):
    split = _split(3, 24)
    pool = build_pool(SamplerConfig(batch_size=64, band_width=band_width), split, background)
    rgb = np.asarray(composite(split.images, background), np.float32).reshape(-1, 3)  # the slow, obvious way
    fg = np.flatnonzero((split.images[..., 3] > 0).ravel())
    np.testing.assert_array_equal(np.asarray(pool.fg_index), fg)
    np.testing.assert_array_equal(np.asarray(pool.fg_target), rgb[fg])
    band = np.flatnonzero(band_mask(split.images[..., 3], band_width).ravel())
    if band_width:
        np.testing.assert_array_equal(np.asarray(pool.band_index), band)
        np.testing.assert_array_equal(np.asarray(pool.band_target), rgb[band])
    else:  # the placeholder row, never drawn
        assert pool.num_band == 0 and np.asarray(pool.band_index).tolist() == [0]
        np.testing.assert_array_equal(np.asarray(pool.band_target), rgb[:1])


def test_building_holds_the_pools_pixels_not_the_split_again():
    split = _split(4, 128)  # the object covers about 7% of each view
    build_pool(SamplerConfig(batch_size=256), _split(1, 8), "white")  # JAX started, the pool's transfers warm
    tracemalloc.start()
    try:
        build_pool(SamplerConfig(batch_size=256), split, "white")
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    # compositing every pixel would hold 3/4 of the images again (in float64: 1.5x); the masks (a
    # byte per pixel each, a few at a time: 1/16 of the images each), the indices and the pool's
    # targets are a fraction of that
    assert peak < 0.6 * split.images.nbytes, (peak, split.images.nbytes)

"""Shared helpers for the data tests: random rigid cameras and a tiny scene writer."""

from __future__ import annotations

import numpy as np
import pytest

from ne_jax.data.nerf_synthetic import write_split


def _random_c2w(rng: np.random.Generator, n: int) -> np.ndarray:
    """``[n, 4, 4]`` float32 random rigid camera-to-world matrices."""
    out = np.zeros((n, 4, 4), np.float64)
    for i in range(n):
        q, r = np.linalg.qr(rng.normal(size=(3, 3)))
        q = q * np.sign(np.diag(r))
        if np.linalg.det(q) < 0:
            q[:, 0] = -q[:, 0]
        out[i, :3, :3] = q
        out[i, :3, 3] = rng.normal(size=3) * 3
        out[i, 3, 3] = 1.0
    return out.astype(np.float32)


def _random_rgba(rng: np.random.Generator, n: int, h: int, w: int) -> np.ndarray:
    """``[n, h, w, 4]`` float32 in [0, 1] with some fully transparent and opaque pixels."""
    x = rng.random((n, h, w, 4)).astype(np.float32)
    x[:, 0, 0, 3] = 0.0
    x[:, -1, -1, 3] = 1.0
    return x


@pytest.fixture
def random_c2w():
    """``random_c2w(rng, n) -> [n, 4, 4]`` rigid float32 matrices."""
    return _random_c2w


@pytest.fixture
def random_rgba():
    """``random_rgba(rng, n, h, w) -> [n, h, w, 4]`` float32 straight RGBA."""
    return _random_rgba


@pytest.fixture
def make_scene(tmp_path):
    """Factory: write a small scene and return ``(scene_dir, {split: (images, c2ws)})``."""

    def make(splits=("train",), n=3, h=4, w=6, bit_depth=8, angle=0.8, seed=0):
        rng = np.random.default_rng(seed)
        scene = tmp_path / "scene"
        data = {}
        for split in splits:
            images, c2ws = _random_rgba(rng, n, h, w), _random_c2w(rng, n)
            write_split(scene, split, images, c2ws, angle, bit_depth=bit_depth)
            data[split] = (images, c2ws)
        return scene, data

    return make

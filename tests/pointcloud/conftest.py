"""Shared fixtures of the point-cloud tests: an analytic sphere seen by cameras all around it."""

from __future__ import annotations

import numpy as np
import pytest

from ne_jax.data.cameras import look_at
from ne_jax.pointcloud.init import Views

RADIUS = 0.6
"""Radius of the test sphere (centred at the origin)."""


def fibonacci_sphere(n: int, radius: float = 1.0) -> np.ndarray:
    """``[n, 3]`` nearly uniform points on a sphere of ``radius`` centred at the origin."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = np.pi * (1.0 + 5**0.5) * i
    r = np.sqrt(1.0 - z**2)
    return radius * np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)


def _subpixel_rays(c2w: np.ndarray, size: int, focal: float, ss: int) -> tuple[np.ndarray, np.ndarray]:
    """Camera centre ``[3]`` and unit directions ``[size * size * ss * ss, 3]`` through an ``ss x ss``
    sub-pixel grid of every pixel (row-major, samples of a pixel contiguous)."""
    off = (np.arange(ss) + 0.5) / ss
    j, i, sj, si = np.meshgrid(np.arange(size), np.arange(size), off, off, indexing="ij")
    d = np.stack([(i + si - size / 2) / focal, -(j + sj - size / 2) / focal, -np.ones_like(i, float)], -1)
    d = d.reshape(-1, 3) @ c2w[:3, :3].T
    return c2w[:3, 3], d / np.linalg.norm(d, axis=1, keepdims=True)


def sphere_alpha(c2w: np.ndarray, size: int, focal: float, radius: float, ss: int = 4) -> np.ndarray:
    """``[size, size]`` analytic alpha of a sphere at the origin seen by ``c2w`` (OpenGL), pixel
    centres at ``i + 0.5``, ``ss x ss`` samples per pixel."""
    o, d = _subpixel_rays(c2w, size, focal, ss)
    t = -(d @ o)  # closest approach along each ray
    miss = np.linalg.norm(o + t[:, None] * d, axis=1)
    hit = (miss < radius) & (t > 0)
    return hit.reshape(size, size, ss * ss).mean(-1).astype(np.float32)


def sphere_rgba(c2w: np.ndarray, size: int, focal: float, radius: float, ss: int = 2) -> np.ndarray:
    """``[size, size, 4]`` straight RGBA of the sphere with the colour ``0.5 + 0.4 sin(6 p)`` of
    each surface point ``p`` (view-independent, so photo-consistent), black background."""
    o, d = _subpixel_rays(c2w, size, focal, ss)
    b = d @ o
    disc = b**2 - (o @ o - radius**2)
    hit = disc > 0
    t = -b - np.sqrt(np.maximum(disc, 0.0))
    color = 0.5 + 0.4 * np.sin(6.0 * (o + t[:, None] * d)) * hit[:, None]
    hit = hit.reshape(size, size, ss * ss)
    color = color.reshape(size, size, ss * ss, 3)
    rgb = (color * hit[..., None]).sum(2) / np.maximum(hit.sum(-1), 1)[..., None]
    return np.concatenate([rgb, hit.mean(-1)[..., None]], -1).astype(np.float32)


def sphere_views(n_views: int = 40, size: int = 96, radius: float = RADIUS, distance: float = 4.0) -> Views:
    """``n_views`` cameras on a Fibonacci sphere of ``distance`` looking at the origin, with the
    sphere's analytic masks (field of view about 40 degrees)."""
    focal = 0.5 * size / np.tan(0.5 * 0.6911112070083618)
    eyes = fibonacci_sphere(n_views, distance)
    c2w = np.stack([look_at(e) for e in eyes])
    alpha = np.stack([sphere_alpha(c, size, focal, radius) for c in c2w])
    return Views.create(alpha, c2w, focal, focal, size / 2, size / 2)


@pytest.fixture(scope="session")
def sphere():
    """``Views`` of the analytic sphere of radius :data:`RADIUS` (40 views, 96 x 96)."""
    return sphere_views()

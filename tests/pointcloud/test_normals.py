"""Normals: Open3D estimation oriented towards the cameras; degenerate clouds."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from ne_jax.pointcloud.normals import (
    ORIENTATIONS,
    NormalConfig,
    estimate_normals,
    mean_spacing,
    orient_normals,
    unique_rows,
)

from .conftest import RADIUS, fibonacci_sphere

ORIENTED = [o for o in ORIENTATIONS if o != "none"]


@pytest.fixture(scope="module")
def sphere_points():
    rng = np.random.default_rng(0)
    pts = fibonacci_sphere(4000, RADIUS)
    return pts + rng.normal(scale=0.002, size=pts.shape)  # a little noise, like a carved cloud


@pytest.mark.parametrize("orient", ORIENTED)
def test_sphere_normals_point_outward(sphere, sphere_points, orient):
    n = estimate_normals(NormalConfig(orient=orient), sphere_points, sphere)
    assert n.shape == sphere_points.shape and n.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-5)
    outward = sphere_points / np.linalg.norm(sphere_points, axis=1, keepdims=True)
    cos = np.sum(n * outward, axis=1)
    assert (cos > 0.9).mean() > 0.95


def test_unoriented_normals_have_both_signs(sphere_points):
    # the orientation step is what makes the test above pass: Open3D's raw signs are mixed
    n = estimate_normals(NormalConfig(orient="none"), sphere_points)
    cos = np.sum(n * sphere_points, axis=1)
    assert 0.05 < (cos > 0).mean() < 0.95
    assert (np.abs(cos) / np.linalg.norm(sphere_points, axis=1) > 0.9).mean() > 0.95


def test_flipped_input_is_reoriented(sphere, sphere_points):
    outward = sphere_points / np.linalg.norm(sphere_points, axis=1, keepdims=True)
    rng = np.random.default_rng(1)
    flips = np.where(rng.random(len(outward)) < 0.5, -1.0, 1.0)[:, None]
    out = orient_normals(NormalConfig(), sphere_points, outward * flips, sphere)
    assert (np.sum(out * outward, axis=1) > 0).mean() > 0.99


def test_thin_plate_sides_face_their_cameras(sphere):
    # Two parallel sheets 4 spacings apart (a thin wall): each side's normals face away from the
    # other side; propagation must not join the two sides.
    g = np.linspace(-0.5, 0.5, 50)
    x, y = np.meshgrid(g, g)
    gap = 4 * (g[1] - g[0])
    top = np.stack([x.ravel(), y.ravel(), np.full(x.size, gap / 2)], 1)
    bottom = top * np.array([1, 1, -1])
    pts = np.concatenate([top, bottom])
    n = estimate_normals(NormalConfig(), pts, sphere)
    assert (n[: len(top), 2] > 0.9).mean() > 0.95
    assert (n[len(top):, 2] < -0.9).mean() > 0.95


DEGENERATE = {
    "one point": np.array([[0.1, 0.2, 0.3]]),
    "two points": np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
    "collinear along z": np.stack([np.zeros(10), np.zeros(10), np.linspace(-0.5, 0.5, 10)], 1),
    "collinear oblique": np.linspace(-0.5, 0.5, 12)[:, None] * np.array([[1.0, 2.0, 3.0]]),
    "duplicates": np.zeros((7, 3)),
    "duplicates of two": np.repeat(np.array([[0.0, 0.0, 0.0], [0.3, 0.1, 0.0]]), 5, axis=0),
    "plane with duplicates": np.concatenate([
        np.stack([np.repeat(np.arange(5), 5), np.tile(np.arange(5), 5), np.zeros(25)], 1) * 0.1,
        np.zeros((5, 3)),
    ]),
}


@pytest.mark.parametrize("orient", ORIENTATIONS)
@pytest.mark.parametrize("name", list(DEGENERATE))
def test_degenerate_clouds_give_finite_unit_normals(sphere, name, orient):
    pts = DEGENERATE[name]
    n = estimate_normals(NormalConfig(orient=orient), pts, sphere)
    assert n.shape == pts.shape
    assert np.isfinite(n).all()
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-5)
    if name.startswith("collinear"):
        axis = pts[-1] - pts[0]
        axis /= np.linalg.norm(axis)
        np.testing.assert_allclose(n @ axis, 0.0, atol=1e-6)  # perpendicular to the line
    if name == "plane with duplicates":
        assert (np.abs(n[:, 2]) > 0.99).all()


def test_empty_cloud(sphere):
    assert estimate_normals(NormalConfig(), np.zeros((0, 3)), sphere).shape == (0, 3)


@pytest.mark.parametrize("n", [0, 1, 2, 7, 500])
def test_unique_rows_is_np_unique(n):
    """The lexsort dedupe gives np.unique(axis=0)'s rows in its order: duplicates, ties in the first
    columns, signed zeros, a grid where every coordinate repeats."""
    rng = np.random.default_rng(n)
    xyz = np.round(rng.normal(size=(n, 3)), 1)
    if n > 5:
        m = len(xyz[1::3])
        xyz[::3][:m] = xyz[1::3]
        xyz[0], xyz[1] = (-0.0, 0.5, 0.5), (0.0, 0.5, 0.5)
    np.testing.assert_array_equal(unique_rows(xyz), np.unique(xyz, axis=0))
    grid = np.stack(np.meshgrid(*[np.arange(3.0)] * 3), -1).reshape(-1, 3)
    np.testing.assert_array_equal(unique_rows(np.concatenate([grid, grid[::-1]])), np.unique(grid, axis=0))


def test_mean_spacing():
    g = np.arange(5) * 0.25
    grid = np.stack(np.meshgrid(g, g, g), -1).reshape(-1, 3)
    assert mean_spacing(grid) == pytest.approx(0.25)
    assert mean_spacing(np.concatenate([grid, grid])) == pytest.approx(0.25)  # duplicates ignored
    assert mean_spacing(np.zeros((3, 3))) == 0.0


def test_errors_name_the_argument(sphere, sphere_points):
    with pytest.raises(ValueError, match=r"xyz: expected shape \[N, 3\]"):
        estimate_normals(NormalConfig(), np.zeros((4, 2)), sphere)
    with pytest.raises(ValueError, match="xyz: expected finite"):
        estimate_normals(NormalConfig(), np.full((4, 3), np.nan), sphere)
    with pytest.raises(ValueError, match="cfg.orient: expected one of"):
        estimate_normals(NormalConfig(orient="up"), sphere_points, sphere)
    with pytest.raises(ValueError, match="cameras: orientation 'visibility' needs cameras, found None"):
        estimate_normals(NormalConfig(), sphere_points)
    with pytest.raises(TypeError, match="needs a Views"):
        estimate_normals(NormalConfig(), sphere_points, sphere.centers)
    # camera centres are enough for the nearest-camera rule
    n = estimate_normals(dataclasses.replace(NormalConfig(), orient="nearest_camera"), sphere_points, sphere.centers)
    assert (np.sum(n * sphere_points, axis=1) > 0).mean() > 0.95

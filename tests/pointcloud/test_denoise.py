"""Denoising between epochs: statistical outlier removal (Open3D) with a floor at a multiple of the
median neighbour distance, so a clean cloud keeps its points round after round."""

import jax
import numpy as np
import pytest

from ne_jax.geometry.points import PointState
from ne_jax.pointcloud.rounds import RoundConfig, denoise_points, mean_neighbor_distance


def _plane_with_hole(n=60, seed=0):
    """A jittered grid on z = 0 with a square hole in the middle: clean, but its points near the
    hole and the border have sparser neighbourhoods."""
    rng = np.random.default_rng(seed)
    u, v = np.meshgrid(np.linspace(-1, 1, n), np.linspace(-1, 1, n))
    xyz = np.stack([u.ravel(), v.ravel(), np.zeros(n * n)], 1)
    xyz[:, :2] += rng.normal(0, 0.004, (n * n, 2))
    return xyz[(np.abs(xyz[:, 0]) > 0.3) | (np.abs(xyz[:, 1]) > 0.3)]


def _state(xyz, capacity=None):
    return PointState.from_numpy(xyz, capacity=capacity or len(xyz) + 8, feature_dim=4, key=jax.random.key(0))


def test_mean_neighbor_distance_matches_brute_force():
    xyz = np.random.default_rng(1).uniform(-1, 1, (150, 3))
    d = np.linalg.norm(xyz[:, None] - xyz[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    expected = np.sort(d, axis=1)[:, :8].mean(1)
    np.testing.assert_allclose(mean_neighbor_distance(xyz, 8), expected, rtol=1e-12)


def test_a_clean_cloud_keeps_every_point_round_after_round():
    points = _state(_plane_with_hole())
    cfg = RoundConfig(outlier_neighbors=16)
    for _ in range(3):
        points, report = denoise_points(cfg, points)
        assert report["denoised"] == 0


def test_without_the_floor_a_clean_cloud_erodes():
    """The statistical rule alone removes good points at the hole and the border every round."""
    points = _state(_plane_with_hole())
    cfg = RoundConfig(outlier_neighbors=16, outlier_min_ratio=0.0)
    removed = []
    for _ in range(3):
        points, report = denoise_points(cfg, points)
        removed.append(report["denoised"])
    assert all(r > 0 for r in removed)


def test_floaters_are_removed_and_the_surface_is_not():
    plane = _plane_with_hole()
    floaters = np.random.default_rng(2).uniform(-1, 1, (15, 3)) * [1, 1, 0] + [0, 0, 0.5]
    floaters[:, 2] += np.random.default_rng(3).uniform(0, 0.5, 15)
    points, report = denoise_points(RoundConfig(outlier_neighbors=16), _state(np.concatenate([plane, floaters])))
    alive = np.asarray(points.alive)
    assert alive[:len(plane)].all() and not alive[len(plane):len(plane) + 15].any()
    assert report["denoised"] == 15


def test_identical_points_and_dead_slots():
    """All points at one place (median distance 0): nothing is an outlier; dead slots stay dead."""
    points = _state(np.zeros((100, 3)), capacity=120)
    out, report = denoise_points(RoundConfig(outlier_neighbors=16), points)
    assert report["denoised"] == 0 and np.asarray(out.alive).sum() == 100


@pytest.mark.parametrize("value", [-1.0, float("nan")])
def test_bad_floor_names_the_field(value):
    with pytest.raises(ValueError, match="outlier_min_ratio"):
        RoundConfig(outlier_min_ratio=value)

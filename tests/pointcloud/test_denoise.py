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


def test_confident_outliers_stay_with_outlier_keep_confidence():
    """A thin ring of 12 points beside the plane is flagged point by point; with
    ``outlier_keep_confidence`` the ring's confident points stay and its unconfident ones and the
    floaters go; without it every one of them goes."""
    plane = _plane_with_hole()
    a = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    ring = np.stack([0.1 * np.cos(a), 0.1 * np.sin(a), np.full(12, 0.8)], 1)
    floaters = np.array([[0.5, 0.5, 0.6], [-0.5, 0.2, 0.7], [0.0, -0.6, 0.9]])
    xyz = np.concatenate([plane, ring, floaters])
    conf_logit = np.zeros(len(xyz) + 8, np.float32)  # 0.5 everywhere
    n = len(plane)
    conf_logit[n:n + 10] = 3.0  # ten ring points rendered with confidence 0.95; two and the floaters not
    points = _state(xyz).replace(conf_logit=jax.numpy.asarray(conf_logit))
    kept, report = denoise_points(RoundConfig(outlier_neighbors=16, outlier_keep_confidence=0.9), points)
    alive = np.asarray(kept.alive)
    assert alive[:n].all() and alive[n:n + 10].all() and not alive[n + 10:len(xyz)].any()
    assert report["denoised"] == 5
    _, plain = denoise_points(RoundConfig(outlier_neighbors=16), points)
    assert plain["denoised"] == 15


def test_identical_points_and_dead_slots():
    """All points at one place (median distance 0): nothing is an outlier; dead slots stay dead."""
    points = _state(np.zeros((100, 3)), capacity=120)
    out, report = denoise_points(RoundConfig(outlier_neighbors=16), points)
    assert report["denoised"] == 0 and np.asarray(out.alive).sum() == 100


@pytest.mark.parametrize("value", [-1.0, float("nan")])
def test_bad_floor_names_the_field(value):
    with pytest.raises(ValueError, match="outlier_min_ratio"):
        RoundConfig(outlier_min_ratio=value)
    with pytest.raises(ValueError, match="outlier_keep_confidence"):
        RoundConfig(outlier_keep_confidence=value)

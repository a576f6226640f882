"""Chamfer distance and normal agreement against hand-computed values."""

from __future__ import annotations

import numpy as np
import pytest

from ne_jax.pointcloud.metrics import chamfer, normal_agreement


def _grid(n=6, step=1.0):
    g = np.arange(n) * step
    return np.stack(np.meshgrid(g, g, g), -1).reshape(-1, 3)


def test_chamfer_of_a_cloud_with_itself_is_zero():
    pts = np.random.default_rng(0).normal(size=(500, 3))
    ch = chamfer(pts, pts)
    assert ch.accuracy_mean == ch.accuracy_median == ch.completeness_mean == ch.completeness_median == 0.0
    assert ch.mean == 0.0


def test_chamfer_of_a_shifted_copy_is_the_shift():
    pts = _grid()
    shift = np.array([0.1, -0.2, 0.05])  # less than half the spacing: each point's nearest is its copy
    ch = chamfer(pts + shift, pts)
    for v in (ch.accuracy_mean, ch.accuracy_median, ch.completeness_mean, ch.completeness_median, ch.mean):
        assert v == pytest.approx(np.linalg.norm(shift), rel=1e-12)


def test_chamfer_is_asymmetric_by_direction():
    ref = _grid(n=4)
    sub = ref[:1]  # one point: accurate (on the reference) but very incomplete
    ch = chamfer(sub, ref)
    assert ch.accuracy_mean == 0.0
    expected = np.linalg.norm(ref - ref[0], axis=1)
    assert ch.completeness_mean == pytest.approx(expected.mean())
    assert ch.completeness_median == pytest.approx(np.median(expected))
    assert ch.as_dict()["mean"] == pytest.approx(0.5 * expected.mean())


def test_normal_agreement():
    pts = _grid(n=3)
    rng = np.random.default_rng(0)
    n = rng.normal(size=pts.shape)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    same = normal_agreement(pts, n, pts, n)
    assert same.abs_cos == pytest.approx(1.0) and same.cos == pytest.approx(1.0) and same.oriented == 1.0
    flipped = normal_agreement(pts, -n, pts, n)
    assert flipped.abs_cos == pytest.approx(1.0) and flipped.cos == pytest.approx(-1.0) and flipped.oriented == 0.0
    half = n.copy()
    half[::2] *= -1
    h = normal_agreement(pts, 3.0 * half, pts, n)  # length does not matter
    assert h.cos == pytest.approx((len(pts) // 2 - (len(pts) - len(pts) // 2)) / len(pts))
    zero = normal_agreement(pts, np.zeros_like(n), pts, n)
    assert zero.abs_cos == 0.0 and zero.zero == 1.0


def test_normal_agreement_uses_the_nearest_reference():
    ref = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]])
    ref_n = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    pts = np.array([[0.5, 0.0, 0.0], [9.0, 0.0, 0.0]])
    a = normal_agreement(pts, np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]), ref, ref_n)
    assert a.abs_cos == pytest.approx(0.5) and a.oriented == 0.5


def test_errors_name_the_argument():
    with pytest.raises(ValueError, match=r"points: expected an \[N, 3\] point cloud"):
        chamfer(np.zeros((3, 2)), np.zeros((3, 3)))
    with pytest.raises(ValueError, match="reference: expected at least one point"):
        chamfer(np.zeros((3, 3)), np.zeros((0, 3)))
    with pytest.raises(ValueError, match="points: expected finite"):
        chamfer(np.full((3, 3), np.nan), np.zeros((3, 3)))
    with pytest.raises(ValueError, match=r"normals: expected shape \(3, 3\)"):
        normal_agreement(np.zeros((3, 3)), np.zeros((2, 3)), np.zeros((3, 3)), np.zeros((3, 3)))

"""PCA normals and statistical outliers: the scipy path (used where Open3D cannot be imported) against
Open3D itself, and the training's cloud operations running without Open3D."""

import sys
import warnings

import jax
import numpy as np
import pytest

from ne_jax.geometry.points import PointState
from ne_jax.pointcloud import neighbors
from ne_jax.pointcloud.neighbors import pca_normals, statistical_outliers
from ne_jax.pointcloud.normals import NormalConfig, estimate_normals
from ne_jax.pointcloud.rounds import RoundConfig, denoise_points

from .conftest import RADIUS


def _noisy_cloud(seed=0, n=6000):
    """A jittered unit sphere and a plane, 120 uniform outliers and 40 exact duplicates."""
    rng = np.random.default_rng(seed)
    sphere = rng.normal(size=(n, 3))
    sphere /= np.linalg.norm(sphere, axis=1, keepdims=True)
    plane = np.c_[rng.uniform(-1, 1, (n // 2, 2)), np.full(n // 2, -1.5)]
    xyz = np.concatenate([sphere, plane]) + rng.normal(0, 0.003, (n + n // 2, 3))
    return np.concatenate([xyz, rng.uniform(-2, 2, (120, 3)), xyz[:40]])


def _well_posed(xyz, radius, max_nn):
    """Points whose neighbourhood (Open3D's hybrid search) has >= 3 points spanning a plane and a
    smallest covariance eigenvalue well apart from the next: there the normal is unique up to sign."""
    from scipy.spatial import cKDTree

    dist, idx = cKDTree(xyz).query(xyz, k=max_nn, distance_upper_bound=radius)
    ok = np.zeros(len(xyz), bool)
    for i in range(len(xyz)):
        nb = xyz[idx[i][idx[i] < len(xyz)]]
        if len(nb) >= 3:
            ev = np.linalg.eigvalsh(np.cov(nb.T, bias=True))
            ok[i] = ev[0] < 0.1 * ev[1] and ev[1] > 1e-3 * ev[2]  # a plane, not a line
    return ok


@pytest.mark.parametrize("radius,max_nn", [(0.08, 30), (0.03, 16), (0.5, 8)])
def test_pca_normals_scipy_equal_open3d(radius, max_nn):
    xyz = _noisy_cloud()
    a = pca_normals(xyz, radius, max_nn, backend="open3d")
    b = pca_normals(xyz, radius, max_nn, backend="scipy")
    np.testing.assert_allclose(np.linalg.norm(b, axis=1), 1.0, atol=1e-12)
    ok = _well_posed(xyz, radius, max_nn)
    assert ok.mean() > 0.3
    np.testing.assert_allclose(np.abs((a[ok] * b[ok]).sum(1)), 1.0, atol=1e-6)  # same axis, any sign


def test_pca_normals_sparse_neighborhoods_point_up():
    xyz = np.array([[0.0, 0, 0], [0.01, 0, 0], [5, 5, 5], [9, 0, 0]])
    for backend in ("open3d", "scipy"):
        out = pca_normals(xyz, radius=0.1, max_nn=10, backend=backend)
        np.testing.assert_array_equal(out, np.tile([0.0, 0.0, 1.0], (4, 1)))


@pytest.mark.parametrize("k,std_ratio", [(8, 3.0), (20, 2.0), (64, 1.0)])
def test_statistical_outliers_scipy_equal_open3d(k, std_ratio):
    xyz = _noisy_cloud(seed=1)
    a = statistical_outliers(xyz, k, std_ratio, backend="open3d")
    b = statistical_outliers(xyz, k, std_ratio, backend="scipy")
    assert 50 <= a.sum() < len(xyz) // 4
    np.testing.assert_array_equal(a, b)


def test_bad_backend_is_named():
    with pytest.raises(ValueError, match="backend: expected 'auto', 'open3d' or 'scipy', found 'cgal'"):
        pca_normals(np.zeros((4, 3)), 1.0, 4, backend="cgal")


def test_training_cloud_operations_run_without_open3d(monkeypatch, sphere):
    """With Open3D gone, normals (every orientation) and denoising still work and agree with
    Open3D's: the same outliers, the same oriented normals on a sphere seen from all around."""
    rng = np.random.default_rng(2)
    xyz = rng.normal(size=(3000, 3))
    xyz = RADIUS * xyz / np.linalg.norm(xyz, axis=1, keepdims=True) + rng.normal(0, 0.002, xyz.shape)
    cfg = NormalConfig()
    with_o3d = estimate_normals(cfg, xyz, sphere)
    state = PointState.from_numpy(np.concatenate([xyz, [[3.0, 3, 3]]]), feature_dim=4, key=jax.random.key(0))
    denoised_o3d, report_o3d = denoise_points(RoundConfig(outlier_neighbors=16), state)

    monkeypatch.setitem(sys.modules, "open3d", None)  # `import open3d` now raises ImportError
    neighbors.open3d_module.cache_clear()
    try:
        with pytest.warns(UserWarning, match="open3d cannot be imported"):
            assert neighbors.open3d_module() is None
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # warned once, and nothing else complains
            without = estimate_normals(cfg, xyz, sphere)
            tangent = estimate_normals(NormalConfig(orient="tangent_plane"), xyz, sphere)
            votes = estimate_normals(NormalConfig(orient="visibility_votes"), xyz, sphere)
            denoised, report = denoise_points(RoundConfig(outlier_neighbors=16), state)
    finally:
        neighbors.open3d_module.cache_clear()  # Open3D again for the tests that follow
    agree = (with_o3d * without).sum(1)
    assert (agree > 0.999).mean() > 0.99  # oriented the same way, not only the same axis
    np.testing.assert_array_equal(tangent, votes)  # no scipy twin: the visibility votes decide
    assert report["denoised"] == report_o3d["denoised"] >= 1
    np.testing.assert_array_equal(np.asarray(denoised.alive), np.asarray(denoised_o3d.alive))

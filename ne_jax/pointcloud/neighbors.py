"""Neighbourhood statistics of a cloud: PCA normals and statistical outliers, by Open3D or by scipy.

Both are Open3D's algorithms. With Open3D importable (the normal case: it is a dependency) Open3D
computes them. Where it cannot be imported (a machine whose image lacks it, a Python it has no wheel
for), the same computation runs on scipy's ``cKDTree`` and numpy, with one warning. The two agree
up to floating point and the sign of a normal (which the orientation step sets anyway); the tests
check them against each other.

``pca_normals``: for each point, its neighbours within ``radius``, at most ``max_nn`` nearest (the
point included: Open3D's hybrid search); the normal is the covariance's eigenvector of the smallest
eigenvalue, ``(0, 0, 1)`` with fewer than 3 neighbours or no plane.

``statistical_outliers``: each point's mean distance to its ``k`` nearest points (itself included,
as Open3D counts); a point is an outlier unless ``0 < mean < m + std_ratio * s``, with ``m`` and
``s`` the mean and sample standard deviation of those means over the cloud.
"""

from __future__ import annotations

import functools
import warnings

import numpy as np
from scipy.spatial import cKDTree

BLOCK = 65_536
"""Points per block in the scipy path (bounds its temporaries to ``BLOCK * max_nn * 3`` floats)."""


@functools.cache
def open3d_module():
    """Open3D, or ``None`` (warned once) where it cannot be imported."""
    try:
        import open3d
    except ImportError as e:  # includes a missing system library (libGL, ...)
        warnings.warn(f"open3d cannot be imported ({e}); normals and outlier removal use the scipy "
                      "implementation of the same algorithms", stacklevel=2)
        return None
    return open3d


def pca_normals(xyz: np.ndarray, radius: float, max_nn: int, backend: str = "auto") -> np.ndarray:
    """``[N, 3]`` float64 unit normals (unoriented) of ``xyz`` ``[N, 3]``; ``backend``: ``"auto"``
    (Open3D if importable), ``"open3d"`` or ``"scipy"``."""
    xyz = np.asarray(xyz, np.float64)
    o3d = _backend(backend)
    if o3d is not None:
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
        pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=max_nn))
        return np.asarray(pcd.normals).copy()
    n = len(xyz)
    tree, k = cKDTree(xyz), min(int(max_nn), n)
    out = np.tile(np.array([0.0, 0.0, 1.0]), (n, 1))
    for s in range(0, n, BLOCK):
        dist, idx = tree.query(xyz[s:s + BLOCK], k=k, distance_upper_bound=radius, workers=-1)
        idx = idx.reshape(len(dist), k)
        found = idx < n
        count = found.sum(1)
        nbr = xyz[np.where(found, idx, 0)]
        w = found[..., None]
        mean = (nbr * w).sum(1) / np.maximum(count, 1)[:, None]
        d = (nbr - mean[:, None]) * w
        cov = np.einsum("nki,nkj->nij", d, d) / np.maximum(count, 1)[:, None, None]
        _, vec = np.linalg.eigh(cov)
        normal = vec[:, :, 0]
        ok = (count >= 3) & (np.linalg.norm(normal, axis=1) > 0) & np.isfinite(normal).all(1)
        out[s:s + BLOCK][ok] = normal[ok]
    return out


def statistical_outliers(xyz: np.ndarray, k: int, std_ratio: float, backend: str = "auto") -> np.ndarray:
    """``[N]`` bool: the statistical outliers of ``xyz`` ``[N, 3]`` (module docstring)."""
    xyz = np.asarray(xyz, np.float64)
    o3d = _backend(backend)
    if o3d is not None:
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
        _, inliers = pcd.remove_statistical_outlier(nb_neighbors=int(k), std_ratio=float(std_ratio))
        out = np.ones(len(xyz), bool)
        out[np.asarray(inliers, np.int64)] = False
        return out
    dist, _ = cKDTree(xyz).query(xyz, k=min(int(k), len(xyz)), workers=-1)
    mean = dist.reshape(len(xyz), -1).mean(1)
    threshold = mean.mean() + std_ratio * (mean.std(ddof=1) if len(mean) > 1 else 0.0)
    return ~((mean > 0) & (mean < threshold))


def _backend(name: str):
    if name == "scipy":
        return None
    if name == "open3d":
        o3d = open3d_module()
        if o3d is None:
            raise ImportError("backend='open3d': expected an importable open3d, found none")
        return o3d
    if name != "auto":
        raise ValueError(f"backend: expected 'auto', 'open3d' or 'scipy', found {name!r}")
    return open3d_module()


__all__ = ["open3d_module", "pca_normals", "statistical_outliers"]

"""An initial cloud from a capture's structure-from-motion points, for images without masks.

SfM points (COLMAP's ``points3D``, nerfstudio's ``sparse_pc.ply``) are sparse, a little noisy and
hold some outliers. :func:`sfm_cloud` cleans them and spreads them over the surfaces they sample:

1. **clean**: drop points whose reprojection error is above ``max_error_factor`` times the median
   (where the format stores errors); points that fewer than ``min_views`` cameras see in front of
   them and inside their image; and statistical outliers (Open3D's ``remove_statistical_outlier``,
   ``outlier_neighbors`` neighbours, ``outlier_std`` standard deviations);
2. **smooth**: each kept point moves along its local normal onto the plane through the mean of its
   ``smooth_neighbors`` nearest neighbours, so the noise across a surface (which would otherwise
   become a fuzzy layer, blurring its texture) is averaged over them;
3. **densify** to ``num_points``: each kept point ``p`` with its local normal ``n`` (the smallest
   principal axis of its ``k`` nearest neighbours) and spacing ``h`` (the distance to its
   ``k``-th neighbour, so the discs of neighbours overlap) is spread into samples uniform on the disc
   of radius ``h`` about ``p`` perpendicular to ``n``; owners are drawn in proportion to their disc's
   area (``h`` capped at ``max_spacing_factor`` times the median), so a sparsely sampled part of a
   surface is covered as densely as the rest; every point keeps itself. More points than
   ``num_points`` are sub-sampled instead.

Point growing in training fills what the SfM points miss.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial import cKDTree

from ne_jax.pointcloud.init import InitialCloud, Views

SFM_SOURCE = "sfm"


@dataclasses.dataclass(frozen=True)
class SfmCleaning:
    """Settings of :func:`sfm_cloud`'s cleaning, smoothing (``smooth_neighbors``, 0: off) and
    densification (module docstring)."""

    max_error_factor: float = 3.0
    min_views: int = 2
    outlier_neighbors: int = 16
    outlier_std: float = 2.0
    smooth_neighbors: int = 16
    neighbors: int = 8
    max_spacing_factor: float = 3.0


def _seen_by(views: Views, xyz: np.ndarray) -> np.ndarray:
    """``[N]`` int: how many views see each point in front of the camera and inside the image."""
    h, w = views.alpha.shape[1:]
    count = np.zeros(len(xyz), np.int64)
    for k in range(views.num_views):
        u, v, depth = views.project(k, xyz)
        count += (depth > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    return count


def _local_frames(pts: np.ndarray, k: int):
    """For each point of ``pts`` ``[P, 3]``: its ``k`` nearest neighbours' distances ``[P, k + 1]``
    (itself first), their mean ``[P, 3]`` and their smallest principal axis ``[P, 3]``."""
    dist, nbr = cKDTree(pts).query(pts, k=k + 1)
    mean = pts[nbr].mean(1)
    local = pts[nbr] - mean[:, None]
    _, vecs = np.linalg.eigh(np.einsum("nki,nkj->nij", local, local))
    return dist, mean, vecs[:, :, 0]


def _onto_local_planes(pts: np.ndarray, k: int) -> np.ndarray:
    """``pts`` each moved along its local normal onto the plane through its ``k`` nearest neighbours'
    mean: SfM noise across a surface averaged over ``k`` points."""
    _, mean, normal = _local_frames(pts, k)
    return pts - np.sum((pts - mean) * normal, axis=1, keepdims=True) * normal


def sfm_cloud(xyz: np.ndarray, views: Views, num_points: int, *,
              error: np.ndarray | None = None, cfg: SfmCleaning = SfmCleaning(), seed: int = 0) -> InitialCloud:
    """The initial cloud from SfM points ``xyz`` ``[P, 3]`` (scene frame) seen by ``views``
    (module docstring); ``error`` ``[P]`` (reprojection errors) is optional. ``info`` counts what
    each step kept.

    Raises:
        ValueError: fewer than 4 points survive the cleaning (too few to estimate surfaces from)."""
    xyz = np.asarray(xyz, np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"xyz: expected SfM points [P, 3], found shape {xyz.shape}")
    keep = np.isfinite(xyz).all(1)
    info = {"sfm_points": int(len(xyz))}
    if error is not None:
        error = np.asarray(error, np.float64)
        limit = cfg.max_error_factor * float(np.median(error[keep])) if keep.any() else np.inf
        keep &= ~(error > limit)
        info["after_error"] = int(keep.sum())
    keep[keep] = _seen_by(views, xyz[keep]) >= cfg.min_views
    info["after_visibility"] = int(keep.sum())
    pts = xyz[keep]
    if len(pts) > cfg.outlier_neighbors:
        import open3d as o3d

        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        _, inlier = pcd.remove_statistical_outlier(nb_neighbors=cfg.outlier_neighbors, std_ratio=cfg.outlier_std)
        pts = pts[np.asarray(inlier, np.int64)]
    info["after_outliers"] = int(len(pts))
    if len(pts) < 4:
        raise ValueError(f"SfM points: {len(pts)} of {len(xyz)} survive cleaning (reprojection error, seen by "
                         f">= {cfg.min_views} views, statistical outliers); expected at least 4")
    if cfg.smooth_neighbors > 0:
        pts = _onto_local_planes(pts, min(cfg.smooth_neighbors, len(pts) - 1))
    rng = np.random.default_rng(seed)
    if len(pts) >= num_points:
        out = pts[rng.choice(len(pts), num_points, replace=False)]
    else:
        k = min(cfg.neighbors, len(pts) - 1)
        dist, _, normal = _local_frames(pts, k)
        spacing = dist[:, -1]
        extra = num_points - len(pts)
        # owners drawn by the area their disc covers, so sparse parts of a surface get as many points
        # per area as dense ones; capped, so an isolated point does not take a large share
        area = np.minimum(spacing, cfg.max_spacing_factor * np.median(spacing)) ** 2
        owner = rng.choice(len(pts), extra, p=area / area.sum())
        # an orthonormal pair perpendicular to each owner's normal
        n = normal[owner]
        helper = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
        a = np.cross(n, helper)
        a /= np.linalg.norm(a, axis=1, keepdims=True)
        b = np.cross(n, a)
        r = spacing[owner] * np.sqrt(rng.random(extra))
        phi = 2 * np.pi * rng.random(extra)
        out = np.concatenate([pts, pts[owner] + r[:, None] * (np.cos(phi)[:, None] * a + np.sin(phi)[:, None] * b)])
    info["points"] = int(len(out))
    return InitialCloud(out.astype(np.float32), None, SFM_SOURCE, info)


__all__ = ["SFM_SOURCE", "SfmCleaning", "sfm_cloud"]

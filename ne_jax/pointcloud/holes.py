"""Growth into holes: candidates where a badly rendered ray meets no voxel.

The round's scan (:func:`~ne_jax.pointcloud.rounds.scan_growth`) only looks inside the K-D voxels, so
a part of the surface the cloud misses entirely proposes nothing there: the ray passes through empty
space and meets no voxel. :func:`hole_candidates` looks along such rays by photo-consistency, as a
plane-sweep stereo does for one pixel:

1. the rays: those the scan found no candidate on, whose rendered error is among the highest;
2. along each, ``depths`` samples evenly spaced over its stretch inside the region of interest (the
   cloud's bounding box, grown by ``margin``);
3. each sample is projected into the ``views`` training views whose viewing direction is nearest
   the ray's (other than the ray's own camera); its cost is the mean absolute RGB difference between
   the ray's target colour and those views' colours there (views that see it: in front, inside the
   image; at least two). Where the views have alpha masks, a sample outside a silhouette is out;
4. the ray's candidate is its cheapest sample when that cost is at most ``max_cost`` and at most
   ``peak_ratio`` times the ray's median cost (a textureless or infinitely far stretch, whose colours
   agree at every depth, proposes nothing), and it lies at least ``min_distance`` from every point.

Everything here is host-side numpy; its cost is ``rays x depths x views`` projections.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial import cKDTree

from ne_jax.pointcloud.init import Views, bilinear


@dataclasses.dataclass(frozen=True)
class HoleSearch:
    """Settings of :func:`hole_candidates`."""

    depths: int = 64
    views: int = 4
    max_cost: float = 0.08
    peak_ratio: float = 0.5
    margin: float = 0.05


def box_stretch(origin: np.ndarray, direction: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """``[R, 2]`` the ray parameters where each ray ``origin + t direction`` (``[R, 3]``) enters and
    leaves the box ``[lo, hi]`` (slab test; ``t >= 0``; an empty stretch has ``t0 >= t1``)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / direction
        a, b = (lo - origin) * inv, (hi - origin) * inv
    t0 = np.nanmax(np.minimum(a, b), axis=1)
    t1 = np.nanmin(np.maximum(a, b), axis=1)
    return np.stack([np.maximum(t0, 0.0), t1], axis=1)


def hole_candidates(cfg: HoleSearch, views: Views, origin: np.ndarray, direction: np.ndarray, target: np.ndarray,
                    cloud: np.ndarray, min_distance: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Photo-consistent candidates along rays (module docstring).

    ``origin``, ``direction`` ``[R, 3]`` (unit directions), ``target`` ``[R, 3]`` the rays' pixel
    colours (as the views' images hold them), ``cloud`` ``[N, 3]`` the alive points.
    Returns ``(xyz [R, 3], cost [R], found [R] bool)``."""
    origin, direction = np.asarray(origin, np.float64), np.asarray(direction, np.float64)
    r = len(origin)
    xyz, cost, found = np.zeros((r, 3)), np.full(r, np.inf), np.zeros(r, bool)
    if r == 0 or len(cloud) == 0:
        return xyz, cost, found
    lo, hi = cloud.min(0), cloud.max(0)
    pad = cfg.margin * (hi - lo).max()
    stretch = box_stretch(origin, direction, lo - pad, hi + pad)
    frac = (np.arange(cfg.depths) + 0.5) / cfg.depths
    t = stretch[:, :1] + (stretch[:, 1:] - stretch[:, :1]) * frac  # [R, D]
    pts = origin[:, None] + t[..., None] * direction[:, None]  # [R, D, 3]

    centers = views.c2w[:, :3, 3]
    mid = origin + 0.5 * (stretch[:, :1] + stretch[:, 1:]) * direction
    to_mid = mid[:, None] - centers[None]  # [R, V, 3]
    dist = np.linalg.norm(to_mid, axis=-1)
    cos = np.einsum("rvk,rk->rv", to_mid, direction) / np.maximum(dist, 1e-12)
    own = np.linalg.norm(origin[:, None] - centers[None], axis=-1) < 1e-6 * (1 + dist)
    cos = np.where(own, -np.inf, cos)
    k = min(cfg.views, views.num_views - 1) if views.num_views > 1 else 0
    if k < 1:
        return xyz, cost, found
    pick = np.argsort(-cos, axis=1)[:, :k]  # [R, k] the views looking most like the ray

    rgb = views.rgb
    if rgb is None:
        raise ValueError("hole_candidates: expected views with colours (Views.rgb), found None")
    masked = bool((views.alpha < 0.99).any())
    h, w = views.alpha.shape[1:]
    total, count = np.zeros(pts.shape[:2]), np.zeros(pts.shape[:2])
    outside = np.zeros(pts.shape[:2], bool)
    flat = pts.reshape(-1, 3)
    for j in range(k):
        view = np.repeat(pick[:, j], cfg.depths)
        u, v, depth = views.project(view, flat)
        seen = (depth > 1e-9) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        colour = bilinear(rgb, u, v, view)
        diff = np.abs(colour - np.repeat(target, cfg.depths, axis=0)).mean(1)
        total += np.where(seen, diff, 0.0).reshape(r, -1)
        count += seen.reshape(r, -1)
        if masked:
            a = bilinear(views.alpha, u, v, view)
            outside |= (seen & (a < 0.5)).reshape(r, -1)
    with np.errstate(invalid="ignore", divide="ignore"):
        sample_cost = np.where((count >= 2) & ~outside, total / np.maximum(count, 1), np.inf)
    best = np.argmin(sample_cost, axis=1)
    cost = sample_cost[np.arange(r), best]
    xyz = pts[np.arange(r), best]
    finite = np.where(np.isfinite(sample_cost), sample_cost, np.nan)
    with np.errstate(all="ignore"):
        median = np.nanmedian(np.where(np.isfinite(finite).any(1, keepdims=True), finite, 0.0), axis=1)
    found = (stretch[:, 1] > stretch[:, 0]) & np.isfinite(cost) & (cost <= cfg.max_cost) & \
        (cost <= cfg.peak_ratio * median)
    if found.any():
        near, _ = cKDTree(cloud).query(xyz[found])
        found[np.flatnonzero(found)[near < min_distance]] = False
    return xyz, cost, found


__all__ = ["HoleSearch", "box_stretch", "hole_candidates"]

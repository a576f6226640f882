"""Point normals with Open3D, oriented consistently towards the cameras.

Estimation: Open3D ``estimate_normals`` (PCA of the neighbourhood) with a hybrid KD-tree search,
radius :data:`RADIUS_FACTOR` times the mean nearest-neighbour spacing, at most ``cfg.max_nn``
neighbours (:func:`~ne_jax.pointcloud.neighbors.pca_normals`: the same on scipy where Open3D
cannot be imported). Re-run after every change of the cloud (growing, pruning, editing).

Orientation (``cfg.orient``) — PCA gives an axis, not a sign:

``"visibility"`` (default)
    Visibility votes (below), then propagation: points whose vote magnitude is at least
    ``VOTE_THRESHOLD`` keep their voted sign; every other point repeatedly takes the sign that
    agrees best with its ``PROPAGATE_K`` nearest neighbours, weighted by ``n_i . n_j`` and by
    ``exp(-(h / spacing)^2)`` with ``h`` the neighbour's height above the point's tangent plane (so
    the two sides of a thin wall do not vote for each other), until nothing changes.
``"visibility_votes"``
    Each point votes over the views that *see* it: a z-buffer of the cloud is splatted per view
    (pixels about two point spacings wide at the cloud's depth) and a point is visible when it lies
    within ``DEPTH_TOLERANCE`` spacings of the front-most point of its pixel. Each visible view
    adds ``cos(n, camera - p)``; the normal is flipped when the sum is negative. Points no view sees
    face their nearest camera centre.
``"nearest_camera"``
    Face the nearest camera centre (Open3D's ``orient_normals_towards_camera_location`` with each
    point's own nearest camera).
``"tangent_plane"``
    Open3D ``orient_normals_consistent_tangent_plane(TANGENT_K)`` (propagation over a Riemannian
    graph), then one global sign chosen by the visibility votes. Falls back to
    ``"visibility_votes"`` where Open3D refuses the input (degenerate clouds) or cannot be imported.
``"none"``
    Open3D's arbitrary signs.

``visibility`` is the default. ``tangent_plane`` suits one closed hull but takes a single global
sign, which flips whole parts of multi-part clouds. How often each rule faces the normals out, and
what they cost: docs/decisions.md, "The initial cloud".

Degenerate input: an empty cloud gives ``[0, 3]``; a cloud with fewer than 3 distinct points, or
whose points are collinear, gets unit normals perpendicular to its line (any perpendicular for a
single distinct point), oriented like the others. Open3D itself returns ``(0, 0, 1)`` for a
neighbourhood without a plane; those are kept (finite, unit). Output normals are always finite and
unit length (never zero) for ``N >= 1``.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial import cKDTree

from ne_jax.pointcloud.init import Views, visibility
from ne_jax.pointcloud.neighbors import open3d_module, pca_normals

ORIENTATIONS = ("visibility", "visibility_votes", "nearest_camera", "tangent_plane", "none")


RADIUS_FACTOR = 4.0
"""PCA search radius in units of the mean nearest-neighbour spacing."""
TANGENT_K = 16
"""Neighbours of the Riemannian graph of ``orient="tangent_plane"``."""
DEPTH_TOLERANCE = 2.0
"""Visibility: a point within this many spacings behind the front-most point of its z-buffer pixel
counts as visible."""
VOTE_THRESHOLD = 1.0
"""``"visibility"``: points whose summed visibility vote has at least this magnitude keep its sign."""
PROPAGATE_K = 16
"""``"visibility"``: neighbours in the sign propagation."""
PROPAGATE_ITERS = 50
"""``"visibility"``: at most this many propagation sweeps."""


@dataclasses.dataclass(frozen=True)
class NormalConfig:
    """Settings of :func:`estimate_normals`."""

    max_nn: int = 30
    """At most this many neighbours in the PCA."""
    orient: str = "visibility"
    """One of :data:`ORIENTATIONS` (see the module docstring)."""


def unique_rows(xyz: np.ndarray) -> np.ndarray:
    """The distinct rows of ``xyz [N, D]`` in lexicographic order: ``np.unique(xyz, axis=0)``, by a
    ``lexsort`` of the columns (np.unique sorts rows as structured records, 10x slower)."""
    xyz = np.asarray(xyz)
    if xyz.shape[0] < 2:
        return xyz.copy()
    rows = xyz[np.lexsort(xyz.T[::-1])]
    first = np.ones(rows.shape[0], bool)
    first[1:] = np.any(rows[1:] != rows[:-1], axis=1)
    return rows[first]


def mean_spacing(xyz: np.ndarray) -> float:
    """Mean distance from each point ``[N, 3]`` to its nearest *distinct* neighbour (0 when there is
    no distinct pair)."""
    xyz = np.asarray(xyz, np.float64)
    uniq = unique_rows(xyz)
    if uniq.shape[0] < 2:
        return 0.0
    d, _ = cKDTree(uniq).query(uniq, k=2, workers=-1)
    return float(d[:, 1].mean())


def _check_xyz(xyz) -> np.ndarray:
    xyz = np.asarray(xyz, np.float64)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"xyz: expected shape [N, 3], found {xyz.shape}")
    if not np.isfinite(xyz).all():
        raise ValueError("xyz: expected finite coordinates, found NaN/inf")
    return xyz


def _centers(cameras) -> np.ndarray | None:
    if cameras is None:
        return None
    if isinstance(cameras, Views):
        return cameras.centers
    c = np.asarray(cameras, np.float64)
    if c.ndim != 2 or c.shape[1] != 3 or c.shape[0] == 0 or not np.isfinite(c).all():
        raise ValueError(f"cameras: expected a Views or finite camera centres [V >= 1, 3], found shape {c.shape}")
    return c


def _degenerate_normals(xyz: np.ndarray) -> np.ndarray | None:
    """Normals for clouds without a plane (< 3 distinct points or collinear), else ``None``."""
    uniq = unique_rows(xyz)
    centered = uniq - uniq.mean(0)
    s = np.linalg.svd(centered, compute_uv=False) if len(uniq) > 1 else np.zeros(1)
    scale = max(float(s[0]), 1e-300)
    if len(uniq) >= 3 and len(s) >= 2 and s[1] > 1e-9 * scale:
        return None
    if len(uniq) > 1:
        axis = np.linalg.svd(centered)[2][0]
    else:
        axis = np.array([0.0, 0.0, 1.0])
    helper = np.eye(3)[np.argmin(np.abs(axis))]
    perp = np.cross(axis, helper)
    perp /= np.linalg.norm(perp)
    return np.broadcast_to(perp, xyz.shape).copy()


def _visibility_votes(views: Views, xyz, normals, spacing, tolerance) -> np.ndarray:
    """``[N]`` sum over the views that see each point of ``cos(n, camera - p)``."""
    vis = visibility(views, xyz, spacing, tolerance)
    votes = np.zeros(len(xyz))
    for k in range(views.num_views):
        sel = vis[k]
        if sel.any():
            to_cam = views.centers[k] - xyz[sel]
            to_cam /= np.maximum(np.linalg.norm(to_cam, axis=1, keepdims=True), 1e-12)
            votes[sel] += np.sum(normals[sel] * to_cam, axis=1)
    return votes


def _nearest_camera_sign(centers: np.ndarray, xyz, normals) -> np.ndarray:
    _, near = cKDTree(centers).query(xyz, k=1, workers=-1)
    return np.sign(np.sum(normals * (centers[near] - xyz), axis=1))


def orient_normals(cfg: NormalConfig, xyz, normals, cameras, spacing: float | None = None) -> np.ndarray:
    """Flip ``normals`` ``[N, 3]`` at ``xyz`` ``[N, 3]`` by ``cfg.orient`` (see the module docstring).

    ``cameras``: a :class:`Views` (needed by ``"visibility"`` and ``"tangent_plane"``) or camera
    centres ``[V, 3]`` (enough for ``"nearest_camera"``); may be ``None`` only with ``"none"``."""
    if cfg.orient not in ORIENTATIONS:
        raise ValueError(f"cfg.orient: expected one of {ORIENTATIONS}, found {cfg.orient!r}")
    xyz = _check_xyz(xyz)
    normals = np.array(normals, np.float64)
    if cfg.orient == "none" or len(xyz) == 0:
        return normals
    centers = _centers(cameras)
    if centers is None:
        raise ValueError(f"cameras: orientation {cfg.orient!r} needs cameras, found None")
    if cfg.orient == "nearest_camera":
        sign = _nearest_camera_sign(centers, xyz, normals)
        return normals * np.where(sign < 0, -1.0, 1.0)[:, None]
    if not isinstance(cameras, Views):
        raise TypeError(f"cameras: orientation {cfg.orient!r} needs a Views (intrinsics for the z-buffer), "
                         f"found {type(cameras).__name__}")
    spacing = mean_spacing(xyz) if spacing is None else spacing
    if cfg.orient == "tangent_plane":
        propagated = _tangent_plane(cfg, xyz, normals)
        if propagated is not None:
            votes = _visibility_votes(cameras, xyz, propagated, spacing, DEPTH_TOLERANCE)
            return -propagated if votes.sum() < 0 else propagated
    votes = _visibility_votes(cameras, xyz, normals, spacing, DEPTH_TOLERANCE)
    sign = np.sign(votes)
    if cfg.orient == "visibility" and len(xyz) > 1:
        sign = _propagate_signs(cfg, xyz, normals, votes, spacing)
    undecided = sign == 0  # seen by no view, and (propagation) reached by no decided neighbour
    if undecided.any():
        sign[undecided] = _nearest_camera_sign(centers, xyz[undecided], normals[undecided])
    return normals * np.where(sign < 0, -1.0, 1.0)[:, None]


def _propagate_signs(cfg: NormalConfig, xyz, normals, votes, spacing) -> np.ndarray:
    """``[N]`` signs in ``{-1, 0, 1}``: confident votes fixed, the rest by weighted neighbour
    agreement (see the module docstring), ``votes`` breaking ties; 0 where nothing decided."""
    k = min(PROPAGATE_K, len(xyz) - 1)
    _, nb = cKDTree(xyz).query(xyz, k=k + 1, workers=-1)
    nb = nb[:, 1:]
    height = np.abs(np.einsum("nkc,nc->nk", xyz[nb] - xyz[:, None], normals))
    weight = np.einsum("nkc,nc->nk", normals[nb], normals) * np.exp(-((height / max(spacing, 1e-12)) ** 2))
    fixed = np.abs(votes) >= VOTE_THRESHOLD
    sign = np.where(fixed, np.sign(votes), 0.0)
    for _ in range(PROPAGATE_ITERS):
        score = (weight * sign[nb]).sum(1) + 1e-3 * votes
        new = np.where(fixed, sign, np.sign(score))
        if np.array_equal(new, sign):
            break
        sign = new
    return sign


def _tangent_plane(cfg: NormalConfig, xyz, normals) -> np.ndarray | None:
    o3d = open3d_module()
    if o3d is None or len(xyz) <= TANGENT_K:  # no scipy twin: the caller takes the visibility votes
        return None
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
    pcd.normals = o3d.utility.Vector3dVector(normals)
    try:
        pcd.orient_normals_consistent_tangent_plane(TANGENT_K)
    except RuntimeError:  # qhull refuses co-planar/co-spherical/degenerate input
        return None
    out = np.asarray(pcd.normals).copy()
    return out if np.isfinite(out).all() else None


def estimate_normals(cfg: NormalConfig, xyz, cameras=None) -> np.ndarray:
    """Unit normals ``[N, 3]`` float32 of the cloud ``xyz`` ``[N, 3]``, estimated by Open3D and
    oriented by ``cfg.orient`` towards ``cameras`` (a :class:`Views`, or camera centres ``[V, 3]``
    for ``"nearest_camera"``).

    Raises:
        ValueError: bad ``xyz``/``cameras``/``cfg`` (naming it, the expectation and what was found).
    """
    xyz = _check_xyz(xyz)
    if cfg.orient not in ORIENTATIONS:
        raise ValueError(f"cfg.orient: expected one of {ORIENTATIONS}, found {cfg.orient!r}")
    if int(cfg.max_nn) < 3:
        raise ValueError(f"cfg.max_nn: expected an integer >= 3, found {cfg.max_nn}")
    if len(xyz) == 0:
        return np.zeros((0, 3), np.float32)
    spacing = mean_spacing(xyz)
    normals = _degenerate_normals(xyz)
    if normals is None:
        normals = pca_normals(xyz, RADIUS_FACTOR * spacing, cfg.max_nn)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    bad = ~(np.isfinite(normals).all(1, keepdims=True) & (length > 1e-12))
    normals = np.where(bad, np.array([0.0, 0.0, 1.0]), normals / np.where(bad, 1.0, length))
    if cfg.orient != "none":
        normals = orient_normals(cfg, xyz, normals, cameras, spacing=spacing)
    return normals.astype(np.float32)

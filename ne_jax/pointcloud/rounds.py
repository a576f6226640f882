"""Point-cloud rounds between training epochs: grow, prune, denoise (docs/design.md facts).

One round (:func:`point_round`) on a trained model:

1. **Grow.** :func:`scan_growth` (jit) walks each scanned training ray through the K-D voxels of the
   rendering levels *and* the growing level (whose larger boxes also cover holes in the cloud),
   evaluates the model's density at every sample, and takes per ray the densest sample; it is a
   candidate when it lies at least ``GROW_MIN_DISTANCE`` point spacings from every point (its
   nearest KNN candidate) and its density reaches ``GROW_MIN_SIGMA`` (PointNeRF's rule: the ray's
   opacity peak sits in a gap of the cloud). The ray's priority is its photometric error. On the host,
   :func:`select_growth` keeps one candidate per cubic cell of ``GROW_CELL`` spacings (the highest
   priority; a uniform grid stands in for the paper's "small K-D voxel": the tree's voxels hold
   points, and a candidate lies where there are none) and at most ``grow_max_fraction`` of the alive
   count, highest priority first. New points take the KNN-interpolated feature at their position and
   confidence 0.5; they fill dead slots first and the capacity is re-allocated on the host when
   that is not enough (:func:`add_points`).
2. **Prune** points with confidence below ``prune_threshold``.
3. **Denoise**: Open3D statistical outlier removal (``outlier_neighbors`` = 64 neighbours as the
   released code, ``OUTLIER_STD_RATIO``), limited to points at least ``outlier_min_ratio`` times the
   median mean-neighbour distance from their neighbours (ours: without it a clean cloud loses its
   sparsest 2% every round) and, optionally, to points less confident than
   ``outlier_keep_confidence``.
4. **Normals** re-estimated with Open3D for the new cloud (the tree is rebuilt by the caller).

Pruning and denoising never leave fewer than :data:`MIN_POINTS` alive points: a step that would is
skipped, and the report says so (a model whose confidences all collapsed keeps its cloud rather than
losing it). Every count is reported, nothing is dropped silently.
"""

from __future__ import annotations

import dataclasses
import functools
import operator

import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial import cKDTree

from ne_jax.checks import checked
from ne_jax.data.rays import Rays
from ne_jax.fields import require
from ne_jax.geometry.capacity import LostCounts
from ne_jax.geometry.intersect import intersect
from ne_jax.geometry.points import PointState
from ne_jax.pointcloud.holes import HoleSearch, hole_candidates
from ne_jax.pointcloud.init import Views
from ne_jax.pointcloud.neighbors import statistical_outliers
from ne_jax.pointcloud.normals import NormalConfig, estimate_normals
from ne_jax.render.driver import until_complete
from ne_jax.render.quadrature import at_test_time, level_samples
from ne_jax.render.renderer import PointScene, RenderConfig, render_rays
from ne_jax.render.stage import shade_samples

MIN_POINTS = 64
"""Pruning and denoising are skipped when they would leave fewer alive points."""
GROW_MIN_DISTANCE = 2.0
"""A growth candidate lies at least this many point spacings from its nearest point ..."""
GROW_MIN_SIGMA = 1.0
"""... and its density (per point spacing) is at least this (opacity ``1 - e^-1`` over one spacing)."""
GROW_CELL = 2.0
"""One growth candidate per cubic cell of this many point spacings."""
HOLE_SHARE = 0.25
"""With ``RoundConfig.fill_holes``: the share of the scanned rays, highest error first among those
the scan found no candidate on, searched for holes."""
OUTLIER_STD_RATIO = 3.0
"""A point is a statistical outlier when its mean neighbour distance exceeds the mean by this many
standard deviations (ours: 2.0 removed a few per cent of good points per round on thin parts)."""
CAPACITY_HEADROOM = 1.25
"""When growth needs more slots than the capacity has free, the new capacity is
``ceil(needed * CAPACITY_HEADROOM)``."""


@dataclasses.dataclass(frozen=True)
class RoundConfig:
    """Settings of one point-cloud round (hashable)."""

    grow: bool = True
    prune: bool = True
    denoise: bool = True
    grow_rays: int = 8192
    """Training rays scanned for growth candidates per round."""
    grow_chunk: int = 512
    """Rays per compiled scan call (memory: ``chunk * max_segments * samples * K`` neighbours)."""
    grow_max_fraction: float = 0.02
    """At most this share of the alive count is added per round."""
    fill_holes: bool = False
    """Also look for candidates where badly rendered rays meet no voxel, by photo-consistency along
    them (:mod:`ne_jax.pointcloud.holes`): a part of the surface the cloud misses entirely."""
    prune_threshold: float = 0.1
    """Points with confidence below this are pruned (docs/design.md: 0.1)."""
    outlier_neighbors: int = 64
    """Neighbours of the statistical outlier removal (released code: 64)."""
    outlier_min_ratio: float = 2.0
    """A statistical outlier (:data:`OUTLIER_STD_RATIO`) is removed only when its mean neighbour
    distance is at least this multiple of the median one (ours): on a clean surface cloud the
    statistical threshold alone sits near the median, so each round would remove the sparsest good
    points and holes would grow round after round. A floater is many times the median away; 0 turns
    the floor off."""
    outlier_keep_confidence: float | None = None
    """``None``: every statistical outlier beyond the floor goes. A number: outliers whose confidence
    is at least this stay. A thin part (stool's foot ring: a few dozen points, fewer than the 64
    neighbours the test compares against) is flagged point by point; when the rendering needs it its
    confidences say so, which only a density gate (``KDTreeConfig.density_falloff``) lets them do."""

    def __post_init__(self):
        def need(cond, name, expected):
            require(self, cond, name, expected)

        need(self.grow_rays >= 1, "grow_rays", "an integer >= 1")
        need(self.grow_chunk >= 1, "grow_chunk", "an integer >= 1")
        need(0 <= self.grow_max_fraction <= 1, "grow_max_fraction", "a value in [0, 1]")
        need(0 <= self.prune_threshold < 1, "prune_threshold", "a value in [0, 1)")
        need(self.outlier_neighbors >= 2, "outlier_neighbors", "an integer >= 2")
        need(self.outlier_min_ratio >= 0, "outlier_min_ratio", ">= 0")
        need(self.outlier_keep_confidence is None or 0 < self.outlier_keep_confidence <= 1,
             "outlier_keep_confidence", "None or a value in (0, 1]")

    def replace(self, **changes) -> RoundConfig:
        return dataclasses.replace(self, **changes)


# ---------------------------------------------------------------- grow


def scan_growth(cfg: RenderConfig, params: dict, scene: PointScene, rays: Rays, background,
                min_distance: float, min_sigma: float) -> dict:
    """Per ray, the densest sample, kept when it lies far from every point (one jitted pass over
    ``[R]`` rays; PointNeRF's rule: the ray's opacity peak sits in a gap of the cloud).

    Returns ``{"xyz": [R, 3], "feature": [R, F], "sigma": [R], "found": [R] bool, "error": [R]}``:
    the densest sample's position, its interpolated feature, its density (per spacing), whether it
    is a candidate (density at least ``min_sigma`` and at least ``min_distance`` spacings from its
    nearest point), and the ray's photometric error (mean squared RGB error of a render,
    ``rays.target`` holding the colour on the background) -- the candidate's priority; and what the
    scan's traversal and the render lost to the scene's capacities (``lost``, ``render_lost``:
    :class:`~ne_jax.geometry.capacity.Lost`, ``[R]`` per field). With ``cfg.checks`` the scan runs
    under the runtime checks (:mod:`ne_jax.checks`) and raises on the first non-finite stage.
    """
    scan = _checked_scan(cfg) if cfg.checks else functools.partial(_scan_growth, cfg)
    return scan(params, scene, rays, background, min_distance, min_sigma)


def _scan(cfg: RenderConfig, params: dict, scene: PointScene, rays: Rays, background, min_distance, min_sigma):
    tree = scene.tree
    seg = intersect(tree, rays, cfg.kdtree, scene.capacities, include_grow_level=True)  # [R, M]
    level_index = (tree.depth - 1) - seg.level  # 0 = bottom rendering level, L = growing level
    t, w = level_samples(cfg.quadrature, seg.t_lo, seg.t_hi, level_index)  # [R, M, S]
    pos = rays.origin[:, None, None, :] + t[..., None] * rays.direction[:, None, None, :]
    view = jnp.broadcast_to(rays.direction[:, None, :], seg.t_lo.shape + (3,))
    sh = shade_samples(cfg, params, scene, pos, seg.node, view)  # [R, M, S], candidates once per segment
    sample = seg.valid[..., None] & (w > 0)
    score = jnp.where(sample, sh.sigma, -jnp.inf).reshape(sh.sigma.shape[0], -1)
    best = jnp.argmax(score, axis=-1)  # the ray's densest sample ...
    take = lambda a: jnp.take_along_axis(a.reshape(a.shape[0], -1, *a.shape[3:]),  # noqa: E731
                                         best.reshape((-1, 1) + (1,) * (a.ndim - 3)), axis=1)[:, 0]
    found = (jnp.max(score, axis=-1) >= min_sigma) & (take(sh.nearest) >= min_distance * tree.spacing)  # ... in a gap
    rendered = render_rays(cfg, params, scene, rays, background)
    error = jnp.mean(jnp.square(rendered.rgb - rays.target[:, :3]), axis=-1)
    out = {"xyz": take(pos), "feature": take(sh.values["feature"]), "sigma": take(sh.sigma), "found": found,
           "error": error, "lost": seg.lost(), "render_lost": rendered.lost}
    if "ist" in sh.values:  # an edited model: new points take the interpolated IST
        out["ist"] = take(sh.values["ist"])
    return out


_scan_growth = jax.jit(_scan, static_argnums=0)


@functools.cache
def _checked_scan(cfg: RenderConfig):
    return checked(functools.partial(_scan, cfg))


def select_growth(xyz: np.ndarray, priority: np.ndarray, cell: float, max_new: int) -> np.ndarray:
    """Host side: indices of the candidates to add, highest ``priority`` first, one per cubic cell
    of side ``cell`` (the highest-priority candidate of the cell), at most ``max_new``.
    ``xyz`` ``[N, 3]``, ``priority`` ``[N]``."""
    if xyz.shape[0] == 0 or max_new <= 0:
        return np.zeros((0,), np.int64)
    cells = np.floor(np.asarray(xyz, np.float64) / cell).astype(np.int64)
    order = np.argsort(-np.asarray(priority), kind="stable")
    _, first = np.unique(cells[order], axis=0, return_index=True)
    keep = order[np.sort(first)]  # one per cell, in priority order
    return keep[:max_new]


def add_points(points: PointState, xyz: np.ndarray, feature: np.ndarray, confidence: float = 0.5,
               headroom: float = 1.25, ist: np.ndarray | None = None) -> tuple[PointState, np.ndarray]:
    """Host side: ``points`` with ``[N, 3]`` new points (features ``[N, F]``, ISTs ``[N, 3, 3]`` or
    the identity) in dead slots, first come first; when there are fewer dead slots than new points,
    the capacity grows to ``ceil((alive + N) * headroom)`` (new slots dead, normals zero, IST identity).
    Returns ``(points, slots [N])`` -- where the new points went."""
    xyz = np.asarray(xyz, np.float32).reshape(-1, 3)
    n = xyz.shape[0]
    alive = np.asarray(points.alive)
    free = np.flatnonzero(~alive)
    if free.size < n:
        points = resize_capacity(points, int(np.ceil((int(alive.sum()) + n) * headroom)))
        free = np.flatnonzero(~np.asarray(points.alive))
    slots = free[:n]
    logit = float(np.log(confidence) - np.log1p(-confidence))
    j = jnp.asarray(slots)
    points = points.replace(
        xyz=points.xyz.at[j].set(jnp.asarray(xyz, points.xyz.dtype)),
        alive=points.alive.at[j].set(True),
        feature=points.feature.at[j].set(jnp.asarray(feature, points.feature.dtype)),
        conf_logit=points.conf_logit.at[j].set(logit),
        normal=points.normal.at[j].set(0.0),
        ist=points.ist.at[j].set(jnp.eye(3, dtype=points.ist.dtype) if ist is None
                                 else jnp.asarray(ist, points.ist.dtype).reshape(-1, 3, 3)),
    )
    return points, slots


def resize_capacity(points: PointState, capacity: int) -> PointState:
    """Host side: the same cloud in ``capacity`` slots (>= the current capacity; indices kept, new
    slots dead with finite placeholders)."""
    c = points.capacity
    if capacity < c:
        raise ValueError(f"capacity: expected >= the current capacity {c}, found {capacity}")
    pad = capacity - c

    def grow(a, fill=0.0):
        block = jnp.full((pad,) + a.shape[1:], fill, a.dtype)
        return jnp.concatenate([a, block])

    eye = jnp.broadcast_to(jnp.eye(3, dtype=points.ist.dtype), (pad, 3, 3))
    return points.replace(xyz=grow(points.xyz), alive=grow(points.alive, False), feature=grow(points.feature),
                          conf_logit=grow(points.conf_logit), normal=grow(points.normal),
                          ist=jnp.concatenate([points.ist, eye]))


def grow_points(cfg: RoundConfig, render_cfg: RenderConfig, params: dict, scene: PointScene,
                rays: Rays, background, max_grow: int = 4, views: Views | None = None) -> tuple[PointState, dict]:
    """Scan ``rays`` (``[R]``, targets set) in chunks, select and add the new points. A chunk that
    lost segments to the scene's capacities is scanned again with them grown
    (:meth:`~ne_jax.render.renderer.PointScene.grown`, at most ``max_grow`` times).
    Returns ``(points, report)``; the report counts rays scanned, candidates found and points added,
    whether the point capacity was re-allocated, what was still lost (``lost``, as
    :class:`~ne_jax.geometry.capacity.LostCounts`) and the capacities the scan ended with. With
    ``cfg.fill_holes`` (and ``views``) the rays it found nothing on are searched for holes too
    (:func:`hole_growth`); both kinds of candidate share the cells and the cap."""
    render_cfg = render_cfg.replace(quadrature=at_test_time(render_cfg.quadrature))  # no jitter in the scan
    n = rays.num_rays
    chunk = min(cfg.grow_chunk, n)
    pad = (-n) % chunk
    padded = jax.tree_util.tree_map(lambda a: jnp.concatenate([a, jnp.repeat(a[-1:], pad, axis=0)]), rays)
    parts, lost = [], LostCounts()

    def lost_of(out):  # the scan's traversal and its render, one transfer each
        return out["lost"].counts() + out["render_lost"].counts()

    for s in range(0, n + pad, chunk):
        part = jax.tree_util.tree_map(operator.itemgetter(slice(s, s + chunk)), padded)
        out, scene = until_complete(
            scene, lambda sc, part=part: scan_growth(render_cfg, params, sc, part, background, GROW_MIN_DISTANCE,
                                                      GROW_MIN_SIGMA), lost_of, max_grow)
        lost += lost_of(out)
        parts.append(jax.device_get({k: v for k, v in out.items() if k not in ("lost", "render_lost")}))
    scan = {k: np.concatenate([p[k] for p in parts])[:n] for k in parts[0]}
    found = np.flatnonzero(scan["found"])
    holes = {}
    if cfg.fill_holes and views is not None:
        scan, holes = hole_growth(cfg, scene, rays, scan, views)
    alive = int(np.asarray(scene.points.alive).sum())
    max_new = int(np.floor(cfg.grow_max_fraction * alive))
    spacing = float(scene.tree.spacing)
    candidates = np.flatnonzero(scan["found"])
    pick = candidates[select_growth(scan["xyz"][candidates], scan["error"][candidates], GROW_CELL * spacing,
                                    max_new)]
    capacity = scene.points.capacity
    points, slots = add_points(scene.points, scan["xyz"][pick], scan["feature"][pick],
                               headroom=CAPACITY_HEADROOM, ist=scan["ist"][pick] if "ist" in scan else None)
    if holes:
        holes["added"] = int(np.isin(pick, holes.pop("rows")).sum())
    report = {"rays": int(n), "candidates": int(found.size), "added": int(pick.size),
              **({"holes": holes} if holes else {}), "capacity_before": capacity, "capacity_after": points.capacity,
              "reallocated": points.capacity != capacity, "lost": lost.as_dict(),
              "capacities": dataclasses.asdict(scene.capacities)}
    return points, report


def hole_growth(cfg: RoundConfig, scene: PointScene, rays: Rays, scan: dict, views: Views) -> tuple[dict, dict]:
    """The scan with hole candidates (:func:`~ne_jax.pointcloud.holes.hole_candidates`) on the
    ``HOLE_SHARE`` highest-error rays it found nothing on; a hole candidate takes the feature (and
    IST) of its nearest alive point. Returns ``(scan, report)``: rays searched, candidates found, and
    ``rows`` (their ray indices, for the caller's count of what was added)."""
    error = scan["error"]
    empty = np.flatnonzero(~scan["found"])
    count = int(np.ceil(HOLE_SHARE * len(error)))
    rows = empty[np.argsort(-error[empty], kind="stable")[:count]]
    points = scene.points
    alive = np.flatnonzero(np.asarray(points.alive))
    cloud = np.asarray(points.xyz, np.float64)[alive]
    host = jax.device_get({"o": rays.origin[rows], "d": rays.direction[rows], "t": rays.target[rows, :3]})
    xyz, _, found = hole_candidates(HoleSearch(), views, host["o"], host["d"], host["t"], cloud,
                                    GROW_MIN_DISTANCE * float(scene.tree.spacing))
    rows = rows[found]
    scan = {k: np.array(v, copy=True) for k, v in scan.items()}
    if rows.size:
        _, nearest = cKDTree(cloud).query(xyz[found])
        scan["xyz"][rows] = xyz[found]
        scan["feature"][rows] = np.asarray(points.feature)[alive[nearest]]
        if "ist" in scan:
            scan["ist"][rows] = np.asarray(points.ist)[alive[nearest]]
        scan["found"][rows] = True
    return scan, {"rays": int(count), "candidates": int(rows.size), "rows": rows}


# ---------------------------------------------------------------- prune and denoise


def _guarded_removal(points: PointState, remove: np.ndarray, min_points: int, what: str) -> tuple[PointState, dict]:
    alive = np.asarray(points.alive)
    remove = remove & alive
    left = int(alive.sum() - remove.sum())
    if left < min_points:
        return points, {f"{what}": 0, f"{what}_skipped": True,
                        f"{what}_note": f"would leave {left} < min_points={min_points} alive points; skipped"}
    return points.replace(alive=jnp.asarray(alive & ~remove)), {f"{what}": int(remove.sum()), f"{what}_skipped": False}


def prune_points(cfg: RoundConfig, points: PointState) -> tuple[PointState, dict]:
    """Mark points with confidence below ``cfg.prune_threshold`` dead, unless fewer than
    :data:`MIN_POINTS` would stay alive. Returns ``(points, report)``."""
    alive, confidence = np.asarray(points.alive), np.asarray(points.confidence)
    remove = alive & (confidence < cfg.prune_threshold)
    return _guarded_removal(points, remove, MIN_POINTS, "pruned")


def mean_neighbor_distance(xyz: np.ndarray, k: int) -> np.ndarray:
    """``[N]`` mean distance of each point of ``xyz`` ``[N, 3]`` to its ``k`` nearest other points."""
    dist, _ = cKDTree(xyz).query(xyz, k=k + 1, workers=-1)
    return dist[:, 1:].mean(axis=1)


def denoise_points(cfg: RoundConfig, points: PointState) -> tuple[PointState, dict]:
    """Open3D's statistical outlier removal over the alive points (``cfg.outlier_neighbors``,
    ``OUTLIER_STD_RATIO``; :func:`~ne_jax.pointcloud.neighbors.statistical_outliers`), keeping
    every point whose mean neighbour distance is below ``cfg.outlier_min_ratio`` times the median
    one and, with ``cfg.outlier_keep_confidence``, every point at least that confident. Returns
    ``(points, report)``."""
    alive = np.flatnonzero(np.asarray(points.alive))
    if alive.size <= cfg.outlier_neighbors:
        return points, {"denoised": 0, "denoised_skipped": True,
                        "denoised_note": f"{alive.size} alive points <= outlier_neighbors={cfg.outlier_neighbors}"}
    xyz = np.asarray(points.xyz, np.float64)[alive]
    outlier = statistical_outliers(xyz, cfg.outlier_neighbors, OUTLIER_STD_RATIO)
    if cfg.outlier_min_ratio > 0 and outlier.any():
        mean_dist = mean_neighbor_distance(xyz, cfg.outlier_neighbors)
        outlier &= mean_dist >= cfg.outlier_min_ratio * np.median(mean_dist)
    if cfg.outlier_keep_confidence is not None:
        outlier &= np.asarray(points.confidence)[alive] < cfg.outlier_keep_confidence
    remove = np.zeros(points.capacity, bool)
    remove[alive[outlier]] = True
    return _guarded_removal(points, remove, MIN_POINTS, "denoised")


def refresh_normals(points: PointState, views: Views | None, normal_cfg: NormalConfig = NormalConfig()) -> PointState:
    """Re-estimate the normals of the alive points with Open3D, oriented towards ``views``
    (dead slots: zeros)."""
    alive = np.flatnonzero(np.asarray(points.alive))
    normals = np.zeros((points.capacity, 3), np.float32)
    normals[alive] = estimate_normals(normal_cfg, np.asarray(points.xyz)[alive], views)
    return points.replace(normal=jnp.asarray(normals, points.normal.dtype))


def point_round(cfg: RoundConfig, render_cfg: RenderConfig, params: dict, scene: PointScene,
                rays: Rays, background, views: Views | None,
                normal_cfg: NormalConfig = NormalConfig()) -> tuple[PointState, dict]:
    """One round: grow (from ``rays``), prune, denoise, re-estimate normals (see the module
    docstring). Returns the new :class:`PointState` (rebuild the tree with
    :meth:`PointScene.build`) and a report of every count."""
    points = scene.points
    report = {"alive_before": int(np.asarray(points.alive).sum())}
    if cfg.grow:
        points, r = grow_points(cfg, render_cfg, params, scene, rays, background, views=views)
        report.update(grown=r)
    if cfg.prune:
        points, r = prune_points(cfg, points)
        report.update(r)
    if cfg.denoise:
        points, r = denoise_points(cfg, points)
        report.update(r)
    points = refresh_normals(points, views, normal_cfg)
    report["alive_after"] = int(np.asarray(points.alive).sum())
    report["capacity"] = points.capacity
    return points, report


__all__ = ["RoundConfig", "add_points", "denoise_points", "grow_points", "hole_growth", "mean_neighbor_distance",
           "point_round", "prune_points", "refresh_normals", "resize_capacity", "scan_growth", "select_growth"]

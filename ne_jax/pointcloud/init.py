"""Initial point clouds without pretrained weights: visual-hull carving, a user's PLY, or (benchmark
only, on explicit request) the ground-truth surface samples.

The paper initialises from a pretrained MVS point-generation network, which cannot be had offline
(``docs/design.md``, "Not available offline"). :func:`carve_visual_hull` stands in: it carves a voxel grid
with the training views' foreground masks and keeps the shell of what survives.

Carving (classical shape-from-silhouette):

1. Voxel centres of an ``R x R x R`` grid over ``cfg.bounds`` are projected into every view.
2. A view *carves* a voxel when the voxel projects in front of the camera and inside the image
   (its frustum) and the bilinearly interpolated alpha there is ``<= cfg.alpha_threshold``. A voxel
   outside a view's frustum gets *no information* from that view (it is neither carved nor
   confirmed). A voxel survives when no view carves it and at least ``cfg.min_views`` views see it.
3. The shell: surviving voxels with at least one 6-neighbour that did not survive (carved, seen
   by too few views, or outside the grid).
4. ``cfg.num_points`` points are drawn from the shell voxels (every voxel once before any twice),
   jittered uniformly inside their voxel, then (``cfg.snap_steps > 0``) moved onto the hull surface:
   along the voxel's outward direction (towards its empty 6-neighbours) the inside/outside test of
   step 2 is bisected between ``-1`` and ``+1.5`` voxel sizes; points whose segment does not
   bracket a crossing stay where they are.

The result is the *visual hull*, not the surface: concavities that no silhouette reveals (the
inside of a cup seen from outside) stay filled, and the hull is only as sharp as the masks (one
pixel at the object's distance). Optional photo-consistency sweeps (``cfg.photo_iters``, off by
default; :func:`photo_consistency`) remove shell voxels whose colours disagree across the views
that see them (visibility by a z-buffer of the shell). Growing and pruning during training are what
refine the cloud further.

Snapping puts points *on the hull*. Where the hull is loose (concavities), unsnapped points half a
voxel inside it can lie slightly closer to the true surface. What the sweeps, the snapping and the
carving's time come to on the benchmark: docs/decisions.md, "The initial cloud".

Shapes: ``V`` views, ``H x W`` images, ``N`` points.
"""

from __future__ import annotations

import dataclasses
import os
import time
import warnings
from pathlib import Path

import numpy as np

from ne_jax.data.ply import PlyError, read_ply

GT_SOURCE = "ground-truth surface samples (benchmark only)"
"""The :attr:`InitialCloud.source` label of a cloud read from a benchmark's ``points.ply``."""


class CarvingError(ValueError):
    """Carving cannot give a cloud (empty masks, no background, nothing left); the message says why."""


@dataclasses.dataclass(frozen=True)
class InitialCloud:
    """A host-side initial point cloud and where it came from.

    ``xyz`` ``[N, 3]`` float32; ``normals`` ``[N, 3]`` float32 unit vectors, or ``None`` when the
    source has none (estimate them with :func:`ne_jax.pointcloud.normals.estimate_normals`);
    ``source`` one of ``"carving"``, ``"ply:<path>"`` or :data:`GT_SOURCE` — carry it into every
    result made from this cloud; ``info`` free-form numbers about how it was made (voxel size,
    counts, seconds)."""

    xyz: np.ndarray
    normals: np.ndarray | None
    source: str
    info: dict = dataclasses.field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.xyz.shape[0])

    @property
    def is_ground_truth(self) -> bool:
        """True when the cloud is the benchmark's ground truth (results must be labelled so)."""
        return self.source == GT_SOURCE

    def with_normals(self, normals: np.ndarray) -> InitialCloud:
        """The same cloud with ``normals`` ``[N, 3]``."""
        normals = np.asarray(normals, np.float32)
        if normals.shape != self.xyz.shape:
            raise ValueError(f"normals: expected shape {self.xyz.shape}, found {normals.shape}")
        return dataclasses.replace(self, normals=normals)


# ----------------------------------------------------------------------------------------------
# Views
# ----------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Views:
    """Masks and pinhole cameras of ``V`` views, host-side.

    ``alpha`` ``[V, H, W]`` float32 in ``[0, 1]`` (row 0 at the top); ``c2w`` ``[V, 4, 4]``
    camera-to-world in the OpenGL convention (camera looks down ``-z``, ``+y`` up); ``fx, fy, cx,
    cy`` pixel intrinsics shared by all views, pixel centres at ``i + 0.5``; ``rgb`` ``[V, H, W, 3]``
    float32 straight colours, or ``None`` (only photo-consistency needs them)."""

    alpha: np.ndarray
    c2w: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    rgb: np.ndarray | None = None

    @classmethod
    def from_split(cls, split) -> Views:
        """From a :class:`ne_jax.data.nerf_synthetic.SceneSplit` (its images' alpha channel)."""
        images = split.images
        return cls.create(images[..., 3], split.c2w, split.fx, split.fy, split.cx, split.cy, rgb=images[..., :3])

    @classmethod
    def create(cls, alpha, c2w, fx, fy, cx, cy, rgb=None) -> Views:
        """Checked constructor; raises ``ValueError`` naming the argument."""
        alpha = np.asarray(alpha, np.float32)
        c2w = np.asarray(c2w, np.float64)
        if alpha.ndim != 3 or alpha.shape[0] == 0 or min(alpha.shape[1:]) == 0:
            raise ValueError(f"alpha: expected shape [V, H, W] with V, H, W >= 1, found {alpha.shape}")
        if c2w.shape != (alpha.shape[0], 4, 4):
            raise ValueError(f"c2w: expected shape [V={alpha.shape[0]}, 4, 4], found {c2w.shape}")
        if not np.isfinite(alpha).all():
            raise ValueError("alpha: expected finite values, found NaN/inf")
        if not np.isfinite(c2w).all():
            raise ValueError("c2w: expected finite values, found NaN/inf")
        for name, v in (("fx", fx), ("fy", fy)):
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name}: expected a positive focal length in pixels, found {v!r}")
        if rgb is not None:
            rgb = np.asarray(rgb, np.float32)
            if rgb.shape != alpha.shape + (3,):
                raise ValueError(f"rgb: expected shape {alpha.shape + (3,)} like alpha plus 3 channels, "
                                 f"found {rgb.shape}")
            if not np.isfinite(rgb).all():
                raise ValueError("rgb: expected finite values, found NaN/inf")
        return cls(alpha, c2w, float(fx), float(fy), float(cx), float(cy), rgb)

    @property
    def num_views(self) -> int:
        return int(self.alpha.shape[0])

    @property
    def centers(self) -> np.ndarray:
        """``[V, 3]`` camera centres."""
        return self.c2w[:, :3, 3]

    def project(self, view: int | np.ndarray, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pixel coordinates ``u, v`` ``[N]`` (continuous, pixel centres at ``i + 0.5``) and depth
        ``[N]`` (distance along the viewing axis, positive in front) of points ``[N, 3]`` in one view
        (``view`` an index) or each in its own (``view`` ``[N]`` indices)."""
        rot, centre = self.c2w[view, :3, :3], self.c2w[view, :3, 3]
        # world -> camera: R^T (x - t)
        cam = (xyz - centre) @ rot if rot.ndim == 2 else np.einsum("nk,nkj->nj", xyz - centre, rot)
        depth = -cam[:, 2]
        safe = np.where(depth > 1e-9, depth, 1.0)
        u = self.cx + self.fx * cam[:, 0] / safe
        v = self.cy - self.fy * cam[:, 1] / safe
        return u, v, depth


def bilinear(img: np.ndarray, u: np.ndarray, v: np.ndarray, view: np.ndarray | None = None) -> np.ndarray:
    """Bilinear lookup at continuous pixel coordinates ``u, v`` ``[N]`` (centres at ``i + 0.5``),
    clamped at the border, of ``img`` ``[H, W]`` or ``[H, W, C]``, or with ``view`` ``[N]`` of the
    images ``img[view]`` of a stack ``[V, H, W(, C)]``; returns ``[N]`` or ``[N, C]``."""
    h, w = img.shape[:2] if view is None else img.shape[1:3]
    x = np.clip(u - 0.5, 0.0, w - 1.0)
    y = np.clip(v - 0.5, 0.0, h - 1.0)
    x0 = np.minimum(x.astype(np.int64), w - 2) if w > 1 else np.zeros(x.shape, np.int64)
    y0 = np.minimum(y.astype(np.int64), h - 2) if h > 1 else np.zeros(y.shape, np.int64)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = (x - x0).astype(np.float32), (y - y0).astype(np.float32)
    pixel = (lambda yy, xx: img[yy, xx]) if view is None else (lambda yy, xx: img[view, yy, xx])
    if img.ndim == (2 if view is None else 3) + 1:  # a channel axis
        fx, fy = fx[:, None], fy[:, None]
    top = pixel(y0, x0) * (1 - fx) + pixel(y0, x1) * fx
    bot = pixel(y1, x0) * (1 - fx) + pixel(y1, x1) * fx
    return top * (1 - fy) + bot * fy


def _carves(views: Views, view: int, xyz: np.ndarray, alpha_threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """``(carved [N], in_frustum [N])`` of points ``[N, 3]`` in one view."""
    h, w = views.alpha.shape[1:]
    u, v, depth = views.project(view, xyz)
    inside = (depth > 1e-6) & (u >= 0) & (u <= w) & (v >= 0) & (v <= h)
    carved = np.zeros(len(xyz), bool)
    carved[inside] = bilinear(views.alpha[view], u[inside], v[inside]) <= alpha_threshold
    return carved, inside


def hull_test(views: Views, xyz: np.ndarray, alpha_threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """Visual-hull membership of points ``[N, 3]``.

    Returns ``(carved [N] bool, seen [N] int)``: ``carved`` when some view sees the point (in front
    of the camera, inside the image) with alpha ``<= alpha_threshold`` there; ``seen`` the number of
    views whose frustum holds the point, counted until the point is carved (points are dropped from
    later views once carved)."""
    xyz = np.asarray(xyz, np.float64)
    n = xyz.shape[0]
    carved = np.zeros(n, bool)
    seen = np.zeros(n, np.int32)
    live = np.arange(n)
    for k in range(views.num_views):
        if live.size == 0:
            break
        c, inside = _carves(views, k, xyz[live], alpha_threshold)
        seen[live[inside]] += 1
        carved[live[c]] = True
        live = live[~c]
    return carved, seen


def visibility(views: Views, xyz: np.ndarray, spacing: float, tolerance: float = 2.0) -> np.ndarray:
    """``[V, N]`` bool: point ``n`` is seen by view ``v`` (z-buffer of the cloud itself, pixels about
    two spacings wide at the cloud's median depth, a point visible within ``tolerance`` spacings of
    its pixel's front-most point)."""
    xyz = np.asarray(xyz, np.float64)
    h, w = views.alpha.shape[1:]
    out = np.zeros((views.num_views, len(xyz)), bool)
    spacing = max(spacing, 1e-12)
    for k in range(views.num_views):
        u, v, depth = views.project(k, xyz)
        front = depth > 1e-6
        if not front.any():
            continue
        # z-buffer pixel: 2 spacings at the median depth (never finer than the image)
        scale = min(1.0, float(np.median(depth[front])) / (2.0 * spacing * views.fx))
        wz, hz = max(1, int(np.ceil(w * scale))), max(1, int(np.ceil(h * scale)))
        iu = np.floor(u * scale).astype(np.int64)
        iv = np.floor(v * scale).astype(np.int64)
        ok = front & (iu >= 0) & (iu < wz) & (iv >= 0) & (iv < hz)
        idx = np.flatnonzero(ok)
        pix = iv[idx] * wz + iu[idx]
        zbuf = np.full(wz * hz, np.inf)
        np.minimum.at(zbuf, pix, depth[idx])
        out[k, idx] = depth[idx] <= zbuf[pix] + tolerance * spacing
    return out


# ----------------------------------------------------------------------------------------------
# Carving
# ----------------------------------------------------------------------------------------------


PHOTO_TOLERANCE = 0.1
"""Photo-consistency: a view agrees with a voxel when its colour (straight RGB in [0, 1]) is within
this of the median colour over the voxel's visible views, in every channel."""
PHOTO_AGREE = 0.6
"""A voxel is photo-consistent when at least this fraction of its visible views agree (robust to
highlights seen in a few views)."""
PHOTO_MIN_VIEWS = 3
"""Voxels visible in fewer views are never removed by photo-consistency."""


@dataclasses.dataclass(frozen=True)
class CarveConfig:
    """Settings of :func:`carve_visual_hull`."""

    resolution: int = 128
    """Voxels per axis ``R`` (the grid is ``R^3`` cubes over ``bounds``)."""
    bounds: tuple[tuple[float, float, float], tuple[float, float, float]] = ((-1.5,) * 3, (1.5,) * 3)
    """``(lo, hi)`` corners of the carved box in world units; must contain the object (NeRF
    Synthetic objects lie in ``[-1.5, 1.5]^3``; the ne_jax benchmark in ``[-1, 1]^3``)."""
    alpha_threshold: float = 0.5
    """Foreground is alpha ``>`` this (0.5 puts the silhouette at the anti-aliased edge)."""
    min_views: int = 2
    """A voxel must lie in at least this many views' frusta to survive (unseen space is dropped)."""
    num_points: int = 100_000
    """Points in the result (shell voxels are sub-sampled, or used several times with jitter)."""
    jitter: float = 1.0
    """Uniform jitter inside the voxel, as a fraction of the voxel size (0: voxel centres)."""
    snap_steps: int = 8
    """Bisection steps moving each point onto the hull surface (0: no snapping)."""
    seed: int = 0
    """Seed of the sub-sampling and jitter."""
    photo_iters: int = 0
    """Photo-consistency sweeps after silhouette carving (0: off; needs ``Views.rgb``). Each sweep
    removes the shell voxels whose colours disagree across the views that see them."""


def _check_cfg(cfg: CarveConfig) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = (np.asarray(b, np.float64) for b in cfg.bounds)
    if lo.shape != (3,) or hi.shape != (3,) or not (np.isfinite(lo).all() and np.isfinite(hi).all()):
        raise ValueError(f"cfg.bounds: expected two finite 3-vectors (lo, hi), found {cfg.bounds!r}")
    if not (hi > lo).all():
        raise ValueError(f"cfg.bounds: expected hi > lo on every axis, found lo={lo.tolist()} hi={hi.tolist()}")
    if int(cfg.resolution) < 2:
        raise ValueError(f"cfg.resolution: expected an integer >= 2, found {cfg.resolution!r}")
    if not 0.0 <= cfg.alpha_threshold < 1.0:
        raise ValueError(f"cfg.alpha_threshold: expected a value in [0, 1), found {cfg.alpha_threshold!r}")
    if int(cfg.num_points) < 1:
        raise ValueError(f"cfg.num_points: expected an integer >= 1, found {cfg.num_points!r}")
    if int(cfg.min_views) < 1:
        raise ValueError(f"cfg.min_views: expected an integer >= 1, found {cfg.min_views!r}")
    if not 0.0 <= cfg.jitter <= 1.0:
        raise ValueError(f"cfg.jitter: expected a fraction in [0, 1], found {cfg.jitter!r}")
    if int(cfg.photo_iters) < 0:
        raise ValueError(f"cfg.photo_iters: expected an integer >= 0, found {cfg.photo_iters!r}")
    return lo, hi


_NEIGHBORS = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]])


def carve_occupancy(cfg: CarveConfig, views: Views) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The carved grid: ``(occupied [R, R, R] bool, seen [R, R, R] int32, voxel_size [3])``, index
    ``[i, j, k]`` the voxel centred at ``lo + (i + 0.5, j + 0.5, k + 0.5) * voxel_size``.

    Raises :class:`CarvingError` when no view has a foreground pixel, when no view has a background
    pixel (nothing to carve with: the images have no masks), or when nothing survives."""
    lo, hi = _check_cfg(cfg)
    fg = views.alpha > cfg.alpha_threshold
    if not fg.any():
        raise CarvingError(
            f"empty masks: no pixel has alpha > {cfg.alpha_threshold} (cfg.alpha_threshold) in any of the "
            f"{views.num_views} views; carving needs foreground masks"
        )
    if fg.all():
        raise CarvingError(
            f"no background: every pixel of all {views.num_views} views has alpha > {cfg.alpha_threshold}; "
            "carving needs masks (RGBA images with a transparent background) or a user's PLY instead"
        )
    r = int(cfg.resolution)
    size = (hi - lo) / r
    axes = [lo[a] + (np.arange(r) + 0.5) * size[a] for a in range(3)]
    centers = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    carved, seen = hull_test(views, centers, cfg.alpha_threshold)
    occupied = (~carved & (seen >= cfg.min_views)).reshape(r, r, r)
    if not occupied.any():
        raise CarvingError(
            f"carving left no voxel of the {r}^3 grid over cfg.bounds={cfg.bounds}: the masks of the "
            f"{views.num_views} views do not agree on a common foreground inside the bounds (wrong cameras, "
            f"bounds missing the object, or cfg.min_views={cfg.min_views} too high)"
        )
    return occupied, seen.reshape(r, r, r).astype(np.int32), size


def shell_voxels(occupied: np.ndarray) -> np.ndarray:
    """``[M, 3]`` int indices of occupied voxels with a non-occupied (or out-of-grid) 6-neighbour."""
    pad = np.pad(occupied, 1, constant_values=False)
    interior = occupied.copy()
    r0, r1, r2 = occupied.shape
    for d in _NEIGHBORS:
        interior &= pad[1 + d[0]: 1 + d[0] + r0, 1 + d[1]: 1 + d[1] + r1, 1 + d[2]: 1 + d[2] + r2]
    return np.argwhere(occupied & ~interior)


def _outward(occupied: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """``[M, 3]`` unit outward directions of shell voxels: the sum of the offsets to their empty
    6-neighbours (zero when they cancel)."""
    pad = np.pad(occupied, 1, constant_values=False)
    out = np.zeros(idx.shape, np.float64)
    for d in _NEIGHBORS:
        nb = idx + 1 + d
        empty = ~pad[nb[:, 0], nb[:, 1], nb[:, 2]]
        out += empty[:, None] * d
    norm = np.linalg.norm(out, axis=1, keepdims=True)
    return np.where(norm > 0, out / np.maximum(norm, 1e-12), 0.0)


def photo_consistency(cfg: CarveConfig, views: Views, occupied: np.ndarray,
                      size: np.ndarray) -> tuple[np.ndarray, dict]:
    """Remove photo-inconsistent shell voxels for ``cfg.photo_iters`` sweeps (or until none is).

    Per sweep: the shell voxels' centres are z-buffered per view (:func:`visibility`, pixels about
    two voxels wide, 1.5 voxels of depth tolerance); each visible view's colour is sampled
    bilinearly (premultiplied by alpha, then divided by it, so the background does not bleed in) at
    the voxel centre moved onto the silhouette hull along its outward direction where the hull
    crosses within the voxel's reach (parallax between views would otherwise mix colours); a voxel
    seen by at least :data:`PHOTO_MIN_VIEWS` views is removed when fewer than
    :data:`PHOTO_AGREE` of them lie within :data:`PHOTO_TOLERANCE` of the median colour. Removing a
    voxel exposes the one behind it to the next sweep, so concavities that silhouettes cannot see
    (a cup's opening) are dug out sweep by sweep.

    Args:
        cfg: :class:`CarveConfig`.
        views: :class:`Views` with ``rgb``.
        occupied: ``[R, R, R]`` bool from :func:`carve_occupancy` (not modified).
        size: ``[3]`` voxel size.

    Returns:
        ``(occupied [R, R, R] bool, info)`` with ``info`` the number removed per sweep.
    """
    if views.rgb is None:
        raise ValueError("views.rgb: photo-consistency (cfg.photo_iters > 0) needs colours, found None")
    lo = np.asarray(cfg.bounds[0], np.float64)
    occupied = occupied.copy()
    removed = []
    for _ in range(int(cfg.photo_iters)):
        shell = shell_voxels(occupied)
        centers = lo + (shell + 0.5) * size
        vis = visibility(views, centers, float(np.max(size)), tolerance=1.5)
        # sample where the surface is: on the silhouette hull where the voxel touches it
        at, _ = _snap(views, centers, _outward(occupied, shell) * size, cfg.alpha_threshold, 6)
        color = np.full((views.num_views, len(shell), 3), np.nan, np.float32)
        for k in range(views.num_views):
            sel = np.flatnonzero(vis[k])
            if sel.size:
                u, v, _ = views.project(k, at[sel])
                a = views.alpha[k]
                premultiplied = bilinear(views.rgb[k] * a[..., None], u, v)
                color[k, sel] = premultiplied / np.maximum(bilinear(a, u, v), 1e-6)[:, None]
        count = vis.sum(0)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns: voxels nobody sees
            median = np.nanmedian(color, axis=0)
        agree = (np.abs(color - median) <= PHOTO_TOLERANCE).all(-1) & vis
        frac = agree.sum(0) / np.maximum(count, 1)
        bad = (count >= PHOTO_MIN_VIEWS) & (frac < PHOTO_AGREE)
        removed.append(int(bad.sum()))
        if not bad.any():
            break
        occupied[tuple(shell[bad].T)] = False
        if not occupied.any():
            raise CarvingError(
                "photo-consistency removed every voxel: colours disagree across views everywhere "
                f"(PHOTO_TOLERANCE={PHOTO_TOLERANCE} too small, or the cameras do not match the images)"
            )
    return occupied, {"photo_removed_per_sweep": removed}


def carve_visual_hull(cfg: CarveConfig, views: Views) -> InitialCloud:
    """Carve, keep the shell, sample ``cfg.num_points`` points and snap them onto the hull.

    Args:
        cfg: :class:`CarveConfig`.
        views: :class:`Views` (e.g. ``Views.from_split(load_split(scene, "train"))``).

    Returns:
        :class:`InitialCloud` with ``xyz`` ``[cfg.num_points, 3]``, ``normals=None``,
        ``source="carving"`` and ``info`` (voxel size, occupied/shell counts, snapped fraction,
        seconds).

    Raises:
        CarvingError: empty masks, no background, or nothing survives (see :func:`carve_occupancy`).
    """
    t0 = time.perf_counter()
    occupied, _, size = carve_occupancy(cfg, views)
    photo_info = {}
    if cfg.photo_iters > 0:
        occupied, photo_info = photo_consistency(cfg, views, occupied, size)
    lo = np.asarray(cfg.bounds[0], np.float64)
    r = occupied.shape[0]
    shell = shell_voxels(occupied)
    if np.any(shell == 0) or np.any(shell == r - 1):
        warnings.warn(
            f"carve_visual_hull: the carved volume touches the boundary of cfg.bounds={cfg.bounds}; "
            "the object may extend beyond it (enlarge the bounds)",
            stacklevel=2,
        )
    rng = np.random.default_rng(cfg.seed)
    n, m = int(cfg.num_points), shell.shape[0]
    reps = -(-n // m)
    pick = np.concatenate([rng.permutation(m) for _ in range(reps)])[:n]
    vox = shell[pick]
    xyz = lo + (vox + 0.5) * size
    xyz = xyz + (rng.random(xyz.shape) - 0.5) * cfg.jitter * size
    snapped = np.zeros(n, bool)
    if cfg.snap_steps > 0:
        direction = _outward(occupied, vox)
        xyz, snapped = _snap(views, xyz, direction * size, cfg.alpha_threshold, int(cfg.snap_steps))
    info = {
        "resolution": r,
        "voxel_size": float(np.max(size)),
        "occupied_voxels": int(occupied.sum()),
        "shell_voxels": int(m),
        "snapped_fraction": float(snapped.mean()),
        "views": views.num_views,
        **photo_info,
        "seconds": time.perf_counter() - t0,
    }
    return InitialCloud(xyz.astype(np.float32), None, "carving", info)


def _snap(views: Views, xyz, step, alpha_threshold, steps) -> tuple[np.ndarray, np.ndarray]:
    """Bisect the hull boundary on ``xyz + t * step``, ``t in [-1, 1.5]``; ``step`` ``[N, 3]`` is the
    outward direction scaled by the voxel size. Returns new points and a ``[N]`` snapped mask.

    Only the *critical* views of a point take part in the bisection: those where the inner end is
    inside the mask and the outer end is carved. Other views cannot change the answer along the
    segment, up to silhouettes that fold within the segment's footprint (a pixel or two)."""
    a, b = xyz - step, xyz + 1.5 * step
    n, nv = len(xyz), views.num_views
    inner_ok = np.linalg.norm(step, axis=1) > 0
    critical = np.zeros((nv, n), bool)
    for k in range(nv):
        carved_a, _ = _carves(views, k, a, alpha_threshold)
        carved_b, _ = _carves(views, k, b, alpha_threshold)
        inner_ok &= ~carved_a
        critical[k] = carved_b
    ok = inner_ok & critical.any(0)
    idx = np.flatnonzero(ok)
    lo, hi = a[idx], b[idx]
    pairs = [np.flatnonzero(critical[k, idx]) for k in range(nv)]
    for _ in range(steps):
        mid = 0.5 * (lo + hi)
        out = np.zeros(len(idx), bool)
        for k, sel in enumerate(pairs):
            if sel.size:
                c, _ = _carves(views, k, mid[sel], alpha_threshold)
                out[sel[c]] = True
        lo = np.where(out[:, None], lo, mid)
        hi = np.where(out[:, None], mid, hi)
    result = xyz.copy()
    result[idx] = 0.5 * (lo + hi)
    return result, ok


# ----------------------------------------------------------------------------------------------
# Clouds from files
# ----------------------------------------------------------------------------------------------


def _cloud_from_ply(path: Path, source: str) -> InitialCloud:
    try:
        cols = read_ply(path)
    except PlyError:
        raise
    except (OSError, ValueError, UnicodeDecodeError) as e:
        raise PlyError(f"{path}: cannot be read as PLY ({e})") from None
    missing = [c for c in "xyz" if c not in cols]
    if missing:
        raise PlyError(
            f"{path}: expected vertex properties x, y, z; missing {', '.join(missing)} "
            f"(found {', '.join(sorted(cols)) or 'none'})"
        )
    xyz = np.stack([cols[c] for c in "xyz"], 1).astype(np.float64)
    if xyz.shape[0] == 0:
        raise PlyError(f"{path}: expected at least one vertex, found 0")
    bad = ~np.isfinite(xyz).all(1)
    if bad.any():
        rows = np.flatnonzero(bad)
        raise PlyError(
            f"{path}: expected finite x, y, z; found {rows.size} vertex(es) with NaN/inf "
            f"(first at index {int(rows[0])}: {xyz[rows[0]].tolist()})"
        )
    normals = None
    if all(f"n{c}" in cols for c in "xyz"):
        nrm = np.stack([cols[f"n{c}"] for c in "xyz"], 1).astype(np.float64)
        length = np.linalg.norm(nrm, axis=1, keepdims=True)
        if np.isfinite(nrm).all() and (length > 1e-6).all():
            normals = (nrm / length).astype(np.float32)
        else:
            warnings.warn(f"{path}: normals nx, ny, nz have NaN/inf or zero rows; ignored", stacklevel=3)
    return InitialCloud(xyz.astype(np.float32), normals, source, {"points": int(xyz.shape[0])})


def load_ply_cloud(path: str | os.PathLike) -> InitialCloud:
    """A user's point cloud from a PLY file (properties ``x, y, z``; ``nx, ny, nz`` used when present
    and valid). ``source`` is ``"ply:<path>"``.

    Raises:
        PlyError: the file is missing or not PLY, lacks ``x``/``y``/``z``, has no vertex, or has a
            non-finite coordinate — the message names the file.
    """
    path = Path(path)
    if not path.is_file():
        raise PlyError(f"point cloud PLY file not found: {path}")
    return _cloud_from_ply(path, f"ply:{path}")


def ground_truth_cloud(scene_dir: str | os.PathLike) -> InitialCloud:
    """The benchmark's ground-truth surface samples (``<scene_dir>/points.ply``) with their normals,
    labelled ``source=GT_SOURCE``. Use only when the user asks for it; results made from it must say
    so (``InitialCloud.is_ground_truth``)."""
    path = Path(scene_dir) / "points.ply"
    if not path.is_file():
        raise PlyError(
            f"ground-truth surface samples not found: {path} (only scenes made by "
            "ne_jax.benchmark.generate have them)"
        )
    return _cloud_from_ply(path, GT_SOURCE)

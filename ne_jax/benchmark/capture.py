"""The capture variant of the benchmark: the path-traced scenes as a real capture looks, written in
the layouts real captures come in (presets ``tiny_capture``, ``default_capture``).

What differs from the path-traced variant (:mod:`ne_jax.benchmark.pathtracer`, ``*_pt``):

* **The environment is visible** behind the objects and the images are opaque RGB (no alpha).
* **A ground** (:class:`Ground`) under the objects: a diffuse square of ``2 x GROUND_HALF_SIZE``
  units at ``GROUND_GAP`` below the objects' lowest point, tiled in ``GROUND_CELL`` cells in two
  tones of a checker with a per-cell brightness and hue jitter (a texture SfM can match, and a
  background that is part of the scene).
* **Cameras above the ground**: the training views are random on the benchmark's sphere (radius
  4, looking at the origin) between :data:`MIN_ELEVATION` and 75 degrees of elevation (the ``*_pt``
  presets go down to -15 degrees, under the ground); the test views are the same 25-degree orbit.
  There is no validation split. Train and test views are interleaved in one sequence of images
  named ``frame_00001.png, ...`` so that holding out every 8th image of the sorted names (indices
  0, 8, 16, ...; the LLFF convention the loaders use for formats without a split) gives exactly
  the test views, in orbit order (:func:`view_order`).
* **Edits move the objects, the ground stays** (:func:`objects_only`): an edit acts on the points
  above ``ground.objects_above`` (half the gap above the ground) and leaves the ground, so a part
  an edit pushes down (a cut's lower half, a turn) goes into the ground. The whole-scene turns turn
  the objects (and, for ``turn_with_light``, the environment) but not the ground.
  :func:`ne_jax.benchmark.edits.benchmark_edit` returns the restricted edit for a capture scene.

World frame: **the capture's world frame is the benchmark's** (z up, the objects inside
``[-1, 1]^3`` about the origin, cameras 4 units from it): no normalisation is applied to the
cameras, the points or the edits' ground truth; a loader normalises on its own side.

Layout of ``<root>`` (one scene)::

    <scene>/images/frame_00001.png ...    opaque RGB, train and test views interleaved (view_order)
    <scene>/sparse/0/cameras.txt          COLMAP text model: one PINHOLE camera,
    <scene>/sparse/0/images.txt           world-to-camera poses (QW QX QY QZ TX TY TZ, OpenCV axes)
                                          and each image's 2-D observations (X Y POINT3D_ID),
    <scene>/sparse/0/points3D.txt         the simulated SfM cloud (below) with RGB, error and tracks
    <scene>/points.ply                    the objects' ground-truth surface samples (as every variant)
    <scene>/scene.json                    what was made: preset, ground, split, SfM parameters, edits
    <scene>/unedited/transforms_test.json the test views in the NeRF Synthetic layout (naming
                                          ../images/...), for tools that read that layout
    <scene>/edits/<edit>/                 an edit's ground truth, NeRF Synthetic layout:
                                          transforms_{train,test}.json, {train,test}/r_<i>.png (RGBA,
                                          alpha 1), points.ply, scene.json (``capture_frame: "../.."``);
                                          the test views are the capture's, the training views its
                                          first ``preset.edit_train_views`` (24 at tiny, 100 at default)
    <scene>_ns/transforms.json            the same scene for nerfstudio: PINHOLE fl_x fl_y cx cy w h,
                                          frames[].file_path images/<name>.png, transform_matrix
                                          (camera-to-world, OpenGL axes), ply_file_path sparse_pc.ply
    <scene>_ns/sparse_pc.ply              the same simulated points (x y z double, red green blue uchar)
    <scene>_ns/images/, edits/, points.ply  hard links to the COLMAP folder's files (copies where
                                          hard links fail); scene.json says ``copy_of``

**The SfM simulation** (:class:`SfMSimulation`, :func:`simulate_sfm`; its defaults are the
presets'): ``points`` = 4,000 points in all. Candidates are drawn area-uniformly on the objects and
on a disc of radius ``ground_radius`` = 3 of the ground; a candidate is kept only if at least
``min_views`` = 2 images see it (inside the image, unoccluded by a ray cast, viewed less than
~80 degrees off its normal). Of the inliers, ``object_share`` = 50% lie on the objects and the rest
on the ground, each drawn with a weight ``flat_weight + (1 - flat_weight) min(1, contrast /
contrast_full)`` (``flat_weight`` = 0.1, ``contrast_full`` = 0.15), ``contrast`` the luminance range
of the albedo within 1.5 pixel footprints of the point: denser where texture is. Each inlier is
moved by isotropic Gaussian noise of ``noise_px`` = 1 pixel footprint per axis (the width of a
pixel 4 units from the camera: 0.045 at 64 px, 0.014 at 200 px); its track is every image that
sees it, with observed keypoints at its true projection plus ``keypoint_px`` = 0.5 px Gaussian
noise, and its error the RMS reprojection error of the noisy point against them (about 1.5 px).
``outlier_share`` = 3% of the points are outliers, uniform in the inliers' bounding box grown by
``outlier_margin`` = 0.25 on each side, each with a track of 2-3 images it projects into
(keypoints ``outlier_px`` = 2 px off) and an inlier's colour. Colours are the surface albedo
(sRGB) at the true position. The points are shuffled (outliers are not last).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ne_jax.atomic import atomic_directory, atomic_write_json, atomic_write_text
from ne_jax.benchmark import meshes as M
from ne_jax.benchmark import scenes as S
from ne_jax.data import cameras
from ne_jax.data.nerf_synthetic import write_split
from ne_jax.data.ply import write_ply
from ne_jax.data.png import encode_png, quantise

GROUND_GAP = 0.02
"""The ground lies this far below the objects' lowest point (world units)."""
GROUND_HALF_SIZE = 12.0
"""Half the side of the square ground (world units, centred under the origin)."""
GROUND_CELL = 0.2
"""Side of one ground tile (world units; 4.4 px at 64 px and 14 px at 200 px at the target's distance)."""
GROUND_TONES = ((0.62, 0.58, 0.52), (0.34, 0.32, 0.30))
"""sRGB albedo of the checker's two tones."""
GROUND_JITTER = (0.2, 0.025)
"""Per-cell brightness jitter (a factor in ``1 +- 0.2``) and per-channel hue jitter (+- 0.025)."""
MIN_ELEVATION = 5.0
"""Lowest elevation of the random training cameras (degrees): above the ground."""
MAX_ELEVATION = 75.0
HOLDOUT_EVERY = 8
"""Every 8th image (sorted by name, from index 0) is a test view (the LLFF convention)."""


# ------------------------------------------------------------------------------------- ground


@dataclass(frozen=True)
class Ground:
    """The ground plane ``z = z``: a square of side ``2 half_size`` of ``cell``-sized tiles."""

    z: float
    half_size: float = GROUND_HALF_SIZE
    cell: float = GROUND_CELL

    @property
    def objects_above(self) -> float:
        """Edits act on points above this height (half the gap between the ground and the objects)."""
        return self.z + 0.5 * GROUND_GAP

    def albedo(self, p: np.ndarray) -> np.ndarray:
        """sRGB albedo ``[n, 3]`` of the ground at points ``p [n, 3]`` (only ``x``, ``y`` matter)."""
        i = np.floor(np.asarray(p)[:, 0] / self.cell).astype(np.int64)
        j = np.floor(np.asarray(p)[:, 1] / self.cell).astype(np.int64)
        tones = np.asarray(GROUND_TONES, np.float64)
        base = tones[(i + j) % 2]
        bright, hue = GROUND_JITTER
        scale = 1.0 + bright * (2.0 * _cell_hash(i, j, 0) - 1.0)
        tint = np.stack([hue * (2.0 * _cell_hash(i, j, c) - 1.0) for c in (1, 2, 3)], axis=1)
        return np.clip(base * scale[:, None] + tint, 0.0, 1.0)

    def part(self):
        """The ground as a :class:`~ne_jax.benchmark.pathtracer.FlatPart`: each tile its own four
        vertices of the tile's colour (a diffuse surface)."""
        from ne_jax.benchmark.pathtracer import FlatPart, Surface

        n = int(round(2 * self.half_size / self.cell))
        lo = -0.5 * n * self.cell
        ii, jj = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
        x0, y0 = lo + ii.ravel() * self.cell, lo + jj.ravel() * self.cell
        corners = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float64) * self.cell
        xy = np.stack([x0, y0], 1)[:, None, :] + corners[None]  # [cells, 4, 2]
        vertices = np.concatenate([xy, np.full(xy.shape[:2] + (1,), self.z)], -1).reshape(-1, 3)
        base = 4 * np.arange(n * n)[:, None]
        faces = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]]).astype(np.int64)  # counter-clockwise: +z
        centres = np.stack([x0 + 0.5 * self.cell, y0 + 0.5 * self.cell, np.full(n * n, self.z)], 1)
        albedo = np.repeat(self.albedo(centres), 4, axis=0)
        return FlatPart(vertices, faces, albedo, Surface("diffuse"))

    def quad(self) -> tuple[np.ndarray, np.ndarray]:
        """The ground as two triangles ``(vertices [4, 3], faces [2, 3])`` (for ray casting)."""
        h = self.half_size
        v = np.array([[-h, -h, self.z], [h, -h, self.z], [h, h, self.z], [-h, h, self.z]], np.float64)
        return v, np.array([[0, 1, 2], [0, 2, 3]], np.int64)

    def record(self) -> dict:
        return {"z": self.z, "objects_above": self.objects_above, "half_size": self.half_size, "cell": self.cell,
                "surface": "diffuse, a two-tone checker of tiles with a per-tile brightness and hue jitter"}


def _cell_hash(i: np.ndarray, j: np.ndarray, channel: int) -> np.ndarray:
    """A deterministic number in ``[0, 1)`` per integer cell ``(i, j)`` and ``channel``."""
    h = (i.astype(np.uint64) * np.uint64(73856093)) ^ (j.astype(np.uint64) * np.uint64(19349663))
    h = (h + np.uint64(channel * 83492791 + 1)) * np.uint64(0x9E3779B97F4A7C15)
    h ^= h >> np.uint64(29)
    return (h % np.uint64(1 << 24)).astype(np.float64) / float(1 << 24)


def ground_for(scene: S.Scene) -> Ground:
    """The ground of ``scene``: :data:`GROUND_GAP` below its mesh's lowest vertex."""
    return Ground(z=float(np.round(scene.mesh.vertices[:, 2].min() - GROUND_GAP, 6)))


# -------------------------------------------------------------------------------------- edits


def objects_only(edit, above_z: float):
    """``edit`` acting only on points above ``above_z`` (the objects); the ground below stays, and
    nothing there is deleted. A whole-scene turn becomes a turn of the objects (no ``rigid``
    motion of the whole scene), keeping its ``kind`` and ``moves_environment``."""
    import jax.numpy as jnp

    from ne_jax.edit.deformations import Edit

    z = float(above_z)

    def move(p):
        return jnp.where((p[:, 2] > z)[:, None], edit.move(p), p)

    delete = None
    if edit.delete is not None:
        def delete(p):
            return edit.delete(p) & (p[:, 2] > z)

    return Edit(edit.name, edit.kind, move, delete,
                description=f"{edit.description}; only above z = {z:g} (the ground stays)",
                moves_environment=edit.moves_environment)


# ------------------------------------------------------------------------------------- cameras


def view_order(train_views: int, test_views: int) -> list[tuple[str, int]]:
    """``(split, index)`` of each image in name order: position ``k`` is test view ``k // 8`` when
    ``k % 8 == 0``, else the next training view. Raises ``ValueError`` unless holding out every
    8th image gives exactly ``test_views`` (``ceil((train + test) / 8) == test``)."""
    n = train_views + test_views
    if test_views < 1 or -(-n // HOLDOUT_EVERY) != test_views:
        raise ValueError(f"capture views: holding out every {HOLDOUT_EVERY}th of {n} images gives "
                         f"{-(-n // HOLDOUT_EVERY)} test views, not {test_views}; expected "
                         f"{7 * test_views - 7 + 1}..{7 * test_views} training views for {test_views} test views")
    order, train = [], 0
    for k in range(n):
        if k % HOLDOUT_EVERY == 0:
            order.append(("test", k // HOLDOUT_EVERY))
        else:
            order.append(("train", train))
            train += 1
    return order


def image_name(k: int) -> str:
    """The file name of image ``k`` (0-based) of a capture: ``frame_00001.png``, ..."""
    return f"frame_{k + 1:05d}.png"


@dataclass(frozen=True)
class Pinhole:
    """One pinhole camera in pixels (pixel centres at ``i + 0.5``, COLMAP's convention)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @classmethod
    def benchmark(cls, resolution: int) -> Pinhole:
        """The benchmark's camera (NeRF Synthetic's field of view) at ``resolution`` px."""
        f = 0.5 * resolution / math.tan(0.5 * cameras.CAMERA_ANGLE_X)
        return cls(resolution, resolution, f, f, 0.5 * resolution, 0.5 * resolution)

    def project(self, c2w_gl: np.ndarray, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(pixels [n, 2], depth [n])`` of world points ``xyz [n, 3]`` in the camera ``c2w_gl``
        (OpenGL camera-to-world); ``depth`` > 0 in front of the camera."""
        local = (np.asarray(xyz, np.float64) - c2w_gl[:3, 3]) @ c2w_gl[:3, :3]  # OpenGL camera axes
        depth = -local[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = self.cx + self.fx * local[:, 0] / depth
            v = self.cy - self.fy * local[:, 1] / depth
        return np.stack([u, v], 1), depth

    def inside(self, pixels: np.ndarray, depth: np.ndarray) -> np.ndarray:
        return ((depth > 1e-6) & (pixels[:, 0] >= 0) & (pixels[:, 0] < self.width)
                & (pixels[:, 1] >= 0) & (pixels[:, 1] < self.height))


def world_to_camera_opencv(c2w_gl: np.ndarray) -> np.ndarray:
    """COLMAP's pose ``[4, 4]``: world-to-camera with OpenCV camera axes, of an OpenGL camera-to-world."""
    c2w_cv = np.asarray(c2w_gl, np.float64) @ np.diag([1.0, -1.0, -1.0, 1.0])
    w2c = np.eye(4)
    w2c[:3, :3] = c2w_cv[:3, :3].T
    w2c[:3, 3] = -c2w_cv[:3, :3].T @ c2w_cv[:3, 3]
    return w2c


def rotation_to_quaternion(rot: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(w, x, y, z)`` with ``w >= 0`` of a rotation matrix ``[3, 3]`` (Bar-Itzhack:
    the eigenvector of the largest eigenvalue of a symmetric 4x4, robust for any angle)."""
    m = np.asarray(rot, np.float64)
    k = np.array([
        [m[0, 0] - m[1, 1] - m[2, 2], m[1, 0] + m[0, 1], m[2, 0] + m[0, 2], m[2, 1] - m[1, 2]],
        [m[1, 0] + m[0, 1], m[1, 1] - m[0, 0] - m[2, 2], m[2, 1] + m[1, 2], m[0, 2] - m[2, 0]],
        [m[2, 0] + m[0, 2], m[2, 1] + m[1, 2], m[2, 2] - m[0, 0] - m[1, 1], m[1, 0] - m[0, 1]],
        [m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1], m[0, 0] + m[1, 1] + m[2, 2]],
    ]) / 3.0
    _, vecs = np.linalg.eigh(k)
    x, y, z, w = vecs[:, -1]
    q = np.array([w, x, y, z])
    q /= np.linalg.norm(q)
    return -q if q[0] < 0 else q


# ---------------------------------------------------------------------------- SfM simulation


@dataclass(frozen=True)
class SfMSimulation:
    """How the simulated SfM cloud is made (module docstring)."""

    points: int = 4000
    """Points in all (inliers and outliers)."""
    outlier_share: float = 0.03
    """Share of the points that are outliers (uniform in a box around the scene)."""
    object_share: float = 0.5
    """Share of the inliers on the objects (the rest on the ground)."""
    noise_px: float = 1.0
    """Standard deviation of the inliers' 3-D noise per axis, in pixel footprints at the target."""
    keypoint_px: float = 0.5
    """Standard deviation of an inlier's observed keypoints about its true projection (pixels)."""
    outlier_px: float = 2.0
    """Standard deviation of an outlier's keypoints about its projection (pixels)."""
    flat_weight: float = 0.1
    """Selection weight of a candidate on a flat (untextured) surface; a textured one has 1."""
    contrast_full: float = 0.15
    """Albedo luminance range (within 1.5 pixel footprints) at which a candidate gets weight 1."""
    ground_radius: float = 3.0
    """Ground candidates lie within this distance of the vertical axis through the origin."""
    outlier_margin: float = 0.25
    """The outliers' box: the inliers' bounding box grown by this much on each side (world units)."""
    min_views: int = 2
    """A candidate seen by fewer images is not a point."""
    candidates_per_point: int = 8
    """Candidates drawn per point wanted (before visibility and the texture weights)."""

    def __post_init__(self):
        if self.points < 1 or not 0.0 <= self.outlier_share < 1.0 or not 0.0 <= self.object_share <= 1.0:
            raise ValueError(f"SfMSimulation: expected points >= 1 and shares in [0, 1), found {self}")


@dataclass(frozen=True, eq=False)
class SfMPoints:
    """A simulated SfM cloud: ``xyz [P, 3]`` float64 (noisy), ``rgb [P, 3]`` uint8, ``error [P]``
    (RMS reprojection error, pixels), ``outlier [P]`` bool, and per point its track: the indices of
    the images that observe it (``track_images``, into the capture's name-ordered views) and the
    observed keypoints ``track_xy [k, 2]`` (pixels); ``sigma`` is the inliers' noise per axis
    (world units), ``truth [P, 3]`` the inliers' positions before the noise (outliers: their own)."""

    xyz: np.ndarray
    rgb: np.ndarray
    error: np.ndarray
    outlier: np.ndarray
    track_images: tuple[np.ndarray, ...]
    track_xy: tuple[np.ndarray, ...]
    sigma: float
    truth: np.ndarray

    def record(self) -> dict:
        lengths = [len(t) for t in self.track_images]
        return {"points": int(len(self.xyz)), "outliers": int(self.outlier.sum()), "sigma": self.sigma,
                "mean_track_length": round(float(np.mean(lengths)), 3),
                "mean_error_px": round(float(np.mean(self.error)), 4)}


def _luminance(rgb: np.ndarray) -> np.ndarray:
    return rgb @ np.array([0.2126, 0.7152, 0.0722])


def _tangents(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    helper = np.where(np.abs(normal[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    t1 = np.cross(normal, helper)
    t1 /= np.maximum(np.linalg.norm(t1, axis=1, keepdims=True), 1e-12)
    return t1, np.cross(normal, t1)


def _contrast(albedo_fn, idx: np.ndarray, xyz: np.ndarray, normal: np.ndarray, radius: float) -> np.ndarray:
    """Luminance range ``[n]`` of the albedo ``albedo_fn(idx, p)`` of candidates ``idx [n]`` at their
    positions ``xyz [n, 3]`` and four points ``radius`` away in the tangent plane."""
    t1, t2 = _tangents(normal)
    lum = [_luminance(albedo_fn(idx, xyz))]
    for t in (t1, -t1, t2, -t2):
        lum.append(_luminance(albedo_fn(idx, xyz + radius * t)))
    lum = np.stack(lum, 1)
    return lum.max(1) - lum.min(1)


def _scene_albedo(scene: S.Scene, material: np.ndarray):
    """sRGB albedo ``fn(p [n, 3]) -> [n, 3]`` of points of the given ``material [n]``."""
    def fn(p):
        out = np.zeros_like(p)
        for i, m in enumerate(scene.materials):
            sel = material == i
            if sel.any():
                out[sel] = m.albedo(p[sel])
        return np.clip(out, 0.0, 1.0)
    return fn


def visibility(caster, camera: Pinhole, c2ws: np.ndarray, xyz: np.ndarray, normal: np.ndarray,
               tolerance: float = 2e-3, min_cos: float = 0.17) -> tuple[np.ndarray, np.ndarray]:
    """``(seen [C, n] bool, pixels [C, n, 2])``: which cameras see each surface point (inside the
    image, the first surface along the ray, viewed within ~80 degrees of its normal, either side)."""
    seen = np.zeros((len(c2ws), len(xyz)), bool)
    pixels = np.zeros((len(c2ws), len(xyz), 2))
    for c, c2w in enumerate(np.asarray(c2ws, np.float64)):
        px, depth = camera.project(c2w, xyz)
        pixels[c] = px
        todo = np.nonzero(camera.inside(px, depth))[0]
        v = xyz[todo] - c2w[:3, 3]
        dist = np.linalg.norm(v, axis=1)
        d = v / dist[:, None]
        facing = np.abs(np.sum(d * normal[todo], axis=1)) > min_cos
        todo, d, dist = todo[facing], d[facing], dist[facing]
        if len(todo):
            t_hit = caster.hit_distance(np.broadcast_to(c2w[:3, 3], d.shape), d)
            seen[c, todo[t_hit >= dist - tolerance]] = True
    return seen, pixels


def _caster(scene: S.Scene, ground: Ground):
    from ne_jax.benchmark.raycaster import RayCaster

    gv, gf = ground.quad()
    verts = np.concatenate([scene.mesh.vertices, gv])
    faces = np.concatenate([scene.mesh.faces, gf + len(scene.mesh.vertices)])
    material = np.concatenate([scene.mesh.material, np.full(len(gf), len(scene.materials))])
    return RayCaster(S.EditedMesh(verts, verts, faces, material), scene.materials)


def simulate_sfm(scene: S.Scene, ground: Ground, c2ws: np.ndarray, camera: Pinhole, rng: np.random.Generator,
                 config: SfMSimulation = SfMSimulation()) -> SfMPoints:
    """A simulated SfM cloud of ``scene`` on ``ground`` seen by the cameras ``c2ws [C, 4, 4]``
    (OpenGL camera-to-world, in the capture's name order); see the module docstring."""
    c2ws = np.asarray(c2ws, np.float64)
    footprint = cameras.CAMERA_RADIUS / camera.fx  # a pixel's width at the cameras' target
    sigma = config.noise_px * footprint
    n_out = int(round(config.outlier_share * config.points))
    n_in = config.points - n_out
    n_obj = int(round(config.object_share * n_in))
    groups = {"objects": n_obj, "ground": n_in - n_obj}
    caster = _caster(scene, ground)

    # candidates on the objects and on the ground disc
    k = config.candidates_per_point
    face, bary = M.sample_surface(scene.mesh, max(1, k * n_obj), rng)
    obj_xyz = M.interpolate(scene.mesh.vertices, scene.mesh.faces, face, bary)
    obj_normal, _ = M.face_normals(scene.mesh.vertices, scene.mesh.faces[face])
    obj_material = scene.mesh.material[face]
    n_g = max(1, k * groups["ground"])
    r = config.ground_radius * np.sqrt(rng.random(n_g))
    theta = rng.uniform(0.0, 2.0 * np.pi, n_g)
    gnd_xyz = np.stack([r * np.cos(theta), r * np.sin(theta), np.full(n_g, ground.z)], 1)
    gnd_normal = np.broadcast_to([0.0, 0.0, 1.0], gnd_xyz.shape).copy()
    candidates = {  # (xyz, normal, albedo of candidates idx at points p)
        "objects": (obj_xyz, obj_normal, lambda idx, p: _scene_albedo(scene, obj_material[idx])(p)),
        "ground": (gnd_xyz, gnd_normal, lambda idx, p: ground.albedo(p)),
    }

    truth, colours, tracks, observed = [], [], [], []
    for group, (xyz, normal, albedo_fn) in candidates.items():
        want = groups[group]
        if want == 0:
            continue
        seen, pixels = visibility(caster, camera, c2ws, xyz, normal)
        ok = np.nonzero(seen.sum(0) >= config.min_views)[0]
        contrast = _contrast(albedo_fn, ok, xyz[ok], normal[ok], 1.5 * footprint)
        weight = config.flat_weight + (1.0 - config.flat_weight) * np.minimum(1.0, contrast / config.contrast_full)
        take = ok[rng.choice(len(ok), size=min(want, len(ok)), replace=False, p=weight / weight.sum())]
        truth.append(xyz[take])
        colours.append(albedo_fn(take, xyz[take]))
        for i in take:
            cams = np.nonzero(seen[:, i])[0]
            tracks.append(cams)
            observed.append(pixels[cams, i] + rng.normal(0.0, config.keypoint_px, (len(cams), 2)))
    truth = np.concatenate(truth)
    noisy = truth + rng.normal(0.0, sigma, truth.shape)
    n_inliers = len(truth)

    # outliers: uniform in a box around the scene, each seen (falsely) by 2-3 images it projects into
    lo, hi = truth.min(0) - config.outlier_margin, truth.max(0) + config.outlier_margin
    out_xyz = []
    while len(out_xyz) < n_out:
        p = rng.uniform(lo, hi)
        inside = [c for c, c2w in enumerate(c2ws) if camera.inside(*camera.project(c2w, p[None]))[0]]
        if len(inside) < 2:
            continue
        cams = np.sort(rng.choice(inside, size=min(len(inside), int(rng.integers(2, 4))), replace=False))
        px = np.stack([camera.project(c2ws[c], p[None])[0][0] for c in cams])
        out_xyz.append(p)
        tracks.append(cams)
        observed.append(px + rng.normal(0.0, config.outlier_px, px.shape))
    out_xyz = np.asarray(out_xyz, np.float64).reshape(-1, 3)
    xyz = np.concatenate([noisy, out_xyz])
    truth = np.concatenate([truth, out_xyz])
    colours = np.concatenate(colours + [np.concatenate(colours)[rng.integers(0, n_inliers, n_out)]])
    outlier = np.arange(len(xyz)) >= n_inliers

    projected = np.stack([camera.project(c2w, xyz)[0] for c2w in c2ws])  # [C, P, 2]
    error = np.array([np.sqrt(np.mean(np.sum((projected[cams, i] - obs) ** 2, axis=1)))
                      for i, (cams, obs) in enumerate(zip(tracks, observed))])

    order = rng.permutation(len(xyz))
    return SfMPoints(
        xyz=xyz[order], rgb=np.round(np.clip(colours[order], 0, 1) * 255).astype(np.uint8), error=error[order],
        outlier=outlier[order], track_images=tuple(tracks[i] for i in order),
        track_xy=tuple(observed[i] for i in order), sigma=float(sigma), truth=truth[order])


# ----------------------------------------------------------------------------------- writers


def _f(x: float) -> str:
    return repr(float(x))


def write_colmap_text(model_dir: str | os.PathLike, names: list[str], c2ws: np.ndarray, camera: Pinhole,
                      sfm: SfMPoints) -> Path:
    """Write a COLMAP text model (``cameras.txt``, ``images.txt``, ``points3D.txt``) to ``model_dir``:
    one PINHOLE camera (id 1), image ``k`` (id ``k + 1``) named ``names[k]`` at the OpenGL
    camera-to-world ``c2ws[k]`` (written world-to-camera, OpenCV axes), and the points of ``sfm``
    (ids from 1) with their tracks and each image's observations. Returns ``model_dir``."""
    model_dir = Path(model_dir)
    model_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(model_dir / "cameras.txt", "\n".join([
        "# Camera list with one line of data per camera:",
        "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
        "# Number of cameras: 1",
        f"1 PINHOLE {camera.width} {camera.height} {_f(camera.fx)} {_f(camera.fy)} {_f(camera.cx)} {_f(camera.cy)}",
        ""]))
    observations: list[list[str]] = [[] for _ in names]
    point_lines = []
    for pid, (xyz, rgb, err, cams, obs) in enumerate(
            zip(sfm.xyz, sfm.rgb, sfm.error, sfm.track_images, sfm.track_xy), start=1):
        track = []
        for c, (x, y) in zip(cams, obs):
            track.append(f"{int(c) + 1} {len(observations[c]) // 3}")
            observations[c] += [_f(x), _f(y), str(pid)]
        point_lines.append(" ".join([str(pid), _f(xyz[0]), _f(xyz[1]), _f(xyz[2]), str(int(rgb[0])),
                                     str(int(rgb[1])), str(int(rgb[2])), _f(err)] + track))
    n_obs = sum(len(o) // 3 for o in observations)
    image_lines = [
        "# Image list with two lines of data per image:",
        "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
        "#   POINTS2D[] as (X, Y, POINT3D_ID)",
        f"# Number of images: {len(names)}, mean observations per image: {n_obs / max(1, len(names)):g}",
    ]
    for k, (name, c2w) in enumerate(zip(names, np.asarray(c2ws, np.float64))):
        w2c = world_to_camera_opencv(c2w)
        q, t = rotation_to_quaternion(w2c[:3, :3]), w2c[:3, 3]
        image_lines.append(" ".join([str(k + 1)] + [_f(v) for v in (*q, *t)] + ["1", name]))
        image_lines.append(" ".join(observations[k]))
    atomic_write_text(model_dir / "images.txt", "\n".join(image_lines) + "\n")
    mean_track = float(np.mean([len(t) for t in sfm.track_images])) if len(sfm.xyz) else 0.0
    atomic_write_text(model_dir / "points3D.txt", "\n".join([
        "# 3D point list with one line of data per point:",
        "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
        f"# Number of points: {len(sfm.xyz)}, mean track length: {mean_track:g}"] + point_lines) + "\n")
    return model_dir


def write_points_ply(path: str | os.PathLike, sfm: SfMPoints) -> None:
    """The SfM points as a PLY (``x y z`` double, ``red green blue`` uchar), nerfstudio's ``sparse_pc.ply``."""
    write_ply(path, {"x": sfm.xyz[:, 0], "y": sfm.xyz[:, 1], "z": sfm.xyz[:, 2],
                     "red": sfm.rgb[:, 0], "green": sfm.rgb[:, 1], "blue": sfm.rgb[:, 2]})


def nerfstudio_transforms(names: list[str], c2ws: np.ndarray, camera: Pinhole,
                          ply_file_path: str | None = "sparse_pc.ply") -> dict:
    """nerfstudio's ``transforms.json`` content: one PINHOLE camera, ``frames[].file_path``
    ``images/<name>``, ``transform_matrix`` the OpenGL camera-to-world as given (no re-orienting)."""
    meta = {"camera_model": "PINHOLE", "fl_x": camera.fx, "fl_y": camera.fy, "cx": camera.cx, "cy": camera.cy,
            "w": camera.width, "h": camera.height,
            "frames": [{"file_path": f"images/{name}", "transform_matrix": np.asarray(c2w, np.float64).tolist(),
                        "colmap_im_id": k + 1} for k, (name, c2w) in enumerate(zip(names, c2ws))]}
    if ply_file_path is not None:
        meta["ply_file_path"] = ply_file_path
    return meta


def _link_tree(src: Path, dst: Path) -> None:
    """``dst`` a tree of hard links to the files under ``src`` (copies where a link fails)."""
    for path in sorted(src.rglob("*")):
        target = dst / path.relative_to(src)
        if path.is_dir():
            target.mkdir(parents=True, exist_ok=True)
            continue
        target.parent.mkdir(parents=True, exist_ok=True)
        _link_or_copy(path, target)


def _link_or_copy(src: Path, dst: Path) -> None:
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def write_nerfstudio_copy(scene_dir: str | os.PathLike, ns_dir: str | os.PathLike | None = None) -> Path:
    """The nerfstudio copy ``<scene>_ns`` of a finished capture scene folder ``scene_dir`` (COLMAP
    layout, written by :func:`generate_scene`): ``transforms.json`` from the same cameras (read
    back from ``scene.json``), ``sparse_pc.ply`` the same points, ``images/``, ``edits/`` and
    ``points.ply`` hard-linked. Written atomically; returns its path."""
    scene_dir = Path(scene_dir)
    ns_dir = scene_dir.with_name(scene_dir.name + "_ns") if ns_dir is None else Path(ns_dir)
    meta = json.loads((scene_dir / "scene.json").read_text(encoding="utf-8"))
    cap = meta["capture"]
    camera = Pinhole(**cap["camera"])
    names, c2ws = cap["images"], np.asarray(cap["c2w"], np.float64)
    with atomic_directory(ns_dir) as out:
        atomic_write_json(out / "transforms.json", nerfstudio_transforms(names, c2ws, camera))
        for name in ("sparse_pc.ply", "points.ply"):
            _link_or_copy(scene_dir / name, out / name)
        _link_tree(scene_dir / "images", out / "images")
        if (scene_dir / "edits").is_dir():
            _link_tree(scene_dir / "edits", out / "edits")
        copy = dict(meta, layout="nerfstudio", copy_of=f"../{scene_dir.name}")
        atomic_write_json(out / "scene.json", copy)
    return ns_dir


# --------------------------------------------------------------------------------- rendering


def _tracer(scene: S.Scene, ground: Ground, edit, environment, preset):
    """``render(c2w, seed) -> [H, W, 4]`` (alpha 1) of ``scene`` under ``edit`` (already restricted to
    the objects, or ``None``) on ``ground``, environment visible; and its description."""
    from ne_jax.benchmark import pathtracer as P

    mesh = S.apply_to_mesh(scene.mesh, edit)
    surfaces = (tuple(P.Surface("diffuse") for _ in scene.materials) if preset.matte
                else P.scene_surfaces(scene.name, scene.materials))
    res, angle = preset.resolution, cameras.CAMERA_ANGLE_X
    tracer = P.PathTracer(mesh, scene.materials, surfaces, environment,
                          max_edge=P.pixel_footprint(res, angle), spp=preset.spp,
                          extra_parts=(ground.part(),), visible_environment=True)

    def render(c2w, seed):
        img = tracer.render(c2w, res, res, angle, seed=seed)
        img[..., 3] = 1.0  # the environment is visible: every pixel is opaque
        return img

    description = (f"mitsuba {tracer.mi.__version__} {P.VARIANT} path tracer, {preset.spp} spp, max depth "
                   f"{P.MAX_DEPTH}, procedural environment map (sky and sun spots) visible behind the objects, "
                   "diffuse/plastic/conductor materials, a diffuse tiled ground")
    return render, description


def capture_cameras(preset, scene_name: str, seed: int) -> dict[str, np.ndarray]:
    """``{"train", "test"}`` OpenGL camera-to-world ``[n, 4, 4]`` of a capture scene: random training
    cameras above the ground, the benchmark's test orbit."""
    from ne_jax.benchmark.generate import _rng

    return {"train": cameras.random_cameras(preset.train_views, _rng(seed, scene_name, "train"),
                                            MIN_ELEVATION, MAX_ELEVATION),
            "test": cameras.orbit_cameras(preset.test_views)}


def _write_rgb(path: Path, image: np.ndarray) -> None:
    path.write_bytes(encode_png(quantise(np.clip(image[..., :3], 0.0, 1.0), 8, str(path))))


def generate_scene(scene_name: str, preset, root, seed: int = 0, edits=None, resume: bool = False,
                   sfm: SfMSimulation = SfMSimulation()) -> dict[str, float]:
    """Render one capture scene and its edits into ``root/<scene_name>`` (COLMAP) and
    ``root/<scene_name>_ns`` (nerfstudio); returns timings in seconds. ``edits`` and ``resume``
    as :func:`ne_jax.benchmark.generate.generate_scene`."""
    from ne_jax.benchmark.generate import _kept, _render_split, _rng, _write_points

    t0 = time.perf_counter()
    root = Path(root)
    scene = S.get_scene(scene_name, preset.detail)
    names = list(scene.edits) if edits is None else list(edits)
    unknown = [e for e in names if e not in scene.edits]
    if unknown:
        raise KeyError(f"scene {scene_name!r} has no edit {unknown[0]!r}; expected some of {list(scene.edits)}")
    if resume and (kept := _kept(root / scene_name, preset, seed, names)) is not None:
        if not (root / f"{scene_name}_ns" / "transforms.json").is_file():
            write_nerfstudio_copy(root / scene_name)
        return kept
    partial = None
    if resume:
        partial = root / f".{scene_name}.partial"
        key = {"scene": scene_name, "preset": preset.record(), "seed": seed}
        if (partial / "key.json").is_file() and json.loads((partial / "key.json").read_text()) != key:
            shutil.rmtree(partial)
        atomic_write_json(partial / "key.json", key)
    if preset.matte:
        scene = dataclasses.replace(scene, materials=tuple(dataclasses.replace(m, ks=0.0, reflect=0.0)
                                                           for m in scene.materials))
    ground = ground_for(scene)
    camera = Pinhole.benchmark(preset.resolution)
    cams = capture_cameras(preset, scene_name, seed)
    order = view_order(preset.train_views, preset.test_views)
    image_names = [image_name(k) for k in range(len(order))]
    c2w_all = np.stack([cams[split][i] for split, i in order])
    samples = S.surface_samples(scene, preset.surface_samples, seed)
    points = simulate_sfm(scene, ground, c2w_all, camera, _rng(seed, scene_name, "sfm"), sfm)
    timings = {"build": time.perf_counter() - t0}
    earlier = 0.0
    common = {"scene": scene_name, "difficulty": scene.difficulty, "preset": preset.record(), "seed": seed,
              "effects": preset.effects(scene), "ground": ground.record(),
              "world": "the benchmark's world frame (z up, objects about the origin inside [-1, 1]^3, cameras "
                       f"{cameras.CAMERA_RADIUS:g} units from it); no normalisation applied"}
    variants = [(None, None)] + [(n, scene.edits[n]) for n in names]
    with atomic_directory(root / scene_name) as out:
        for edit_name, edit in variants:
            t1 = time.perf_counter()
            restricted = None if edit is None else objects_only(edit, ground.objects_above)
            environment = edit.matrix[:3, :3] if edit is not None and edit.moves_environment else None
            render, description = _tracer(scene, ground, restricted, environment, preset)
            target = out if edit is None else out / "edits" / edit_name
            target.mkdir(parents=True, exist_ok=True)
            images, cached_seconds, rendered = 0, 0.0, {}
            for split in ("train", "test"):
                views = cams[split]
                if edit is not None and split == "train" and preset.edit_train_views is not None:
                    views = views[:preset.edit_train_views]
                seeds = _rng(seed, scene_name, f"render/{edit_name or 'original'}/{split}").integers(
                    0, 2**31, len(views))
                t2 = time.perf_counter()
                rendered[split], seconds = _render_split(
                    render, views, seeds, preset.resolution, f"{scene_name}/{edit_name or 'original'}/{split}",
                    None if partial is None else partial / (edit_name or "original") / split)
                cached_seconds += max(0.0, seconds - (time.perf_counter() - t2))
                images += len(rendered[split])
                if edit is not None:
                    write_split(target, split, rendered[split], views, cameras.CAMERA_ANGLE_X)
            meta = dict(common, edit=edit_name, edit_description=None if edit is None else restricted.description,
                        renderer=description)
            if edit is None:
                (out / "images").mkdir()
                for k, (split, i) in enumerate(order):
                    _write_rgb(out / "images" / image_names[k], rendered[split][i])
                write_colmap_text(out / "sparse" / "0", image_names, c2w_all, camera, points)
                write_points_ply(out / "sparse_pc.ply", points)
                _write_unedited(out, image_names, order, cams, meta)
                meta.update(layout="colmap", nerfstudio_copy=f"../{scene_name}_ns",
                            split={"rule": f"every {HOLDOUT_EVERY}th image by name held out (indices 0, "
                                           f"{HOLDOUT_EVERY}, ...)",
                                   "test": [image_names[k] for k, (s, _) in enumerate(order) if s == "test"]},
                            sfm=dict(asdict(sfm), **points.record()),
                            capture={"camera": asdict(camera), "images": image_names, "c2w": c2w_all.tolist()},
                            edits={n: {"kind": e.kind, "description": objects_only(e, ground.objects_above).description}
                                   for n, e in variants[1:]})
            else:
                meta.update(layout="nerf_synthetic", capture_frame="../..", moves_environment=edit.moves_environment)
                if edit.rigid is not None:
                    meta["objects_rigid"] = [list(row) for row in edit.rigid]
            _write_points(target / "points.ply", samples if edit is None else S.edit_samples(samples, restricted))
            seconds = time.perf_counter() - t1 + cached_seconds
            earlier += cached_seconds
            meta["generation"] = {"images": images, "seconds": round(seconds, 2)}
            atomic_write_json(target / "scene.json", meta)
            timings[edit_name or "original"] = seconds
    write_nerfstudio_copy(root / scene_name)
    if partial is not None:
        shutil.rmtree(partial, ignore_errors=True)
    timings["total"] = time.perf_counter() - t0 + earlier
    return timings


def _write_unedited(out: Path, image_names: list[str], order, cams: dict[str, np.ndarray], meta: dict) -> None:
    """``out/unedited/``: the capture's train and test views in the NeRF Synthetic layout, as the
    edits' ground truth is written (``transforms_{train,test}.json`` naming ``../images/<name>``, in
    each split's order; ``scene.json`` with ``capture_frame: ".."``)."""
    for split in ("train", "test"):
        by_index = {i: image_names[k] for k, (s, i) in enumerate(order) if s == split}
        frames = [{"file_path": f"../images/{by_index[i]}", "transform_matrix": np.asarray(c2w, np.float64).tolist()}
                  for i, c2w in enumerate(cams[split])]
        atomic_write_json(out / "unedited" / f"transforms_{split}.json",
                          {"camera_angle_x": cameras.CAMERA_ANGLE_X, "frames": frames})
    atomic_write_json(out / "unedited" / "scene.json", dict(meta, layout="nerf_synthetic", capture_frame=".."))


__all__ = ["Ground", "MIN_ELEVATION", "Pinhole", "SfMPoints", "SfMSimulation", "capture_cameras",
           "generate_scene", "ground_for", "image_name", "nerfstudio_transforms", "objects_only",
           "rotation_to_quaternion", "simulate_sfm", "view_order", "visibility", "world_to_camera_opencv",
           "write_colmap_text", "write_nerfstudio_copy", "write_points_ply"]

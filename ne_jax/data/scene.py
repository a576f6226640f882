"""A scene folder of any supported layout, as the rest of the library sees it.

:func:`load_split` is the one entry point: it detects the folder's layout (:func:`detect_format`),
reads it (:mod:`ne_jax.data.formats`), brings it into the frame the presets assume
(:func:`normalisation`), undistorts and downscales the images, and returns a
:class:`~ne_jax.data.nerf_synthetic.SceneSplit` like the NeRF Synthetic loader does. A NeRF
Synthetic folder is read as it always was (identity normalisation, the config's near/far).

**The scene frame.** The presets are sized for the procedural benchmark: the objects inside
``[-1, 1]^3``, cameras about ``CAMERA_RADIUS = 4`` from the origin, ``z`` up. A capture is brought
there by a similarity ``x_scene = s R x_capture + t`` (:class:`Normalisation`):

* ``R`` turns the cameras' mean up vector onto ``+z`` (when the cameras agree on one);
* the centre is the region of interest's: the middle of the format's bounding box (NSVF
  ``bbox.txt``), else the point nearest to every camera's optical axis (the cameras look at it)
  when those axes cross well, else the median of the SfM points, else the mean camera centre;
* the scale brings the region of interest into ``[-1, 1]^3``: the bounding box; else the SfM points
  near the centre (closer than the cameras: the region the cameras look at), their 90th percentile of
  ``|x - c|_inf``; clamped so that the median camera lands between 2 and 8 from the origin; without
  points, the median camera distance becomes 4.

Every number of the normalisation is a pure function of the folder's contents, so every command
(``train``, ``eval``, ``render``, ``view``) recomputes the same frame; the run records it
(:func:`scene_record`), and coordinates a user sees (exported PLYs, edit files) are in the capture's
own frame (:meth:`Normalisation.to_capture`).

**Near and far** per camera come from the SfM points in front of it (``0.5x`` the 1st percentile
of their depths, ``1.5x`` the 99th), else from the format's own bounds (LLFF), else ``max(0.05, d -
2)`` to ``d + 2`` for a camera ``d`` from the origin (the benchmark's); a run's rays use the envelope
over the cameras (:func:`scene_near_far`), and the run records the per-camera values.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import numpy as np

from ne_jax.data.cameras import CAMERA_RADIUS
from ne_jax.data.capture import FORMATS, Capture, CaptureView
from ne_jax.data.nerf_synthetic import SceneSplit, downscale_rgba, transforms_path
from ne_jax.data.nerf_synthetic import load_split as load_nerf_synthetic_split
from ne_jax.data.png import DataError, read_image
from ne_jax.data.png import fail as _fail

LOOKED_FOR = {
    "nerf_synthetic": "transforms_train.json (NeRF Synthetic / Blender)",
    "nerfstudio": "transforms.json (nerfstudio)",
    "colmap": "sparse/0/cameras.bin|txt or sparse/cameras.bin|txt with images/ (COLMAP)",
    "nsvf": "intrinsics.txt and pose/ (NSVF / Tanks and Temples)",
    "llff": "poses_bounds.npy with images/ (LLFF)",
}
"""What :func:`detect_format` looks for, per layout, in detection order."""


def detect_format(root: str | os.PathLike) -> str:
    """The layout of the scene folder ``root`` (one of :data:`~ne_jax.data.capture.FORMATS`).

    A folder that matches several layouts takes the first in :data:`LOOKED_FOR`'s order. Raises
    :class:`DataError` listing what was looked for when it is none of them."""
    root = Path(root)
    if not root.is_dir():
        raise _fail(root, None, "scene directory does not exist")
    if transforms_path(root, "train").is_file():
        return "nerf_synthetic"
    from ne_jax.data.formats import READERS

    for name, (looks_like, _) in READERS.items():
        if looks_like(root):
            return name
    tried = "; ".join(LOOKED_FOR.values())
    raise _fail(root, None, f"not a scene folder of a known layout: looked for {tried}; found none")


def read_capture(root: str | os.PathLike) -> Capture:
    """The :class:`~ne_jax.data.capture.Capture` of a folder of any layout but NeRF Synthetic."""
    fmt = detect_format(root)
    if fmt == "nerf_synthetic":
        raise DataError(f"{root}: a NeRF Synthetic folder is read by ne_jax.data.nerf_synthetic, not as a capture")
    from ne_jax.data.formats import READERS

    capture = READERS[fmt][1](Path(root))
    assert capture.format in FORMATS
    return capture


# ----------------------------------------------------------------------------------------------
# Normalisation
# ----------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Normalisation:
    """The similarity ``x_scene = scale * rotation @ x_capture + translation`` from a capture's
    frame to the scene frame the presets assume (module docstring). ``how`` says how each part was
    chosen (recorded in the run)."""

    scale: float = 1.0
    rotation: tuple[tuple[float, ...], ...] = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    translation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    how: tuple[tuple[str, str], ...] = ()

    @property
    def is_identity(self) -> bool:
        return bool(np.array_equal(self.matrix(), np.eye(4)))

    def matrix(self) -> np.ndarray:
        """``[4, 4]`` float64: the similarity as a homogeneous matrix."""
        m = np.eye(4)
        m[:3, :3] = self.scale * np.asarray(self.rotation, np.float64)
        m[:3, 3] = self.translation
        return m

    def to_scene(self, xyz: np.ndarray) -> np.ndarray:
        """Capture-frame points ``[..., 3]`` -> scene frame (float64)."""
        xyz = np.asarray(xyz, np.float64)
        return self.scale * xyz @ np.asarray(self.rotation).T + np.asarray(self.translation)

    def to_capture(self, xyz: np.ndarray) -> np.ndarray:
        """Scene-frame points ``[..., 3]`` -> the capture's frame (float64)."""
        xyz = np.asarray(xyz, np.float64)
        return (xyz - np.asarray(self.translation)) @ np.asarray(self.rotation) / self.scale

    def rotate_to_scene(self, vectors: np.ndarray) -> np.ndarray:
        """Capture-frame directions (normals) ``[..., 3]`` -> the scene frame (unit length kept)."""
        return np.asarray(vectors, np.float64) @ np.asarray(self.rotation).T

    def rotate_to_capture(self, vectors: np.ndarray) -> np.ndarray:
        """Scene-frame directions (normals) ``[..., 3]`` -> the capture's frame (unit length kept)."""
        return np.asarray(vectors, np.float64) @ np.asarray(self.rotation)

    def c2w_to_scene(self, c2w: np.ndarray) -> np.ndarray:
        """Camera-to-world ``[..., 4, 4]`` (capture frame) -> scene frame, still rigid: the rotation
        turns, the centre moves as a point."""
        c2w = np.array(c2w, np.float64, copy=True)
        c2w[..., :3, :3] = np.asarray(self.rotation) @ c2w[..., :3, :3]
        c2w[..., :3, 3] = self.to_scene(c2w[..., :3, 3])
        return c2w

    def as_dict(self) -> dict:
        return {"scale": self.scale, "rotation": [list(r) for r in self.rotation],
                "translation": list(self.translation), "how": dict(self.how),
                "matrix": self.matrix().tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> Normalisation:
        """The inverse of :meth:`as_dict`."""
        return cls(scale=float(d["scale"]), rotation=tuple(tuple(float(x) for x in r) for r in d["rotation"]),
                   translation=tuple(float(x) for x in d["translation"]), how=tuple(d.get("how", {}).items()))


def _rotation_onto_z(up: np.ndarray) -> np.ndarray:
    """The rotation taking the unit vector ``up`` onto ``+z`` (Rodrigues; ``-z`` turns about ``x``)."""
    z = np.array([0.0, 0.0, 1.0])
    v, c = np.cross(up, z), float(np.dot(up, z))
    if c < -1 + 1e-9:
        return np.diag([1.0, -1.0, -1.0])
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + k + k @ k / (1.0 + c)


def _focus_point(centers: np.ndarray, forward: np.ndarray) -> np.ndarray | None:
    """The point nearest (least squares) to every camera's optical axis, or ``None`` when the axes
    are nearly parallel (a forward-facing capture) or it lies behind most cameras."""
    a = np.zeros((3, 3))
    b = np.zeros(3)
    for c, d in zip(centers, forward):
        p = np.eye(3) - np.outer(d, d)
        a += p
        b += p @ c
    eig = np.linalg.eigvalsh(a / len(centers))
    if eig[0] < 0.05:  # axes too close to parallel to cross at one point
        return None
    x = np.linalg.solve(a, b)
    in_front = np.einsum("ij,ij->i", x - centers, forward) > 0
    return x if in_front.mean() > 0.5 else None


def normalisation(capture: Capture) -> Normalisation:
    """The similarity that brings ``capture`` into the scene frame (module docstring: the rules)."""
    c2w = np.stack([v.c2w for v in capture.views])
    centers, up, forward = c2w[:, :3, 3], c2w[:, :3, 1], -c2w[:, :3, 2]
    how = []
    mean_up = up.mean(0)
    if np.linalg.norm(mean_up) > 0.5:  # the cameras agree on an up direction
        rot = _rotation_onto_z(mean_up / np.linalg.norm(mean_up))
        how.append(("rotation", "the cameras' mean up vector onto +z"))
    else:
        rot = np.eye(3)
        how.append(("rotation", "none: the cameras' up vectors disagree"))
    points = capture.points if capture.points is not None and len(capture.points) >= 20 else None
    if capture.bbox is not None:
        lo, hi = (np.asarray(b, np.float64) for b in capture.bbox)
        centre = 0.5 * (lo + hi)
        how.append(("centre", "the middle of the format's bounding box"))
    else:
        centre = _focus_point(centers, forward)
        if centre is not None:
            how.append(("centre", "the point nearest to every camera's optical axis"))
        elif points is not None:
            centre = np.median(points, axis=0)
            how.append(("centre", "the median of the SfM points"))
        else:
            centre = centers.mean(0)
            how.append(("centre", "the mean camera centre"))
    cam_dist = float(np.median(np.linalg.norm(centers - centre, axis=1)))
    if cam_dist <= 0:
        raise DataError(f"{capture.root}: every camera sits at the scene centre; cannot normalise the scene")
    if capture.bbox is not None:
        lo, hi = (rot @ np.asarray(b, np.float64) for b in capture.bbox)
        radius = float(np.max(np.abs(hi - lo)) / 2)
        how.append(("scale", "the bounding box into [-1, 1]^3"))
    elif points is not None:
        local = (points - centre) @ rot.T
        near = local[np.linalg.norm(local, axis=1) < cam_dist]
        if len(near) >= 20:
            radius = float(np.percentile(np.abs(near).max(1), 90))
            how.append(("scale", "90% of the SfM points nearer than the cameras into [-1, 1]^3"))
        else:
            radius = cam_dist / CAMERA_RADIUS
            how.append(("scale", "the median camera distance to 4 (too few SfM points near the centre)"))
    else:
        radius = cam_dist / CAMERA_RADIUS
        how.append(("scale", "the median camera distance to 4 (no SfM points)"))
    scale = 1.0 / max(radius, 1e-12)
    clamped = float(np.clip(scale * cam_dist, 2.0, 8.0)) / cam_dist
    if clamped != scale:
        how.append(("clamp", f"scale {scale:.4g} -> {clamped:.4g}: the median camera between 2 and 8 from the origin"))
        scale = clamped
    translation = -scale * rot @ centre
    return Normalisation(scale=float(scale), rotation=tuple(tuple(float(x) for x in r) for r in rot),
                         translation=tuple(float(x) for x in translation), how=tuple(how))


# ----------------------------------------------------------------------------------------------
# Splits
# ----------------------------------------------------------------------------------------------


def _undistort(image: np.ndarray, view: CaptureView) -> np.ndarray:
    """``image`` ``[H, W, 4]`` with the lens distortion of ``view`` undone (same pinhole intrinsics)."""
    import cv2

    k = np.array([[view.fx, 0, view.cx - 0.5], [0, view.fy, view.cy - 0.5], [0, 0, 1]], np.float64)
    dist = np.asarray(view.distortion, np.float64)
    return cv2.undistort(image, k, dist, None, k)


def _view_near_far(centre_c2w: np.ndarray, points: np.ndarray) -> tuple[float, float] | None:
    """Near/far of a camera (scene frame) from the points in front of it, or ``None``."""
    depth = (points - centre_c2w[:3, 3]) @ -centre_c2w[:3, 2]
    depth = depth[depth > 1e-6]
    if len(depth) < 10:
        return None
    return 0.5 * float(np.percentile(depth, 1)), 1.5 * float(np.percentile(depth, 99))


@dataclasses.dataclass(frozen=True, eq=False)
class SceneFrame:
    """A capture brought into the scene frame: the ``capture`` as read, its ``normalisation``, the
    cameras ``c2w`` ``[N, 4, 4]`` float64 and ``points`` ``[P, 3]`` float64 (or ``None``) in the
    scene frame, and ``near_far`` ``[N, 2]`` per view."""

    capture: Capture
    normalisation: Normalisation
    c2w: np.ndarray
    points: np.ndarray | None
    near_far: np.ndarray


def scene_frame(root: str | os.PathLike) -> SceneFrame:
    """Read and normalise the capture in ``root`` (any layout but NeRF Synthetic)."""
    capture = read_capture(root)
    norm = normalisation(capture)
    c2w = norm.c2w_to_scene(np.stack([v.c2w for v in capture.views]))
    points = None if capture.points is None else norm.to_scene(capture.points)
    near_far = np.zeros((capture.num_views, 2))
    for i, view in enumerate(capture.views):
        nf = _view_near_far(c2w[i], points) if points is not None else None
        if nf is None and view.near_far is not None:
            nf = tuple(norm.scale * np.asarray(view.near_far))
        if nf is None:
            d = float(np.linalg.norm(c2w[i, :3, 3]))
            nf = (max(0.05, d - 2.0), d + 2.0)
        near_far[i] = nf
    return SceneFrame(capture, norm, c2w, points, near_far)


def load_split(scene_dir: str | os.PathLike, split: str, downscale: int = 1) -> SceneSplit:
    """One split of the scene folder ``scene_dir`` of any layout (module docstring), in the scene
    frame, images undistorted and downscaled by the integer ``downscale``; views of one split must
    share one camera (intrinsics and image size) after downscaling."""
    scene_dir = Path(scene_dir)
    if detect_format(scene_dir) == "nerf_synthetic":
        out = load_nerf_synthetic_split(scene_dir, split, downscale)
        norm = scene_normalisation(scene_dir)
        if norm.is_identity:
            return out
        return dataclasses.replace(out, c2w=norm.c2w_to_scene(out.c2w).astype(np.float32))
    if isinstance(downscale, bool) or not isinstance(downscale, (int, np.integer)) or downscale < 1:
        raise DataError(f"downscale: expected an integer >= 1, found {downscale!r}")
    frame = scene_frame(scene_dir)
    capture = frame.capture
    if split not in capture.splits:
        raise _fail(scene_dir, None, f"no {split!r} split: this {capture.format} scene has "
                    f"{sorted(capture.splits)} ({capture.split_rule})")
    idx = list(capture.splits[split])
    views = [capture.views[i] for i in idx]
    first = views[0]
    for v in views[1:]:
        cam, ref = (v.fx, v.fy, v.cx, v.cy, v.width, v.height), (first.fx, first.fy, first.cx, first.cy,
                                                                   first.width, first.height)
        if not np.allclose(cam, ref, rtol=1e-6, atol=1e-6):
            raise _fail(scene_dir, f"image {v.name}", f"the views of one split must share one camera: expected "
                        f"fx, fy, cx, cy, w, h = {ref} like {first.name}, found {cam}")
    if downscale > min(first.width, first.height):
        raise DataError(f"downscale: factor {downscale} exceeds the image size {first.width}x{first.height} "
                        f"of {scene_dir}")
    images = []
    for v in views:
        img = read_image(v.image_path)
        if img.shape[:2] != (v.height, v.width):
            raise _fail(v.image_path, None, f"expected a {v.width}x{v.height} (WxH) image as the {capture.format} "
                        f"cameras state, found {img.shape[1]}x{img.shape[0]}")
        if v.distortion is not None:
            img = _undistort(img, v)
        images.append(downscale_rgba(img, int(downscale)) if downscale > 1 else img)
    f = float(downscale)
    return SceneSplit(name=split, images=np.stack(images), c2w=frame.c2w[idx].astype(np.float32),
                      fx=first.fx / f, fy=first.fy / f, cx=first.cx / f, cy=first.cy / f,
                      camera_angle_x=2.0 * float(np.arctan(0.5 * first.width / first.fx)),
                      file_paths=tuple(v.name for v in views), image_paths=tuple(v.image_path for v in views),
                      downscale=int(downscale))


def scene_near_far(scene_dir: str | os.PathLike) -> tuple[float, float] | None:
    """The near/far envelope of a capture's cameras (scene frame), or ``None`` for a NeRF Synthetic
    folder (its runs use the config's)."""
    if detect_format(scene_dir) == "nerf_synthetic":
        return None
    nf = scene_frame(scene_dir).near_far
    return float(nf[:, 0].min()), float(nf[:, 1].max())


def scene_points(scene_dir: str | os.PathLike) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None] | None:
    """A capture's SfM points in the scene frame ``([P, 3] float64, rgb [P, 3] | None, error [P] |
    None)``, or ``None`` where the folder has none (NeRF Synthetic, NSVF, LLFF)."""
    if detect_format(scene_dir) == "nerf_synthetic":
        return None
    frame = scene_frame(scene_dir)
    if frame.points is None:
        return None
    return frame.points, frame.capture.point_rgb, frame.capture.point_error


SCENE_RECORD_FILE = "scene_record.json"
"""In a run directory: the scene folder as the run saw it (:func:`scene_record`, plus the run's
downscale and training views)."""


def split_names(scene_dir: str | os.PathLike) -> list[str]:
    """The splits a scene folder has (``train``, ``val``, ``test`` where present)."""
    scene_dir = Path(scene_dir)
    if detect_format(scene_dir) == "nerf_synthetic":
        return [s for s in ("train", "val", "test") if transforms_path(scene_dir, s).is_file()]
    return list(read_capture(scene_dir).splits)


def check_recorded_split(run_dir: str | os.PathLike, split: SceneSplit) -> None:
    """Raise :class:`DataError` when a run directory's scene record lists other images for
    ``split.name`` than ``split`` holds (the scene folder changed since training, so scores would
    not compare); a run that recorded no splits passes."""
    file = Path(run_dir) / SCENE_RECORD_FILE
    if not file.is_file():
        return
    recorded = json.loads(file.read_text(encoding="utf-8")).get("splits", {}).get(split.name)
    if recorded is not None and list(recorded) != list(split.file_paths):
        raise _fail(file, f"splits.{split.name}", f"the run was trained when the {split.name!r} split held "
                    f"{len(recorded)} images ({recorded[:3]}...); the scene folder now gives {len(split.file_paths)} "
                    f"({list(split.file_paths[:3])}...): the scene changed since training")


CAPTURE_FRAME_KEY = "capture_frame"
"""A NeRF Synthetic folder whose ``scene.json`` names a capture folder under this key (a path
relative to the folder) takes that capture's scene frame: the ground truth of an edited capture."""


def scene_normalisation(scene_dir: str | os.PathLike) -> Normalisation:
    """The scene frame of ``scene_dir``: a capture's (:func:`normalisation`); for a NeRF Synthetic
    folder identity, or the frame of the capture its ``scene.json`` names (:data:`CAPTURE_FRAME_KEY`)."""
    scene_dir = Path(scene_dir)
    if detect_format(scene_dir) == "nerf_synthetic":
        meta_file = scene_dir / "scene.json"
        meta = json.loads(meta_file.read_text(encoding="utf-8")) if meta_file.is_file() else {}
        if CAPTURE_FRAME_KEY in meta:
            capture = (scene_dir / meta[CAPTURE_FRAME_KEY]).resolve()
            if detect_format(capture) == "nerf_synthetic":
                raise _fail(meta_file, CAPTURE_FRAME_KEY, f"expected a capture folder, found NeRF Synthetic {capture}")
            return scene_frame(capture).normalisation
        return Normalisation(how=(("all", "NeRF Synthetic: the folder's own frame"),))
    return scene_frame(scene_dir).normalisation


def scene_record(scene_dir: str | os.PathLike) -> dict:
    """What a run records about its scene folder: the layout, the splits (image names, and where they
    came from), the normalisation and the cameras' near/far."""
    scene_dir = Path(scene_dir)
    fmt = detect_format(scene_dir)
    if fmt == "nerf_synthetic":
        return {"format": fmt, "split_rule": "format", "normalisation": scene_normalisation(scene_dir).as_dict()}
    frame = scene_frame(scene_dir)
    c = frame.capture
    return {"format": fmt, "source": list(c.source), "split_rule": c.split_rule,
            "splits": {s: [c.views[i].name for i in ix] for s, ix in c.splits.items()},
            "normalisation": frame.normalisation.as_dict(),
            "near_far": {"per_view": np.round(frame.near_far, 6).tolist(),
                         "envelope": [float(frame.near_far[:, 0].min()), float(frame.near_far[:, 1].max())]},
            "points": 0 if frame.points is None else int(len(frame.points))}


__all__ = [
    "CAPTURE_FRAME_KEY", "LOOKED_FOR", "Normalisation", "SceneFrame", "detect_format", "load_split", "normalisation",
    "read_capture", "scene_frame", "scene_near_far", "scene_normalisation", "scene_points", "scene_record",
    "split_names", "check_recorded_split", "SCENE_RECORD_FILE",
]

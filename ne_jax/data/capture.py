"""A capture: the cameras, image files, splits and sparse points of a scene folder, as its format
stores them, before anything is normalised or loaded.

Every format reader (:mod:`ne_jax.data.formats`) returns a :class:`Capture` in one convention, so
the rest of the library reads one structure:

* ``CaptureView.c2w`` is camera-to-world ``[4, 4]`` float64 with **OpenGL camera axes** (the camera
  looks down its ``-z``, ``+y`` is up in the image, ``+x`` right), in the capture's own world
  coordinates (COLMAP's world-to-camera OpenCV poses are inverted and their ``y``/``z`` axes
  flipped by the reader);
* intrinsics ``fx, fy, cx, cy`` are pixels at the resolution of the image file on disk, pixel
  centres at ``i + 0.5`` (COLMAP's convention, and nerfstudio's);
* ``distortion`` is ``None`` (a pinhole camera) or OpenCV's coefficients ``(k1, k2, p1, p2[, k3[,
  k4, k5, k6]])``, which :func:`ne_jax.data.scene.load_split` undoes on load;
* ``points`` are in the same world coordinates as the cameras.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

FORMATS = ("nerf_synthetic", "nerfstudio", "colmap", "nsvf", "llff")
"""The scene layouts :func:`ne_jax.data.scene.detect_format` recognises."""

HOLDOUT_EVERY = 8
"""Formats without their own split hold out every 8th image (sorted by name) as the test split
(the LLFF / mip-NeRF 360 convention)."""


@dataclasses.dataclass(frozen=True, eq=False)
class CaptureView:
    """One image of a capture: its file, its pose and its camera (module docstring: conventions)."""

    name: str
    """The image as the format names it (e.g. COLMAP's image name, nerfstudio's ``file_path``)."""
    image_path: Path
    """The resolved file (it exists: readers check)."""
    c2w: np.ndarray
    """``[4, 4]`` float64 camera-to-world, OpenGL camera axes, rigid and finite (readers check)."""
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    distortion: tuple[float, ...] | None = None
    """OpenCV distortion coefficients ``(k1, k2, p1, p2[, k3[, k4, k5, k6]])``, or ``None``."""
    near_far: tuple[float, float] | None = None
    """The format's own depth bounds of this view (LLFF), in capture units; ``None`` where absent."""


@dataclasses.dataclass(frozen=True, eq=False)
class Capture:
    """A scene folder as its format stores it.

    ``views`` in a fixed order (sorted by name where the format has no order of its own);
    ``splits`` maps split names (``train``, ``val``, ``test``) to indices into ``views``;
    ``split_rule`` says where the splits came from (``"format"``: the format's own, or
    ``"every 8th held out"``); ``points`` ``[P, 3]`` float64 sparse points (SfM), ``point_rgb``
    ``[P, 3]`` float32 in ``[0, 1]``, ``point_error`` ``[P]`` reprojection error in pixels, each
    ``None`` where the format has none; ``bbox`` ``(lo [3], hi [3])`` the region of interest the
    format states (NSVF's ``bbox.txt``), or ``None``; ``source`` the files the capture was read from
    (for messages and the run's record)."""

    format: str
    root: Path
    views: tuple[CaptureView, ...]
    splits: dict[str, tuple[int, ...]]
    split_rule: str
    points: np.ndarray | None = None
    point_rgb: np.ndarray | None = None
    point_error: np.ndarray | None = None
    bbox: tuple[np.ndarray, np.ndarray] | None = None
    source: tuple[str, ...] = ()

    @property
    def num_views(self) -> int:
        return len(self.views)

    def split_views(self, split: str) -> tuple[CaptureView, ...]:
        """The views of ``split`` (a :class:`KeyError`-free lookup is the caller's job: see
        :func:`ne_jax.data.scene.load_split`)."""
        return tuple(self.views[i] for i in self.splits[split])


def holdout_splits(names: list[str], every: int = HOLDOUT_EVERY) -> dict[str, tuple[int, ...]]:
    """``train``/``test`` indices for ``names`` in their given order: every ``every``-th image
    (0, 8, 16, ...) is a test view, the rest train. With fewer than 2 images all train."""
    n = len(names)
    test = tuple(i for i in range(n) if i % every == 0) if n >= 2 else ()
    train = tuple(i for i in range(n) if i not in set(test))
    out = {"train": train}
    if test:
        out["test"] = test
    return out


def opencv_to_opengl(c2w_opencv: np.ndarray) -> np.ndarray:
    """Camera-to-world with OpenCV camera axes (``+z`` forward, ``+y`` down) -> OpenGL axes
    (``-z`` forward, ``+y`` up): flip the camera's ``y`` and ``z`` columns. ``[..., 4, 4]``."""
    out = np.array(c2w_opencv, dtype=np.float64, copy=True)
    out[..., :3, 1:3] *= -1.0
    return out


__all__ = ["FORMATS", "HOLDOUT_EVERY", "Capture", "CaptureView", "holdout_splits", "opencv_to_opengl"]

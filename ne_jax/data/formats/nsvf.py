"""Read an NSVF-layout scene (NSVF's Synthetic-NeRF and Tanks and Temples releases) into a
:class:`~ne_jax.data.capture.Capture`.

Layout::

    <root>/intrinsics.txt      # "f cx cy 0." on the first line (later lines ignored), or a 4x4
                               # (or 3x3) matrix K: fx = K[0,0], fy = K[1,1], cx = K[0,2], cy = K[1,2]
    <root>/pose/<name>.txt     # 4x4 camera-to-world, OpenCV camera axes (+z forward, +y down)
    <root>/rgb/<name>.png|jpg  # <name> starts with 0_ (train), 1_ (val) or 2_ (test)
    <root>/bbox.txt            # optional: x_min y_min z_min x_max y_max z_max [voxel_size]

Conventions (those of NSVF's ``fairnr/data/data_utils.py``): poses are converted to OpenGL camera
axes by flipping the camera's ``y``/``z``; one camera for all images, all of one size. Splits are
the format's own: ``0_`` train, ``1_`` val, ``2_`` test, except that where no ``2_`` image exists
(Tanks and Temples in NSVF form) the ``1_`` images are the test split. Names without these
prefixes (all of them) fall back to every 8th image held out. ``bbox.txt`` becomes
``Capture.bbox``; there are no points.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ne_jax.data.capture import Capture, CaptureView, holdout_splits, opencv_to_opengl
from ne_jax.data.formats._common import image_size, list_images, matrix_4x4, number, number_rows, positive
from ne_jax.data.nerf_synthetic import check_rigid
from ne_jax.data.png import fail

_PREFIX = re.compile(r"^([0-9]+)_")
_SPLIT_OF_PREFIX = {"0": "train", "1": "val", "2": "test"}


def looks_like(root: Path) -> bool:
    """True when ``<root>/intrinsics.txt`` and the folders ``<root>/pose`` and ``<root>/rgb`` exist."""
    root = Path(root)
    return (root / "intrinsics.txt").is_file() and (root / "pose").is_dir() and (root / "rgb").is_dir()


def read_intrinsics(path: Path) -> tuple[float, float, float, float]:
    """``(fx, fy, cx, cy)`` from an NSVF ``intrinsics.txt`` (either form: module docstring)."""
    rows = number_rows(path, "intrinsics file")
    lengths = [len(r) for _, r in rows]
    if lengths in ([4, 4, 4, 4], [3, 3, 3]):
        k = np.array([r for _, r in rows], dtype=np.float64)
        vals = {"K[0,0]": k[0, 0], "K[1,1]": k[1, 1], "K[0,2]": k[0, 2], "K[1,2]": k[1, 2]}
        fx, fy, cx, cy = (number(v, path, where) for where, v in vals.items())
        if k[0, 1] != 0.0 or k[1, 0] != 0.0:
            raise fail(
                path, "K[0,1]", f"expected a camera without skew (K[0,1] = K[1,0] = 0), found {k[0, 1]!r}, {k[1, 0]!r}"
            )
        if not np.array_equal(k[2, :3], [0.0, 0.0, 1.0]):
            raise fail(path, "K[2]", f"expected the third row of K to be [0, 0, 1], found {k[2, :3].tolist()}")
    elif rows and len(rows[0][1]) == 4:
        lineno, (f, cx, cy, _) = rows[0]
        f = number(f, path, f"line {lineno} f")
        cx, cy = number(cx, path, f"line {lineno} cx"), number(cy, path, f"line {lineno} cy")
        fx = fy = f
    else:
        raise fail(
            path,
            None,
            f"expected 'f cx cy 0.' on the first line or a 4x4 / 3x3 matrix K, found lines of {lengths} numbers",
        )
    positive(fx, path, "fx", "focal length in pixels")
    positive(fy, path, "fy", "focal length in pixels")
    return fx, fy, cx, cy


def read_bbox(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``(lo [3], hi [3])`` from ``bbox.txt`` (``x_min y_min z_min x_max y_max z_max [voxel]``)."""
    rows = number_rows(path, "bounding-box file")
    if not rows or len(rows[0][1]) not in (6, 7):
        found = len(rows[0][1]) if rows else 0
        raise fail(
            path, "line 1", f"expected 6 or 7 numbers (x_min y_min z_min x_max y_max z_max [voxel_size]), found {found}"
        )
    lineno, vals = rows[0]
    vals = [number(v, path, f"line {lineno}") for v in vals[:6]]
    lo, hi = np.array(vals[:3], dtype=np.float64), np.array(vals[3:], dtype=np.float64)
    if not np.all(lo < hi):
        raise fail(
            path, f"line {lineno}", f"expected min < max on every axis, found min {lo.tolist()} max {hi.tolist()}"
        )
    return lo, hi


def _splits(names: list[str], rgb: Path) -> tuple[dict[str, tuple[int, ...]], str]:
    prefixes = [_PREFIX.match(n) for n in names]
    if not any(prefixes):
        return holdout_splits(names), "every 8th held out"
    groups: dict[str, list[int]] = {}
    for i, (name, m) in enumerate(zip(names, prefixes)):
        split = _SPLIT_OF_PREFIX.get(m.group(1)) if m else None
        if split is None:
            raise fail(rgb / name, None, "expected a name starting 0_ (train), 1_ (val) or 2_ (test)")
        groups.setdefault(split, []).append(i)
    if "test" not in groups and "val" in groups:  # Tanks and Temples in NSVF form: 1_ is the test split
        groups["test"] = groups.pop("val")
    return {s: tuple(groups[s]) for s in ("train", "val", "test") if s in groups}, "format"


def read_nsvf(root: Path) -> Capture:
    """Read an NSVF-layout folder (module docstring)."""
    root = Path(root)
    intr_path, pose_dir, rgb_dir = root / "intrinsics.txt", root / "pose", root / "rgb"
    fx, fy, cx, cy = read_intrinsics(intr_path)
    for d in (pose_dir, rgb_dir):
        if not d.is_dir():
            raise fail(d, None, "folder does not exist (an NSVF scene holds pose/ and rgb/)")
    images = list_images(rgb_dir)
    if not images:
        raise fail(rgb_dir, None, "expected .png or .jpg images, found none")
    by_stem = {}
    for p in images:
        if p.stem in by_stem:
            raise fail(p, None, f"two images for one pose: {by_stem[p.stem].name} and {p.name}")
        by_stem[p.stem] = p
    poses = sorted(pose_dir.glob("*.txt"))
    for pose in poses:
        if pose.stem not in by_stem:
            raise fail(pose, None, f"no image for this pose: expected {rgb_dir / pose.stem}.png or .jpg")
    width = height = None
    views = []
    for p in images:
        pose = pose_dir / f"{p.stem}.txt"
        if not pose.is_file():
            raise fail(p, None, f"no pose for this image: expected {pose}")
        c2w = check_rigid(opencv_to_opengl(matrix_4x4(pose, "pose file")), pose, "pose")
        w, h = image_size(p, rgb_dir, p.name)
        if width is None:
            width, height = w, h
        elif (w, h) != (width, height):
            raise fail(p, None, f"image is {w}x{h} (WxH), expected {width}x{height} like {images[0].name} (one camera)")
        views.append(
            CaptureView(name=p.name, image_path=p.resolve(), c2w=c2w, fx=fx, fy=fy, cx=cx, cy=cy, width=w, height=h)
        )
    splits, rule = _splits([v.name for v in views], rgb_dir)
    bbox_path = root / "bbox.txt"
    bbox = read_bbox(bbox_path) if bbox_path.is_file() else None
    source = (str(intr_path), str(pose_dir), str(rgb_dir)) + ((str(bbox_path),) if bbox is not None else ())
    return Capture(
        format="nsvf", root=root, views=tuple(views), splits=splits, split_rule=rule, bbox=bbox, source=source
    )


read = read_nsvf

__all__ = ["looks_like", "read", "read_bbox", "read_intrinsics", "read_nsvf"]

"""Read a nerfstudio scene (``transforms.json``) into a :class:`~ne_jax.data.capture.Capture`.

Layout::

    <root>/transforms.json
        {"camera_model": "OPENCV",                   # optional, default PINHOLE
         "fl_x": .., "fl_y": .., "cx": .., "cy": .., "w": .., "h": ..,   # pixels, global ...
         "k1": .., "k2": .., "k3": .., "k4": .., "p1": .., "p2": ..,      # optional distortion
         "frames": [{"file_path": "images/frame_00001.png",               # relative to <root>
                     "transform_matrix": [[...4x4...]],                   # camera-to-world, OpenGL
                     "fl_x": .., ...}],                                   # ... or per frame
         "ply_file_path": "sparse_pc.ply",           # optional points, same world as the frames
         "train_filenames": [..], "val_filenames": [..], "test_filenames": [..]}  # optional

Conventions: ``transform_matrix`` is camera-to-world with OpenGL camera axes already, kept as is
(no re-orienting or re-scaling: that is the loader's job). Every intrinsic key is looked up in the
frame first and then at the top level (a frame's value wins); ``w``/``h`` may be absent, then the
image's own size is used, else the image must have that size. ``camera_model`` ``PINHOLE``,
``SIMPLE_PINHOLE``, ``SIMPLE_RADIAL``, ``RADIAL`` and ``OPENCV`` are the perspective cameras
nerfstudio treats alike: their distortion is nerfstudio's ``1 + k1 r^2 + k2 r^4 + k3 r^6 + k4 r^8``
radial and ``p1, p2`` tangential terms, which is OpenCV's ``(k1, k2, p1, p2, k3)`` when ``k4`` is 0
(a non-zero ``k4`` has no OpenCV equivalent and raises). ``OPENCV_FISHEYE``, ``EQUIRECTANGULAR``
and the other nerfstudio models raise :class:`~ne_jax.data.png.DataError`.

Views are sorted by ``file_path`` (normalised: ``./images/a.png`` is ``images/a.png``). Splits come
from ``*_filenames`` when any is present, else every 8th view is held out as the test split.
"""

from __future__ import annotations

import json
import posixpath
from pathlib import Path
from typing import Any

import numpy as np

from ne_jax.data.capture import Capture, CaptureView, holdout_splits
from ne_jax.data.formats._common import image_size, number, positive, read_text, zero_is_none
from ne_jax.data.nerf_synthetic import check_rigid, transform_frames
from ne_jax.data.ply import PlyError, read_ply
from ne_jax.data.png import fail

PERSPECTIVE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
"""nerfstudio's ``camera_model`` values this reader accepts (all perspective, same distortion keys)."""
_DISTORTION_KEYS = ("k1", "k2", "p1", "p2", "k3")  # OpenCV's order
_SPLIT_KEYS = (("train", "train_filenames"), ("val", "val_filenames"), ("test", "test_filenames"))


def looks_like(root: Path) -> bool:
    """True when ``<root>/transforms.json`` exists."""
    return (Path(root) / "transforms.json").is_file()


def normalise(file_path: str) -> str:
    """``./images/a.png`` -> ``images/a.png`` (POSIX separators, no ``.`` segments)."""
    return posixpath.normpath(file_path.replace("\\", "/"))


def _load(path: Path) -> dict:
    text = read_text(path, "transforms file")
    try:
        obj = json.loads(text)
    except json.JSONDecodeError as e:
        raise fail(path, None, f"malformed JSON at line {e.lineno} column {e.colno}: {e.msg}") from None
    if not isinstance(obj, dict):
        raise fail(path, None, f"expected a JSON object at the top level, found {type(obj).__name__}")
    return obj


def _lookup(frame: dict, meta: dict, key: str, where: str) -> tuple[Any, str] | None:
    """``(value, where it was found)`` from the frame, else the top level, else ``None``."""
    if key in frame:
        return frame[key], f"{where}.{key}"
    if key in meta:
        return meta[key], key
    return None


def _camera(frame: dict, meta: dict, path: Path, where: str, image: Path) -> dict:
    """``fx, fy, cx, cy, width, height, distortion`` of one frame."""
    out: dict[str, Any] = {}
    for key, name in (("fl_x", "fx"), ("fl_y", "fy"), ("cx", "cx"), ("cy", "cy")):
        found = _lookup(frame, meta, key, where)
        if found is None:
            raise fail(
                path, f"{where}.{key}", f"missing intrinsic {key!r}: expected it in the frame or at the top level"
            )
        out[name] = number(found[0], path, found[1])
    positive(out["fx"], path, f"{where}.fl_x", "focal length in pixels")
    positive(out["fy"], path, f"{where}.fl_y", "focal length in pixels")
    width, height = image_size(image, path, f"{where}.file_path")
    for key, size in (("w", width), ("h", height)):
        found = _lookup(frame, meta, key, where)
        if found is not None and number(found[0], path, found[1]) != size:
            raise fail(
                path,
                found[1],
                f"image {str(image)!r} is {width}x{height} (WxH), expected {key} = {found[0]!r} as the camera "
                "states (intrinsics refer to the image on disk)",
            )
    out["width"], out["height"] = width, height
    coeffs = {}
    for key in (*_DISTORTION_KEYS, "k4"):
        found = _lookup(frame, meta, key, where)
        coeffs[key] = 0.0 if found is None else number(found[0], path, found[1])
    if coeffs["k4"] != 0.0:
        raise fail(
            path,
            f"{where}.k4",
            f"unsupported distortion: nerfstudio's k4 (an r^8 radial term) has no OpenCV equivalent; "
            f"expected k4 = 0, found {coeffs['k4']!r}",
        )
    out["distortion"] = zero_is_none(tuple(coeffs[k] for k in _DISTORTION_KEYS))
    return out


def _points(root: Path, meta: dict, path: Path) -> tuple[np.ndarray | None, np.ndarray | None]:
    if "ply_file_path" not in meta:
        return None, None
    rel = meta["ply_file_path"]
    if not isinstance(rel, str) or not rel:
        raise fail(path, "ply_file_path", f"expected a non-empty string, found {rel!r}")
    ply = root / rel
    if not ply.is_file():
        raise fail(path, "ply_file_path", f"point file {str(ply)!r} does not exist")
    try:
        props = read_ply(ply)
    except PlyError as e:
        raise fail(path, "ply_file_path", str(e)) from None
    missing = [k for k in ("x", "y", "z") if k not in props]
    if missing:
        raise fail(ply, None, f"expected vertex properties x, y, z, missing {missing} (found {sorted(props)})")
    xyz = np.stack([props[k].astype(np.float64) for k in ("x", "y", "z")], axis=1)
    bad = np.flatnonzero(~np.isfinite(xyz).all(axis=1))
    if bad.size:
        raise fail(ply, None, f"expected finite x, y, z, found NaN/Inf at vertices {bad[:5].tolist()}")
    rgb = None
    colours = [k for k in ("red", "green", "blue") if k in props]
    if colours:
        if len(colours) != 3:
            raise fail(ply, None, f"expected vertex properties red, green, blue together, found only {colours}")
        rgb = np.stack([props[k] for k in ("red", "green", "blue")], axis=1).astype(np.float32) / 255.0
    return xyz, rgb


def _splits(meta: dict, names: list[str], path: Path) -> tuple[dict[str, tuple[int, ...]], str]:
    present = [(split, key) for split, key in _SPLIT_KEYS if key in meta]
    if not present:
        return holdout_splits(names), "every 8th held out"
    index = {n: i for i, n in enumerate(names)}
    splits = {}
    for split, key in present:
        listed = meta[key]
        if not isinstance(listed, list):
            raise fail(path, key, f"expected a list of file paths, found {type(listed).__name__}")
        idx = []
        for j, fp in enumerate(listed):
            if not isinstance(fp, str) or normalise(fp) not in index:
                raise fail(path, f"{key}[{j}]", f"expected the file_path of a frame, found {fp!r}")
            idx.append(index[normalise(fp)])
        if idx:
            splits[split] = tuple(sorted(set(idx)))
    return splits, "format"


def read_nerfstudio(root: Path) -> Capture:
    """Read ``<root>/transforms.json``, its images and optional points (module docstring)."""
    root = Path(root)
    path = root / "transforms.json"
    meta = _load(path)
    model = meta.get("camera_model", "PINHOLE")
    if model not in PERSPECTIVE_MODELS:
        raise fail(
            path,
            "camera_model",
            f"unsupported camera model {model!r}: expected one of {', '.join(PERSPECTIVE_MODELS)}",
        )
    entries = [(normalise(frame["file_path"]), i, frame) for i, frame in enumerate(transform_frames(meta, path))]
    entries.sort(key=lambda e: e[0])
    for (a, i, _), (b, j, _) in zip(entries, entries[1:]):
        if a == b:
            raise fail(path, f"frames[{j}].file_path", f"image {a!r} is listed twice (also frames[{i}])")
    views = []
    for name, i, frame in entries:
        where = f"frames[{i}]"
        image = root / name
        if not image.is_file():
            raise fail(path, f"{where}.file_path", f"image {frame['file_path']!r} does not exist ({image})")
        matrix = frame["transform_matrix"]
        if isinstance(matrix, list) and len(matrix) == 3:
            matrix = [*matrix, [0.0, 0.0, 0.0, 1.0]]
        c2w = check_rigid(matrix, path, f"{where}.transform_matrix")
        cam = _camera(frame, meta, path, where, image)
        views.append(CaptureView(name=name, image_path=image.resolve(), c2w=c2w, **cam))
    names = [v.name for v in views]
    splits, rule = _splits(meta, names, path)
    points, rgb = _points(root, meta, path)
    source = (str(path),) + ((str(root / meta["ply_file_path"]),) if points is not None else ())
    return Capture(
        format="nerfstudio",
        root=root,
        views=tuple(views),
        splits=splits,
        split_rule=rule,
        points=points,
        point_rgb=rgb,
        source=source,
    )


read = read_nerfstudio

__all__ = ["PERSPECTIVE_MODELS", "looks_like", "normalise", "read", "read_nerfstudio"]

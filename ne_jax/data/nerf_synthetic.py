"""Read and write scenes in the NeRF Synthetic format.

Layout: ``<scene>/transforms_<split>.json`` for ``split`` in ``train``, ``val``, ``test`` (any other
name works too), each::

    {"camera_angle_x": 0.69,            # horizontal field of view, radians
     "fl_x": .., "fl_y": .., "cx": .., "cy": .., "w": .., "h": ..,   # optional, pixels
     "frames": [{"file_path": "./train/r_0",          # relative to <scene>; ".png" optional
                 "transform_matrix": [[...4x4...]]}]}  # camera-to-world, OpenGL (looks down -z)

and RGBA PNG images (8- or 16-bit; RGB, grey and palette images are accepted with alpha = 1 where
absent). Images are returned as float32 straight (not premultiplied) RGBA in ``[0, 1]``.

When ``fl_x`` is present the pixel intrinsics ``fl_x, fl_y (default fl_x), cx (default W/2),
cy (default H/2)`` win over ``camera_angle_x``; ``w``/``h``, when present, must match the images.

Every bad input raises :class:`DataError` naming the file, the JSON field or frame, what was
expected and what was found.

Images go through :mod:`ne_jax.data.png` (8- and 16-bit PNG codec).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ne_jax.atomic import atomic_directory, atomic_write_json
from ne_jax.data import png
from ne_jax.data.png import DataError, read_image
from ne_jax.data.png import fail as _fail
from ne_jax.data.rays import Camera, Rays, camera_rays

SPLITS = ("train", "val", "test")
RIGID_TOL = 1e-3
"""Tolerance on ``max |R^T R - I|`` (NeRF Synthetic matrices are rigid to ~1e-7)."""
_MISSING_ANGLE = "missing key: expected camera_angle_x (or fl_x) in the top-level object"


# ----------------------------------------------------------------------------------------------
# Transforms JSON
# ----------------------------------------------------------------------------------------------


def _number(value: Any, path: Path, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _fail(path, where, f"expected a number, found {type(value).__name__} {value!r}")
    if not math.isfinite(value):
        raise _fail(path, where, f"expected a finite number, found {value!r}")
    return float(value)


def check_rigid(
    matrix: Any, path: Any = "<array>", where: str = "transform_matrix", tol: float = RIGID_TOL
) -> np.ndarray:
    """Validate a rigid camera-to-world matrix; returns it as float64 ``[4, 4]``.

    Requires: shape 4x4, all finite, last row ``[0, 0, 0, 1]`` (to 1e-6), ``max|R^T R - I| <= tol``
    and ``det R > 0``. Raises :class:`DataError` naming ``path`` and ``where`` otherwise."""
    try:
        m = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError):
        raise _fail(path, where, f"expected a 4x4 array of numbers, found {matrix!r:.200}") from None
    if m.shape != (4, 4):
        raise _fail(path, where, f"expected a 4x4 matrix, found shape {m.shape}")
    if not np.all(np.isfinite(m)):
        bad = [tuple(int(i) for i in ij) for ij in np.argwhere(~np.isfinite(m))]
        raise _fail(path, where, f"expected finite numbers, found NaN/Inf at entries {bad}")
    if np.max(np.abs(m[3] - np.array([0.0, 0.0, 0.0, 1.0]))) > 1e-6:
        raise _fail(
            path, where, f"not a rigid transform: expected last row [0, 0, 0, 1], found {m[3].tolist()}"
        )
    r = m[:3, :3]
    err = float(np.max(np.abs(r.T @ r - np.eye(3))))
    if err > tol:
        scales = np.linalg.norm(r, axis=0)
        raise _fail(
            path,
            where,
            f"not a rigid transform: rotation not orthonormal (max |R^T R - I| = {err:.3g} > {tol:g}; "
            f"column lengths {np.round(scales, 6).tolist()})",
        )
    if np.linalg.det(r) <= 0:
        raise _fail(path, where, "not a rigid transform: rotation has det < 0 (a reflection)")
    return m


def _load_json(path: Path) -> dict:
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise _fail(path, None, "transforms file does not exist") from None
    except (OSError, UnicodeDecodeError) as e:
        raise _fail(path, None, f"cannot read transforms file: {e}") from None
    try:
        obj = json.loads(text)
    except json.JSONDecodeError as e:
        raise _fail(path, None, f"malformed JSON at line {e.lineno} column {e.colno}: {e.msg}") from None
    if not isinstance(obj, dict):
        raise _fail(path, None, f"expected a JSON object at the top level, found {type(obj).__name__}")
    return obj


def _resolve_image(scene_dir: Path, file_path: str, json_path: Path, where: str) -> Path:
    """``./train/r_0`` -> ``<scene>/train/r_0.png`` (the path as written is tried first)."""
    base = scene_dir / file_path
    candidates = [base] if base.suffix else []
    candidates.append(base.with_name(base.name + ".png"))
    for c in candidates:
        if c.is_file():
            return c
    tried = ", ".join(str(c) for c in candidates)
    raise _fail(json_path, where, f"image {file_path!r} does not exist (tried {tried})")


# ----------------------------------------------------------------------------------------------
# Splits
# ----------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class SceneSplit:
    """One split of a scene, host-side (numpy).

    ``images`` ``[N, H, W, 4]`` float32 straight RGBA in [0, 1]; ``c2w`` ``[N, 4, 4]`` float32
    camera-to-world (OpenGL); ``fx, fy, cx, cy`` pixel intrinsics at this resolution (shared by all
    views); ``camera_angle_x`` the horizontal field of view (radians); ``file_paths`` as written in
    the JSON; ``image_paths`` the resolved files; ``downscale`` the factor applied on load."""

    name: str
    images: np.ndarray
    c2w: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    camera_angle_x: float
    file_paths: tuple[str, ...]
    image_paths: tuple[Path, ...]
    downscale: int = 1

    @property
    def num_views(self) -> int:
        return int(self.images.shape[0])

    @property
    def height(self) -> int:
        return int(self.images.shape[1])

    @property
    def width(self) -> int:
        return int(self.images.shape[2])

    def camera(self, index: int) -> Camera:
        """The :class:`Camera` of view ``index``."""
        return Camera(
            c2w=jnp.asarray(self.c2w[index], jnp.float32),
            fx=jnp.asarray(self.fx, jnp.float32),
            fy=jnp.asarray(self.fy, jnp.float32),
            cx=jnp.asarray(self.cx, jnp.float32),
            cy=jnp.asarray(self.cy, jnp.float32),
            width=self.width,
            height=self.height,
        )

    def cameras(self) -> list[Camera]:
        """All views' cameras."""
        return [self.camera(i) for i in range(self.num_views)]

    def take(self, indices: Sequence[int]) -> SceneSplit:
        """The split made of the views ``indices`` (in that order)."""
        idx = [int(i) for i in indices]
        if not idx or any(not 0 <= i < self.num_views for i in idx):
            raise DataError(f"indices: expected a non-empty list of view indices in [0, {self.num_views}) of "
                            f"split {self.name!r}, found {idx}")
        return dataclasses.replace(self, images=self.images[idx], c2w=self.c2w[idx],
                                   file_paths=tuple(self.file_paths[i] for i in idx),
                                   image_paths=tuple(self.image_paths[i] for i in idx))

    def __len__(self) -> int:
        return self.num_views


def transform_frames(meta: dict, path) -> list[dict]:
    """The ``frames`` of a transforms file's JSON ``meta`` (read from ``path``), each checked to be an
    object with a non-empty string ``file_path`` and a ``transform_matrix`` (NeRF Synthetic and
    nerfstudio alike); a :class:`DataError` names the frame and key otherwise."""
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        raise _fail(path, "frames", f"expected a non-empty list of frames, found {frames!r:.100}")
    for i, frame in enumerate(frames):
        where = f"frames[{i}]"
        if not isinstance(frame, dict):
            raise _fail(path, where, f"expected an object, found {type(frame).__name__}")
        for key in ("file_path", "transform_matrix"):
            if key not in frame:
                raise _fail(path, f"{where}.{key}", f"missing key {key!r}")
        fp = frame["file_path"]
        if not isinstance(fp, str) or not fp:
            raise _fail(path, f"{where}.file_path", f"expected a non-empty string, found {fp!r}")
    return frames


def _intrinsics(meta: dict, width: int, height: int, path: Path) -> tuple[float, float, float, float, float]:
    """``(fx, fy, cx, cy, camera_angle_x)`` in pixels at full resolution."""
    for key, size in (("w", width), ("h", height)):
        if key in meta and _number(meta[key], path, key) != size:
            what = "width" if key == "w" else "height"
            raise _fail(path, key, f"expected the image {what} {size}, found {meta[key]!r}")
    if "fl_x" in meta:
        fx = _number(meta["fl_x"], path, "fl_x")
        fy = _number(meta["fl_y"], path, "fl_y") if "fl_y" in meta else fx
        cx = _number(meta["cx"], path, "cx") if "cx" in meta else 0.5 * width
        cy = _number(meta["cy"], path, "cy") if "cy" in meta else 0.5 * height
        for key, v in (("fl_x", fx), ("fl_y", fy)):
            if v <= 0:
                raise _fail(path, key, f"expected a positive focal length in pixels, found {v!r}")
        angle = 2.0 * math.atan(0.5 * width / fx)
        if "camera_angle_x" in meta:
            angle = _number(meta["camera_angle_x"], path, "camera_angle_x")
        return fx, fy, cx, cy, angle
    if "camera_angle_x" not in meta:
        raise _fail(path, "camera_angle_x", _MISSING_ANGLE)
    angle = _number(meta["camera_angle_x"], path, "camera_angle_x")
    if not 0.0 < angle < math.pi:
        raise _fail(path, "camera_angle_x", f"expected a field of view in (0, pi) radians, found {angle!r}")
    focal = 0.5 * width / math.tan(0.5 * angle)
    return focal, focal, 0.5 * width, 0.5 * height, angle


def transforms_path(scene_dir: str | os.PathLike, split: str) -> Path:
    """``<scene_dir>/transforms_<split>.json``."""
    if not split or not re.fullmatch(r"[A-Za-z0-9_.\-]+", split):
        raise DataError(f"split name: expected letters, digits, '_', '-' or '.', found {split!r}")
    return Path(scene_dir) / f"transforms_{split}.json"


def load_split(scene_dir: str | os.PathLike, split: str, downscale: int = 1) -> SceneSplit:
    """Load ``transforms_<split>.json`` and its images, downscaled by the integer ``downscale``
    (see :func:`downscale_rgba`: remainders are cropped, intrinsics divided by the factor)."""
    scene_dir = Path(scene_dir)
    if not scene_dir.is_dir():
        raise _fail(scene_dir, None, "scene directory does not exist")
    if isinstance(downscale, bool) or not isinstance(downscale, (int, np.integer)) or downscale < 1:
        raise DataError(f"downscale: expected an integer >= 1, found {downscale!r}")
    path = transforms_path(scene_dir, split)
    meta = _load_json(path)
    if "frames" not in meta:
        raise _fail(path, "frames", "missing key: expected a list of frames in the top-level object")
    if "fl_x" not in meta and "camera_angle_x" not in meta:
        raise _fail(path, "camera_angle_x", _MISSING_ANGLE)
    c2ws, file_paths, image_paths, images = [], [], [], []
    for i, frame in enumerate(transform_frames(meta, path)):
        where, fp = f"frames[{i}]", frame["file_path"]
        c2ws.append(check_rigid(frame["transform_matrix"], path, f"{where}.transform_matrix"))
        image_path = _resolve_image(scene_dir, fp, path, f"{where}.file_path")
        try:
            img = read_image(image_path)
        except DataError as e:
            raise _fail(path, f"{where}.file_path", str(e)) from None
        if images and img.shape != images[0].shape:
            raise _fail(
                path,
                f"{where}.file_path",
                f"images of different sizes in one split: {image_path} is {img.shape[1]}x{img.shape[0]} "
                f"(WxH), expected {images[0].shape[1]}x{images[0].shape[0]} like {image_paths[0]}",
            )
        file_paths.append(fp)
        image_paths.append(image_path)
        images.append(img)
    height, width = images[0].shape[:2]
    fx, fy, cx, cy, angle = _intrinsics(meta, width, height, path)
    stack = np.stack(images)
    if downscale > 1:
        if downscale > min(height, width):
            raise DataError(
                f"downscale: factor {downscale} exceeds the image size {width}x{height} of {path}"
            )
        stack = downscale_rgba(stack, int(downscale))
        fx, fy, cx, cy = fx / downscale, fy / downscale, cx / downscale, cy / downscale
    return SceneSplit(
        name=split,
        images=stack,
        c2w=np.stack(c2ws).astype(np.float32),
        fx=fx,
        fy=fy,
        cx=cx,
        cy=cy,
        camera_angle_x=angle,
        file_paths=tuple(file_paths),
        image_paths=tuple(image_paths),
        downscale=int(downscale),
    )


def load_scene(
    scene_dir: str | os.PathLike, downscale: int = 1, splits: Sequence[str] | None = None
) -> dict[str, SceneSplit]:
    """Load several splits: ``splits=None`` loads those of ``train``/``val``/``test`` whose
    transforms file exists (at least one must); named splits must all exist."""
    scene_dir = Path(scene_dir)
    if not scene_dir.is_dir():
        raise _fail(scene_dir, None, "scene directory does not exist")
    if splits is None:
        splits = [s for s in SPLITS if transforms_path(scene_dir, s).is_file()]
        if not splits:
            expected = ", ".join(f"transforms_{s}.json" for s in SPLITS)
            raise _fail(scene_dir, None, f"no transforms file: expected one of {expected}")
    return {s: load_split(scene_dir, s, downscale) for s in splits}


def write_split(
    scene_dir: str | os.PathLike,
    split: str,
    images: np.ndarray,
    c2ws: np.ndarray,
    camera_angle_x: float,
    bit_depth: int = 8,
    extra: Mapping[str, Any] | None = None,
) -> Path:
    """Write ``<scene>/<split>/r_<i>.png`` and ``transforms_<split>.json``; returns the JSON path.

    ``images`` ``[N, H, W, 3|4]`` float in [0, 1] straight alpha (or uint8/uint16 matching
    ``bit_depth``); ``c2ws`` ``[N, 4, 4]`` rigid camera-to-world (OpenGL); ``extra`` adds top-level
    JSON fields (e.g. ``fl_x``). Crash-safe: all images are written to a temporary directory that
    replaces ``<split>/`` only when complete; an existing JSON is removed before that swap and the
    new JSON is written (atomically) last, so a JSON never points at missing or partial images."""
    scene_dir = Path(scene_dir)
    json_path = transforms_path(scene_dir, split)
    images = np.asarray(images)
    c2ws = np.asarray(c2ws)
    if images.ndim != 4 or images.shape[-1] not in (3, 4):
        raise DataError(f"write_split images: expected [N, H, W, 3|4], found shape {images.shape}")
    if c2ws.shape != (images.shape[0], 4, 4):
        raise DataError(f"write_split c2ws: expected shape ({images.shape[0]}, 4, 4), found {c2ws.shape}")
    angle = float(camera_angle_x)
    if not (math.isfinite(angle) and 0.0 < angle < math.pi):
        raise DataError(f"write_split camera_angle_x: expected radians in (0, pi), found {camera_angle_x!r}")
    for i, m in enumerate(c2ws):
        check_rigid(m, "write_split c2ws", f"{i}")
    pixels = png.quantise(images, bit_depth, "write_split images")
    extra = dict(extra or {})
    for key in ("frames", "camera_angle_x"):
        if key in extra:
            raise DataError(f"write_split extra: {key!r} is written by write_split itself")
    frames = []
    with atomic_directory(scene_dir / split) as tmp:
        for i in range(pixels.shape[0]):
            name = f"r_{i}"
            (tmp / f"{name}.png").write_bytes(png.encode_png(pixels[i]))
            matrix = c2ws[i].astype(np.float64).tolist()
            frames.append({"file_path": f"./{split}/{name}", "transform_matrix": matrix})
        json_path.unlink(missing_ok=True)
    atomic_write_json(json_path, {"camera_angle_x": angle, **extra, "frames": frames})
    return json_path


# ----------------------------------------------------------------------------------------------
# Image operations
# ----------------------------------------------------------------------------------------------


def downscale_rgba(images: np.ndarray, factor: int) -> np.ndarray:
    """Area-average ``[..., H, W, 4]`` straight RGBA by an integer ``factor`` -> ``[..., H//f, W//f, 4]``.

    Colour is averaged premultiplied and then un-premultiplied, so transparent pixels do not darken
    edges; blocks with zero total alpha take the plain colour average. Rows/columns beyond a multiple
    of ``factor`` (at the bottom/right) are cropped, which keeps ``cx/f, cy/f`` exact."""
    images = np.asarray(images, np.float32)
    if factor == 1:
        return images
    *lead, h, w, c = images.shape
    if c != 4:
        raise DataError(f"downscale_rgba: expected RGBA [..., H, W, 4], found shape {images.shape}")
    hh, ww = h // factor, w // factor
    x = images[..., : hh * factor, : ww * factor, :].astype(np.float64)
    x = x.reshape(*lead, hh, factor, ww, factor, 4)
    alpha = x[..., 3:4]
    sum_a = alpha.sum(axis=(-4, -2))
    sum_rgb_a = (x[..., :3] * alpha).sum(axis=(-4, -2))
    mean_rgb = x[..., :3].mean(axis=(-4, -2))
    rgb = np.where(sum_a > 0, sum_rgb_a / np.where(sum_a > 0, sum_a, 1.0), mean_rgb)
    out = np.concatenate([np.clip(rgb, 0.0, 1.0), sum_a / factor**2], axis=-1)
    return out.astype(np.float32)


_NAMED_BACKGROUNDS = {"black": (0.0, 0.0, 0.0), "white": (1.0, 1.0, 1.0)}


def parse_background(x: Any) -> np.ndarray:
    """A background colour as float32 ``[3]`` in [0, 1].

    Accepts ``"black"``, ``"white"``, a string ``"r,g,b"`` or a 3-sequence/array. Integers mean
    0-255 levels and floats mean [0, 1]: ``"255,128,0"`` and ``(255, 128, 0)`` are 8-bit levels,
    ``"1.0,0.5,0"`` and ``(1.0, 0.5, 0.0)`` are fractions (a string with any ``.`` is read as
    fractions). Anything else raises :class:`DataError`."""
    original = x
    if isinstance(x, str):
        s = x.strip().lower()
        if s in _NAMED_BACKGROUNDS:
            return np.asarray(_NAMED_BACKGROUNDS[s], np.float32)
        parts = [p.strip() for p in s.split(",")]
        if len(parts) != 3:
            raise DataError(
                f"background {original!r}: expected 'black', 'white' or 'r,g,b', "
                f"found {len(parts)} component(s)"
            )
        as_float = any("." in p or "e" in p for p in parts)
        try:
            values = [float(p) if as_float else int(p) for p in parts]
        except ValueError:
            msg = f"background {original!r}: expected three numbers 'r,g,b', found {parts}"
            raise DataError(msg) from None
        x = values
    if isinstance(x, np.ndarray):
        if x.shape != (3,):
            raise DataError(f"background {original!r}: expected 3 components, found shape {x.shape}")
        x = x.tolist()
    if not isinstance(x, (list, tuple)) or len(x) != 3:
        raise DataError(f"background {original!r}: expected 'black', 'white', 'r,g,b' or 3 numbers")
    if any(isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) for v in x):
        raise DataError(f"background {original!r}: expected 3 numbers, found {[type(v).__name__ for v in x]}")
    if all(isinstance(v, (int, np.integer)) for v in x):
        if not all(0 <= v <= 255 for v in x):
            raise DataError(f"background {original!r}: integer components are 0-255 levels, found {list(x)}")
        return np.asarray(x, np.float32) / np.float32(255.0)
    values = [float(v) for v in x]
    if not all(math.isfinite(v) and 0.0 <= v <= 1.0 for v in values):
        raise DataError(
            f"background {original!r}: float components are fractions in [0, 1], found {values} "
            "(use integers for 0-255 levels)"
        )
    return np.asarray(values, np.float32)


def composite(rgba, background):
    """``rgb * a + bg * (1 - a)`` for straight RGBA ``[..., 4]`` -> RGB ``[..., 3]``.

    ``background`` is anything :func:`parse_background` accepts, or an array broadcastable to
    ``[..., 3]`` (per-pixel backgrounds). Works on numpy (host) and jax (device) arrays alike."""
    is_color_array = isinstance(background, np.ndarray) and background.shape == (3,)
    if isinstance(background, (str, tuple, list)) or is_color_array:
        background = parse_background(background)
    rgb, a = rgba[..., :3], rgba[..., 3:4]
    return rgb * a + background * (1 - a)


def split_rays(split: SceneSplit, near: float, far: float, background=None) -> Rays:
    """Rays of all pixels of all views, ``R = N * H * W`` in view-major, row-major order.

    ``target`` ``[R, 4]``: straight RGBA when ``background`` is None; otherwise the RGB composited
    on ``background`` with alpha 1 (an opaque image, so compositing it again changes nothing)."""
    base = split.camera(0)
    rays = jax.vmap(lambda c2w: camera_rays(base.replace(c2w=c2w), near, far))(jnp.asarray(split.c2w))
    rays = jax.tree_util.tree_map(lambda a: a.reshape((-1,) + a.shape[2:]), rays)
    return rays.replace(target=jnp.asarray(_target(split.images, background)).reshape(-1, 4))


def view_rays(split: SceneSplit, index: int, near: float, far: float, background=None) -> Rays:
    """Rays of view ``index``: ``H * W`` rays in row-major order, target as in :func:`split_rays`."""
    rays = camera_rays(split.camera(index), near, far)
    return rays.replace(target=jnp.asarray(_target(split.images[index], background)).reshape(-1, 4))


def _target(images: np.ndarray, background) -> np.ndarray:
    if background is None:
        return images
    rgb = composite(images, background)
    return np.concatenate([rgb, np.ones_like(rgb[..., :1])], axis=-1).astype(np.float32)

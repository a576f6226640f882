"""Read a COLMAP reconstruction into a :class:`~ne_jax.data.capture.Capture`.

Layout::

    <root>/images/<name>                 # the images, named as in the model (sub-folders allowed)
    <root>/sparse/0/cameras.bin|txt      # the model; <root>/sparse/ directly also works
    <root>/sparse/0/images.bin|txt
    <root>/sparse/0/points3D.bin|txt

The model is read with ``pycolmap`` (COLMAP's own bindings), binary when all three ``.bin`` files
are there, else text. Conventions: COLMAP stores world-to-camera poses with OpenCV camera axes
(``+z`` forward, ``+y`` down); the reader inverts them and flips the camera's ``y``/``z`` axes
into the capture's OpenGL camera-to-world. Intrinsics are pixels of the image on disk with pixel
centres at ``i + 0.5``, COLMAP's own convention. Only registered images (those with a pose) are
views, sorted by name; every 8th is held out as the test split. Points: ``xyz``, ``rgb / 255``
and the reprojection error (NaN where COLMAP has not computed it).

Camera models: ``SIMPLE_PINHOLE``, ``PINHOLE``, ``SIMPLE_RADIAL``, ``RADIAL``, ``OPENCV``,
``FULL_OPENCV`` (whose distortions are OpenCV's ``k1, k2, p1, p2[, k3, k4, k5, k6]``); fisheye
and other models raise :class:`~ne_jax.data.png.DataError`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ne_jax.data.capture import Capture, CaptureView, holdout_splits, opencv_to_opengl
from ne_jax.data.formats._common import check_size, number, positive, zero_is_none
from ne_jax.data.nerf_synthetic import check_rigid
from ne_jax.data.png import fail

MIN_REGISTERED = 3
"""Fewer registered images than this is not a usable reconstruction."""

SUPPORTED_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")
_NUM_PARAMS = {"SIMPLE_PINHOLE": 3, "PINHOLE": 4, "SIMPLE_RADIAL": 4, "RADIAL": 5, "OPENCV": 8, "FULL_OPENCV": 12}
_MODEL_FILES = ("cameras", "images", "points3D")


def model_dir(root: Path) -> Path | None:
    """``<root>/sparse/0`` if it holds a model, else ``<root>/sparse`` if that does, else ``None``."""
    for d in (Path(root) / "sparse" / "0", Path(root) / "sparse"):
        if (d / "cameras.bin").is_file() or (d / "cameras.txt").is_file():
            return d
    return None


def looks_like(root: Path) -> bool:
    """True when ``sparse/0/cameras.bin|txt`` or ``sparse/cameras.bin|txt`` exists under ``root``."""
    return model_dir(root) is not None


def _model_files(d: Path) -> tuple[str, tuple[Path, Path, Path]]:
    """``("binary" | "text", (cameras, images, points3D))`` for the model in ``d``."""
    for kind, ext in (("binary", ".bin"), ("text", ".txt")):
        files = tuple(d / f"{name}{ext}" for name in _MODEL_FILES)
        if all(f.is_file() for f in files):
            return kind, files
    found = sorted(p.name for p in d.iterdir() if p.is_file())
    raise fail(
        d,
        None,
        f"incomplete COLMAP model: expected cameras, images and points3D as all .bin or all .txt files, found {found}",
    )


def _intrinsics(camera, cameras_file: Path) -> tuple[float, float, float, float, tuple[float, ...] | None]:
    """``(fx, fy, cx, cy, distortion)`` of a pycolmap camera; unsupported models raise."""
    model = camera.model.name
    where = f"camera {camera.camera_id}"
    if model not in _NUM_PARAMS:
        raise fail(
            cameras_file,
            where,
            f"unsupported camera model {model}: expected one of {', '.join(SUPPORTED_MODELS)} "
            "(undistort fisheye and other models first, e.g. with colmap image_undistorter)",
        )
    p = [number(v, cameras_file, f"{where} params[{i}]") for i, v in enumerate(np.asarray(camera.params))]
    if len(p) != _NUM_PARAMS[model]:
        raise fail(cameras_file, where, f"model {model} expects {_NUM_PARAMS[model]} parameters, found {len(p)}")
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        fx = fy = p[0]
        cx, cy = p[1], p[2]
        k = p[3:] + [0.0] * (4 - len(p[3:]))  # SIMPLE_RADIAL: k; RADIAL: k1 k2 -> OpenCV's k1 k2 p1 p2
        dist = tuple(k)
    else:
        fx, fy, cx, cy = p[:4]
        dist = tuple(p[4:])  # OPENCV: k1 k2 p1 p2; FULL_OPENCV: k1 k2 p1 p2 k3 k4 k5 k6 (OpenCV's order)
    positive(fx, cameras_file, where, "focal length fx in pixels")
    positive(fy, cameras_file, where, "focal length fy in pixels")
    return fx, fy, cx, cy, zero_is_none(dist)


def _c2w(image, images_file: Path, where: str) -> np.ndarray:
    """OpenGL camera-to-world of a pycolmap image (world-to-camera, OpenCV axes, in the model)."""
    pose = image.cam_from_world
    pose = pose() if callable(pose) else pose  # a method in pycolmap 4.x, a property before
    w2c = np.asarray(pose.matrix(), dtype=np.float64)
    rot, t = w2c[:3, :3], w2c[:3, 3]
    c2w = np.eye(4)
    c2w[:3, :3] = rot.T
    c2w[:3, 3] = -rot.T @ t
    return check_rigid(opencv_to_opengl(c2w), images_file, where)


def read_colmap(root: Path) -> Capture:
    """Read ``<root>/images`` and the COLMAP model under ``<root>/sparse`` (module docstring)."""
    import pycolmap

    root = Path(root)
    d = model_dir(root)
    if d is None:
        raise fail(root, None, "not a COLMAP folder: expected sparse/0/cameras.bin|txt or sparse/cameras.bin|txt")
    kind, (cameras_file, images_file, points_file) = _model_files(d)
    rec = pycolmap.Reconstruction()
    try:
        (rec.read_binary if kind == "binary" else rec.read_text)(str(d))
    except Exception as e:  # pycolmap raises ValueError/IndexError/RuntimeError with COLMAP's check text
        raise fail(d, None, f"cannot read the {kind} COLMAP model: {e}") from None
    image_dir = root / "images"
    if not image_dir.is_dir():
        raise fail(image_dir, None, f"image folder does not exist (the model in {d} names its images)")

    registered = sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name)
    if len(registered) < MIN_REGISTERED:
        raise fail(
            images_file,
            None,
            f"expected at least {MIN_REGISTERED} registered images (with a pose), found {len(registered)} "
            f"of {rec.num_images()} images",
        )
    intrinsics: dict[int, tuple] = {}
    views = []
    for im in registered:
        where = f"image {im.image_id} {im.name!r}"
        cam = rec.cameras[im.camera_id]
        if im.camera_id not in intrinsics:
            intrinsics[im.camera_id] = _intrinsics(cam, cameras_file)
        fx, fy, cx, cy, dist = intrinsics[im.camera_id]
        path = image_dir / im.name
        if not path.is_file():
            raise fail(images_file, where, f"image file {str(path)!r} does not exist")
        width, height = int(cam.width), int(cam.height)
        check_size(path, images_file, where, width, height)
        views.append(
            CaptureView(
                name=im.name,
                image_path=path.resolve(),
                c2w=_c2w(im, images_file, where),
                fx=fx,
                fy=fy,
                cx=cx,
                cy=cy,
                width=width,
                height=height,
                distortion=dist,
            )
        )

    points = point_rgb = point_error = None
    if rec.num_points3D() > 0:
        items = sorted(rec.points3D.items())
        points = np.array([p.xyz for _, p in items], dtype=np.float64).reshape(-1, 3)
        point_rgb = np.array([p.color for _, p in items], dtype=np.float32).reshape(-1, 3) / 255.0
        point_error = np.array([p.error if p.error >= 0 else np.nan for _, p in items], dtype=np.float64)
        bad = ~np.all(np.isfinite(points), axis=1)
        if bad.any():
            ids = [items[i][0] for i in np.flatnonzero(bad)[:5]]
            raise fail(points_file, f"points {ids}", "expected finite xyz, found NaN/Inf")

    names = [v.name for v in views]
    return Capture(
        format="colmap",
        root=root,
        views=tuple(views),
        splits=holdout_splits(names),
        split_rule="every 8th held out",
        points=points,
        point_rgb=point_rgb,
        point_error=point_error,
        source=(str(cameras_file), str(images_file), str(points_file)),
    )


read = read_colmap

__all__ = ["MIN_REGISTERED", "SUPPORTED_MODELS", "looks_like", "model_dir", "read", "read_colmap"]

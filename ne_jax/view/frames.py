"""Frames for the viewer, without the GUI: a browser camera as a :class:`~ne_jax.data.rays.Camera`, one
render of a model, and a render output as an 8-bit image in one of the render modes.

Browser cameras (viser's) follow the OpenCV convention (``+z`` forward, ``+y`` down) with a vertical
field of view; ne_jax's cameras are OpenGL (``-z`` forward, ``+y`` up): the two differ by flipping the
camera's ``y`` and ``z`` axes.
"""

from __future__ import annotations

import math
import time

import jax
import jax.numpy as jnp
import numpy as np

from ne_jax.data.nerf_synthetic import parse_background
from ne_jax.data.rays import Camera
from ne_jax.render.driver import render_image
from ne_jax.render.quadrature import at_test_time
from ne_jax.render.renderer import RenderOut
from ne_jax.view.edits import matrix_to_quat, quat_to_matrix

MODES = ("rgb", "depth", "normals", "opacity")
"""Render modes: the colour, the expected depth (near = bright), the opacity-weighted shading normal
(``0.5 + 0.5 n``) and the opacity (the accumulated alpha, how sure the model is a ray hits something)."""

_CV_TO_GL = np.diag([1.0, -1.0, -1.0])


def camera_from_viewer(wxyz, position, fov_y: float, width: int, height: int) -> Camera:
    """A pinhole :class:`Camera` of ``width x height`` pixels (centred principal point) from a browser
    camera: orientation ``wxyz`` and ``position`` ``[3]`` in the OpenCV convention, vertical field of
    view ``fov_y`` radians."""
    if not (isinstance(width, (int, np.integer)) and isinstance(height, (int, np.integer)) and width > 0
            and height > 0):
        raise ValueError(f"camera_from_viewer: expected positive integer width and height, found {width!r}, {height!r}")
    if not (0 < fov_y < math.pi):
        raise ValueError(f"camera_from_viewer: expected a vertical field of view in (0, pi) radians, found {fov_y!r}")
    c2w = np.eye(4)
    c2w[:3, :3] = quat_to_matrix(wxyz) @ _CV_TO_GL
    c2w[:3, 3] = np.asarray(position, np.float64).reshape(3)
    focal = 0.5 * height / math.tan(0.5 * fov_y)
    f = jnp.asarray(focal, jnp.float32)
    return Camera(c2w=jnp.asarray(c2w, jnp.float32), fx=f, fy=f, cx=jnp.asarray(0.5 * width, jnp.float32),
                  cy=jnp.asarray(0.5 * height, jnp.float32), width=int(width), height=int(height))


def viewer_pose(c2w_gl) -> tuple[np.ndarray, np.ndarray]:
    """``(R_cv [3, 3], position [3])`` of an OpenGL camera-to-world ``[4, 4]`` in the OpenCV
    convention (for frustums and the browser camera)."""
    c2w = np.asarray(c2w_gl, np.float64)
    return c2w[:3, :3] @ _CV_TO_GL, c2w[:3, 3].copy()


def fit_size(width: int, height: int, max_side: int) -> tuple[int, int]:
    """``(w, h)``: the browser's ``width x height`` scaled so that its longer side is at most
    ``max_side`` (aspect kept, each side at least 1)."""
    width, height = max(int(width), 1), max(int(height), 1)
    s = min(1.0, max_side / max(width, height))
    return max(1, round(width * s)), max(1, round(height * s))


def look_at(position, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """``wxyz`` ``[4]``: the orientation of an OpenCV camera at ``position`` looking at ``target``
    with ``up`` (not parallel to the view direction) pointing up in the image."""
    fwd = np.asarray(target, np.float64) - np.asarray(position, np.float64)
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, np.asarray(up, np.float64))
    right /= np.linalg.norm(right)
    return matrix_to_quat(np.stack([right, np.cross(fwd, right), fwd], 1))


def render_model(model, camera: Camera, pixel_samples: int | None = None) -> RenderOut:
    """Render ``model`` (a :class:`~ne_jax.train.model.TrainedModel`) from ``camera`` as the evaluation
    does (a stochastic quadrature rule is rendered un-jittered), fields as images ``[H, W, ...]``.
    ``pixel_samples``: rays per pixel side instead of the model's own (e.g. 1 for a quick preview)."""
    cfg = model.run.render
    cfg = cfg.replace(quadrature=at_test_time(cfg.quadrature))
    if pixel_samples is not None:
        cfg = cfg.replace(pixel_samples=int(pixel_samples))
    return render_image(cfg, model.params, model.scene, camera, parse_background(model.background), model.near,
                        model.far, progress=False)


def to_image(out: RenderOut, mode: str, near: float, far: float, background=(1.0, 1.0, 1.0)) -> np.ndarray:
    """``[H, W, 3]`` uint8 image of a render output in ``mode`` (one of :data:`MODES`). Depth is
    shown where the opacity exceeds 0.5, scaled between ``near`` and ``far`` (near bright) and
    composited on ``background``; normals as ``0.5 + 0.5 n``."""
    if mode not in MODES:
        raise ValueError(f"to_image: mode must be one of {', '.join(MODES)}, found {mode!r}")
    rgb, opacity, depth, normal = jax.device_get((out.rgb, out.opacity, out.depth, out.normal))
    opacity = np.asarray(opacity, np.float32)
    if mode == "rgb":
        img = np.asarray(rgb, np.float32)
    elif mode == "opacity":
        img = np.repeat(opacity[..., None], 3, axis=-1)
    elif mode == "normals":
        img = 0.5 + 0.5 * np.asarray(normal, np.float32)
    else:
        d = np.asarray(depth, np.float32) / np.maximum(opacity, 1e-6)
        t = np.clip((far - d) / max(far - near, 1e-6), 0.0, 1.0)
        hit = (opacity > 0.5)[..., None]
        img = np.where(hit, np.repeat(t[..., None], 3, axis=-1), np.asarray(background, np.float32))
    return np.clip(np.round(np.nan_to_num(img) * 255.0), 0, 255).astype(np.uint8)


def render_frame(model, camera: Camera, mode: str = "rgb",
                 pixel_samples: int | None = None) -> tuple[np.ndarray, float]:
    """``(image [H, W, 3] uint8, seconds)``: one frame of ``model`` from ``camera`` in ``mode``
    (``pixel_samples``: see :func:`render_model`), and the wall time of the render (device work
    included)."""
    t0 = time.perf_counter()
    out = render_model(model, camera, pixel_samples)
    bg = np.asarray(parse_background(model.background), np.float32)
    img = to_image(out, mode, model.near, model.far, bg)
    return img, time.perf_counter() - t0


__all__ = ["MODES", "camera_from_viewer", "fit_size", "look_at", "render_frame", "render_model", "to_image",
           "viewer_pose"]

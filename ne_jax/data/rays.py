"""Pinhole cameras (OpenGL convention) and the rays they shoot.

Conventions (as in NeRF Synthetic / Blender): camera-to-world ``c2w`` is 4x4, the camera looks down
its local ``-z`` axis, ``+y`` is up in the image and ``+x`` is right. Pixel ``(i, j)`` (column, row)
has its centre at ``(i + 0.5, j + 0.5)``; row 0 is the top of the image.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct


@struct.dataclass
class Rays:
    """A batch of rays. Shapes: ``origin``/``direction`` ``[R, 3]`` (direction unit length),
    ``near``/``far`` ``[R]``; ``target`` ``[R, 4]`` straight-alpha RGBA in ``[0, 1]`` or ``None``."""

    origin: jax.Array
    direction: jax.Array
    near: jax.Array
    far: jax.Array
    target: jax.Array | None = None

    @property
    def num_rays(self) -> int:
        return self.origin.shape[0]

    def take(self, index) -> Rays:
        """Rays selected by ``index`` (a slice, an index array or a mask) along the ray axis."""
        return jax.tree_util.tree_map(lambda a: a[index], self)


@struct.dataclass
class Camera:
    """A pinhole camera. ``c2w`` ``[4, 4]`` camera-to-world (OpenGL); focal lengths and principal
    point in pixels; ``width``/``height`` are static (they set array shapes)."""

    c2w: jax.Array
    fx: jax.Array
    fy: jax.Array
    cx: jax.Array
    cy: jax.Array
    width: int = struct.field(pytree_node=False)
    height: int = struct.field(pytree_node=False)

    @classmethod
    def from_fov(cls, c2w, width: int, height: int, camera_angle_x: float) -> Camera:
        """NeRF Synthetic intrinsics: ``fx = fy = 0.5 W / tan(camera_angle_x / 2)``, centred."""
        focal = 0.5 * width / math.tan(0.5 * float(camera_angle_x))
        return cls(
            c2w=jnp.asarray(c2w, jnp.float32),
            fx=jnp.asarray(focal, jnp.float32),
            fy=jnp.asarray(focal, jnp.float32),
            cx=jnp.asarray(0.5 * width, jnp.float32),
            cy=jnp.asarray(0.5 * height, jnp.float32),
            width=int(width),
            height=int(height),
        )

    def scaled(self, factor: int) -> Camera:
        """The same camera for an image downscaled by the integer ``factor`` (size floored)."""
        return self.replace(
            fx=self.fx / factor,
            fy=self.fy / factor,
            cx=self.cx / factor,
            cy=self.cy / factor,
            width=self.width // factor,
            height=self.height // factor,
        )


def rays_through_pixels(c2w, fx, fy, cx, cy, pixels: jax.Array, near: float, far: float) -> Rays:
    """Rays through image positions ``pixels`` ``[R, 2]`` given as ``(x, y)`` in pixel units (pixel
    centres at ``i + 0.5``) of pinhole cameras ``c2w`` ``[4, 4]`` (one camera) or ``[R, 4, 4]`` (one
    per ray) with intrinsics ``fx, fy, cx, cy`` (scalars). Unit directions in world space."""
    c2w = jnp.asarray(c2w)
    pixels = jnp.asarray(pixels, c2w.dtype)
    x = (pixels[:, 0] - cx) / fx
    y = -(pixels[:, 1] - cy) / fy
    d_cam = jnp.stack([x, y, -jnp.ones_like(x)], axis=-1)
    d_world = jnp.einsum("...ij,...j->...i", c2w[..., :3, :3], d_cam)
    direction = d_world / jnp.linalg.norm(d_world, axis=-1, keepdims=True)
    origin = jnp.broadcast_to(c2w[..., :3, 3], direction.shape)
    r = direction.shape[0]
    return Rays(
        origin=origin,
        direction=direction,
        near=jnp.full((r,), near, direction.dtype),
        far=jnp.full((r,), far, direction.dtype),
    )


def pixel_rays(camera: Camera, pixels: jax.Array, near: float, far: float) -> Rays:
    """Rays of ``camera`` through image positions ``pixels`` ``[R, 2]`` (see
    :func:`rays_through_pixels`)."""
    return rays_through_pixels(camera.c2w, camera.fx, camera.fy, camera.cx, camera.cy, pixels, near, far)


def subpixel_offsets(n: int) -> np.ndarray:
    """``[n * n, 2]`` positions ``((a + 0.5) / n, (b + 0.5) / n)`` inside a pixel, ``(x, y)``, row
    by row: the regular grid of a pixel's ``n x n`` rays (``n = 1``: the centre)."""
    if int(n) < 1:
        raise ValueError(f"subpixel_offsets: expected n >= 1 rays per pixel side, found {n}")
    b, a = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    return ((np.stack([a.ravel(), b.ravel()], axis=-1) + 0.5) / n).astype(np.float32)


def pixel_centers(width: int, height: int, pixel_samples: int = 1) -> np.ndarray:
    """``[H * W * n * n, 2]`` image positions of every pixel's ``n x n`` rays
    (:func:`subpixel_offsets`, ``n = pixel_samples``), pixels in row-major order (row 0 first) and
    each pixel's rays consecutive; ``n = 1``: the pixel centres ``(i + 0.5, j + 0.5)``."""
    j, i = np.meshgrid(np.arange(height), np.arange(width), indexing="ij")
    corners = np.stack([i.ravel(), j.ravel()], axis=-1).astype(np.float32)
    return (corners[:, None, :] + subpixel_offsets(pixel_samples)[None]).reshape(-1, 2)


def camera_rays(camera: Camera, near: float, far: float, pixel_samples: int = 1) -> Rays:
    """All rays of ``camera``: ``pixel_samples x pixel_samples`` per pixel (:func:`pixel_centers`;
    1: the pixel centres), ``[H * W * pixel_samples**2]`` in row-major pixel order."""
    return pixel_rays(camera, jnp.asarray(pixel_centers(camera.width, camera.height, pixel_samples)), near, far)

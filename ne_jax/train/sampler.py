"""Training ray batches: foreground pixels plus a border band around the foreground.

The host builds a :class:`RayPool` once from a :class:`~ne_jax.data.nerf_synthetic.SceneSplit`:

* foreground = pixels with ``alpha > 0`` (partially covered edge pixels included);
* band = pixels within ``band_width`` pixels of the foreground (Chebyshev distance: a square
  dilation of the mask) that are not foreground; they teach the model where the object ends;
* every pool entry is a flat pixel index ``view * H * W + row * W + col`` and its target: the RGB
  composited on the user's background colour (``rgb * a + bg * (1 - a)``; the background is never
  copied from ground truth into predictions, docs/design.md).

:func:`sample_batch` (jit) draws a fixed-size batch from the pool with a PRNG key: ``num_band``
band pixels and ``batch_size - num_band`` foreground pixels (uniform, with replacement), so the
batch shape is static and the training step never recompiles. It is a pure function of
``(cfg, pool, key)``: the same key gives the same batch. Rays are generated on the device from the
cameras stored in the pool (pixel centres at ``i + 0.5``, OpenGL convention, as
:func:`~ne_jax.data.rays.pixel_rays`; or each pixel's ``n x n`` grid of rays, whose mean colour the
training step compares with the pixel, for a model with ``RenderConfig.pixel_samples = n``).
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from scipy import ndimage

from ne_jax.data.nerf_synthetic import SceneSplit, composite, parse_background
from ne_jax.data.rays import Rays, rays_through_pixels, subpixel_offsets


@dataclasses.dataclass(frozen=True)
class SamplerConfig:
    """Static settings of the ray sampler (hashable)."""

    batch_size: int = 4096
    """Rays per batch (docs/design.md: 4096). Static: it sets the step's array shapes."""
    band_width: int = 4
    """Width in pixels of the border band around the foreground mask (square dilation); 0: no band."""
    band_fraction: float = 0.1
    """Share of each batch drawn from the band (the background share); rounded to whole rays.
    Ignored (all foreground) when the band is empty."""
    near: float = 2.0
    """Ray start distance (the benchmark's ``scene.json`` ``near``)."""
    far: float = 6.0
    """Ray end distance (the benchmark's ``scene.json`` ``far``)."""
    bounds_from_scene: bool = True
    """For a capture (any layout but NeRF Synthetic): ``near``/``far`` are replaced by the envelope
    of the cameras' near/far from its SfM points (:func:`ne_jax.data.scene.scene_near_far`) when a
    run starts, and the run's ``config.json`` holds the values used. ``False``: the values above."""
    pixel_samples: int = 1
    """Rays per pixel side of the training batches (:attr:`~ne_jax.train.run.RunConfig.train_render`;
    ``RenderConfig.pixel_samples`` is the images' grid): 1 trains on pixel centres."""

    def __post_init__(self):
        if int(self.pixel_samples) < 1:
            raise ValueError(f"SamplerConfig.pixel_samples: expected rays per pixel side >= 1, "
                             f"found {self.pixel_samples}")
        if int(self.batch_size) < 1:
            raise ValueError(f"SamplerConfig.batch_size: expected an integer >= 1, found {self.batch_size}")
        if int(self.band_width) < 0:
            raise ValueError(f"SamplerConfig.band_width: expected an integer >= 0, found {self.band_width}")
        if not 0.0 <= float(self.band_fraction) < 1.0:
            raise ValueError(f"SamplerConfig.band_fraction: expected a value in [0, 1), found {self.band_fraction}")
        if not 0.0 <= self.near < self.far:
            raise ValueError(f"SamplerConfig: expected 0 <= near < far, found near={self.near}, far={self.far}")

    def replace(self, **changes) -> SamplerConfig:
        return dataclasses.replace(self, **changes)


@struct.dataclass
class RayPool:
    """The pixels a split trains on (device arrays; built once by :func:`build_pool`).

    Attributes:
        fg_index: ``[P_fg]`` int32 flat pixel indices ``view * H * W + row * W + col`` of the foreground.
        fg_target: ``[P_fg, 3]`` float32 RGB composited on the background.
        band_index: ``[P_band]`` int32 flat indices of the band (``[1]`` placeholder when empty).
        band_target: ``[P_band, 3]``.
        c2w: ``[N, 4, 4]`` float32 camera-to-world matrices; ``intrinsics``: ``[4]`` ``fx, fy, cx, cy``.
        background: ``[3]`` float32 the background colour the targets were composited on.
        width, height: image size (static). num_band: band rays per batch (static; 0 when the band is
        empty).
    """

    fg_index: jax.Array
    fg_target: jax.Array
    band_index: jax.Array
    band_target: jax.Array
    c2w: jax.Array
    intrinsics: jax.Array
    background: jax.Array
    width: int = struct.field(pytree_node=False)
    height: int = struct.field(pytree_node=False)
    num_band: int = struct.field(pytree_node=False)

    @property
    def num_foreground(self) -> int:
        return int(self.fg_index.shape[0])


def band_mask(alpha: np.ndarray, width: int) -> np.ndarray:
    """``[N, H, W]`` bool: pixels within ``width`` pixels (Chebyshev) of ``alpha > 0`` but not in it,
    per view. ``alpha``: ``[N, H, W]``."""
    fg = np.asarray(alpha) > 0
    if width <= 0:
        return np.zeros_like(fg)
    structure = np.zeros((1, 3, 3), bool)
    structure[0] = True  # 8-connected in the image plane, never across views
    dilated = ndimage.binary_dilation(fg, structure=structure, iterations=int(width))
    return dilated & ~fg


def build_pool(cfg: SamplerConfig, split: SceneSplit, background) -> RayPool:
    """Host side, once per split: the foreground and band pixels and their targets. Besides the
    split's images it holds a few bytes per pixel (the masks) and the pool's pixels while it builds:
    the targets are composited at those pixels only. On the device the pool holds 16 bytes per
    foreground and band pixel (an index and an RGB target) and the cameras.

    ``background``: anything :func:`~ne_jax.data.nerf_synthetic.parse_background` accepts
    (``"white"``, ``"black"``, ``(r, g, b)``).

    Raises:
        ValueError: when no view has a foreground pixel (nothing to train on).
    """
    images = np.asarray(split.images, np.float32)
    n, h, w, _ = images.shape
    alpha = images[..., 3]
    fg = alpha > 0
    if not fg.any():
        raise ValueError(
            f"build_pool: split {split.name!r} has no foreground pixel (alpha > 0) in any of its {n} "
            "views; nothing to train on (check the masks / alpha channel)")
    band = band_mask(alpha, cfg.band_width)
    bg = parse_background(background)
    fg_index = np.flatnonzero(fg.ravel()).astype(np.int32)
    band_index = np.flatnonzero(band.ravel()).astype(np.int32)
    # composited at the pool's pixels only: the whole split composited would hold 3/4 of its images again
    flat = images.reshape(-1, 4)
    fg_target, band_target = (np.asarray(composite(flat[i], bg), np.float32) for i in (fg_index, band_index))
    num_band = int(round(cfg.band_fraction * cfg.batch_size)) if band_index.size else 0
    if num_band >= cfg.batch_size:
        num_band = cfg.batch_size - 1
    if band_index.size == 0:  # placeholder row so shapes stay non-empty; never drawn (num_band = 0)
        band_index = np.zeros((1,), np.int32)
        band_target = np.asarray(composite(flat[band_index], bg), np.float32)
    return RayPool(
        fg_index=jnp.asarray(fg_index), fg_target=jnp.asarray(fg_target),
        band_index=jnp.asarray(band_index), band_target=jnp.asarray(band_target),
        c2w=jnp.asarray(split.c2w, jnp.float32),
        intrinsics=jnp.asarray([split.fx, split.fy, split.cx, split.cy], jnp.float32),
        background=jnp.asarray(bg, jnp.float32), width=w, height=h, num_band=num_band)


@struct.dataclass
class Batch:
    """A training batch: ``rays`` (``[B]``; ``target`` ``[B, 4]``: the RGB composited on the
    background, alpha 1, as :func:`~ne_jax.data.nerf_synthetic.split_rays` with a background),
    ``pixel`` ``[B]`` int32 flat pixel indices, ``in_band`` ``[B]`` bool (drawn from the band),
    ``background`` ``[3]`` the colour to render behind the scene. With ``n x n`` rays per pixel
    (:func:`sample_batch`'s ``pixel_samples``) each pixel's ``n * n`` rays are consecutive and share
    its index and target."""

    rays: Rays
    pixel: jax.Array
    in_band: jax.Array
    background: jax.Array


def pixel_index_rays(pool: RayPool, pixel: jax.Array, near: float, far: float, pixel_samples: int = 1) -> Rays:
    """Rays through flat pixel indices ``pixel`` ``[P]``, unit directions: the pixel centres, or
    each pixel's ``n x n`` grid (``n = pixel_samples``, :func:`~ne_jax.data.rays.subpixel_offsets`;
    ``[P * n * n]`` rays, each pixel's consecutive)."""
    view, rest = jnp.divmod(pixel, pool.width * pool.height)
    row, col = jnp.divmod(rest, pool.width)
    corner = jnp.stack([col, row], axis=-1).astype(pool.c2w.dtype)
    xy = (corner[:, None, :] + jnp.asarray(subpixel_offsets(pixel_samples), corner.dtype)).reshape(-1, 2)
    view = jnp.repeat(view, pixel_samples ** 2)
    fx, fy, cx, cy = (pool.intrinsics[i] for i in range(4))
    return rays_through_pixels(pool.c2w[view], fx, fy, cx, cy, xy, near, far)


@functools.partial(jax.jit, static_argnums=(0, 3))
def sample_batch(cfg: SamplerConfig, pool: RayPool, key: jax.Array, pixel_samples: int = 1) -> Batch:
    """``cfg.batch_size`` rays: ``pool.num_band`` from the band, the rest from the foreground,
    uniform with replacement. With ``pixel_samples = n > 1`` the batch holds ``batch_size / n**2``
    pixels (band pixels in the same share), ``n x n`` rays each. Deterministic for ``key``; the
    shape depends only on ``cfg`` and ``n``.

    Raises:
        ValueError: when ``batch_size`` is not a multiple of ``n**2``.
    """
    per_pixel = pixel_samples ** 2
    if cfg.batch_size % per_pixel:
        raise ValueError(f"sample_batch: batch_size {cfg.batch_size} is not a multiple of the {per_pixel} rays "
                         f"of a pixel (pixel_samples={pixel_samples})")
    k_fg, k_band = jax.random.split(key)
    num_pixels = cfg.batch_size // per_pixel
    num_band = min(round(pool.num_band / per_pixel), num_pixels - 1)
    num_fg = num_pixels - num_band
    i_fg = jax.random.randint(k_fg, (num_fg,), 0, pool.fg_index.shape[0])
    i_band = jax.random.randint(k_band, (num_band,), 0, pool.band_index.shape[0])
    pixel = jnp.concatenate([pool.fg_index[i_fg], pool.band_index[i_band]])
    target = jnp.concatenate([pool.fg_target[i_fg], pool.band_target[i_band]])
    in_band = jnp.arange(num_pixels) >= num_fg
    target = jnp.concatenate([target, jnp.ones_like(target[:, :1])], axis=-1)
    rays = pixel_index_rays(pool, pixel, cfg.near, cfg.far, pixel_samples)
    each = lambda a: jnp.repeat(a, per_pixel, axis=0)  # noqa: E731
    return Batch(rays=rays.replace(target=each(target)), pixel=each(pixel), in_band=each(in_band),
                 background=pool.background)


__all__ = ["Batch", "RayPool", "SamplerConfig", "band_mask", "build_pool", "pixel_index_rays", "sample_batch"]

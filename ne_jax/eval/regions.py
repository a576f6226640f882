"""Where the error of a render lives: every pixel of a view gets one region, and the squared error
is summed per region (a diagnosis before tuning, and an error-map picture).

Regions, decided from the ground truth alone (plus the render for holes and see-through pixels),
first match wins:

* ``silhouette``: within ``edge_px`` pixels of the ground truth's alpha edge (alpha crosses 0.5);
* ``hole``: object in the ground truth (alpha >= 0.5) that the render shows as background (every
  channel within ``hole_tol`` of the background colour, where the ground truth is farther from it);
* ``see_through``: object pixels whose rendered depth lies behind the median depth of their 3 x 3
  neighbourhood by more than ``see_through_step`` times that median: the ray passed the surface its
  neighbours stop at and shows what lies behind it (needs the render's depth map; without one no
  pixel is labelled so);
* ``highlight``: object pixels brighter than the median of their ``window`` neighbourhood by more
  than ``highlight_step`` in luminance (specular spots and bright reflections);
* ``texture``: object pixels where the ground truth's luminance gradient (Sobel, per pixel) exceeds
  ``texture_grad`` (stripes, checkers, wood grain, edges between parts);
* ``flat``: the rest of the object;
* ``background``: the rest (alpha < 0.5 away from the edge).

Shapes: images ``[H, W, 3]`` float in [0, 1]; alpha ``[H, W]``.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy import ndimage

from ne_jax.eval.metrics import MSE_FLOOR

REGIONS = ("silhouette", "hole", "see_through", "highlight", "texture", "flat", "background")
"""Region names, in the order they are assigned (a pixel gets the first that matches)."""

COLORS = np.array([
    [1.0, 0.85, 0.0],   # silhouette: yellow
    [1.0, 0.0, 1.0],    # hole: magenta
    [1.0, 0.25, 0.0],   # see_through: orange-red
    [1.0, 1.0, 1.0],    # highlight: white
    [0.0, 0.75, 1.0],   # texture: cyan
    [0.35, 0.35, 0.35],  # flat: grey
    [0.0, 0.0, 0.0],    # background: black
], np.float32)
"""Colour of each region in :func:`error_map_picture`'s label panel."""


@dataclasses.dataclass(frozen=True)
class RegionConfig:
    """Thresholds of :func:`label_regions` (see the module docstring)."""

    edge_px: float = 1.5
    hole_tol: float = 0.04
    highlight_step: float = 0.12
    texture_grad: float = 0.08
    window: int = 7
    see_through_step: float = 0.01


def _luminance(rgb: np.ndarray) -> np.ndarray:
    return rgb @ np.array([0.2126, 0.7152, 0.0722], np.float32)


def _check(name: str, a: np.ndarray, shape: tuple) -> np.ndarray:
    a = np.asarray(a, np.float32)
    if a.shape != shape:
        raise ValueError(f"{name}: expected shape {list(shape)}, found {list(a.shape)}")
    return a


def neighbour_depth(depth: np.ndarray) -> np.ndarray:
    """``[H, W]`` the median depth of each pixel's 3 x 3 neighbourhood (itself included): the surface
    the ``see_through`` rule compares a pixel's own rendered depth with."""
    return ndimage.median_filter(np.asarray(depth, np.float32), size=3, mode="nearest")


def label_regions(target: np.ndarray, alpha: np.ndarray, pred: np.ndarray, background,
                  cfg: RegionConfig = RegionConfig(), depth: np.ndarray | None = None) -> np.ndarray:
    """``[H, W]`` int8 region index (into :data:`REGIONS`) of every pixel.

    Args:
        target: ``[H, W, 3]`` the ground truth composited on ``background``.
        alpha: ``[H, W]`` the ground truth's alpha.
        pred: ``[H, W, 3]`` the render (on the same background).
        background: ``[3]`` the background colour.
        depth: ``[H, W]`` the render's depth map (``RenderOut.depth``: expected distance, 0 where
            nothing was hit), or ``None`` (then no pixel is ``see_through``).
    """
    target = np.asarray(target, np.float32)
    if target.ndim != 3 or target.shape[-1] != 3:
        raise ValueError(f"target: expected shape [H, W, 3], found {list(target.shape)}")
    alpha = _check("alpha", alpha, target.shape[:2])
    pred = _check("pred", pred, target.shape)
    bg = _check("background", background, (3,))
    obj = alpha >= 0.5
    dist_in = ndimage.distance_transform_edt(obj)
    dist_out = ndimage.distance_transform_edt(~obj)
    edge = np.where(obj, dist_in, dist_out) <= cfg.edge_px
    lum = _luminance(target)
    hole = obj & (np.abs(pred - bg).max(-1) <= cfg.hole_tol) & (np.abs(target - bg).max(-1) > cfg.hole_tol)
    bright = lum - ndimage.median_filter(lum, size=cfg.window, mode="nearest") > cfg.highlight_step
    grad = np.hypot(ndimage.sobel(lum, 0, mode="nearest"), ndimage.sobel(lum, 1, mode="nearest")) / 8.0  # per pixel
    behind = np.zeros_like(obj)
    if depth is not None:
        depth = _check("depth", depth, target.shape[:2])
        near = neighbour_depth(depth)
        behind = obj & (near > 0) & (depth - near > cfg.see_through_step * near)
    label = np.full(target.shape[:2], REGIONS.index("background"), np.int8)
    # later wins: the reverse of REGIONS
    for name, mask in (("flat", obj), ("texture", obj & (grad > cfg.texture_grad)), ("highlight", obj & bright),
                       ("see_through", behind), ("hole", hole), ("silhouette", edge)):
        label[mask] = REGIONS.index(name)
    return label


def region_errors(labels: np.ndarray, pred: np.ndarray, target: np.ndarray) -> dict:
    """Per region over any number of views (``labels [..., H, W]``, images ``[..., H, W, 3]``):
    ``{region: {"pixels": share of all pixels, "error": share of the summed squared error,
    "psnr": PSNR over the region's pixels (None where it has none; MSE floored as
    :data:`~ne_jax.eval.metrics.MSE_FLOOR`)}}``."""
    labels = np.asarray(labels)
    sq = np.mean((np.asarray(pred, np.float64) - np.asarray(target, np.float64)) ** 2, axis=-1)
    if sq.shape != labels.shape:
        raise ValueError(f"labels: expected the images' shape {list(sq.shape)}, found {list(labels.shape)}")
    total = max(float(sq.sum()), 1e-30)
    out = {}
    for i, name in enumerate(REGIONS):
        sel = labels == i
        n = int(sel.sum())
        mse = float(sq[sel].mean()) if n else None
        out[name] = {"pixels": n / labels.size, "error": float(sq[sel].sum()) / total,
                     "psnr": None if mse is None else float(-10.0 * np.log10(max(mse, MSE_FLOOR)))}
    return out


def view_shares(labels: np.ndarray, region: str) -> np.ndarray:
    """``[N]``: the share of each view's pixels labelled ``region`` (``labels [N, H, W]``)."""
    if region not in REGIONS:
        raise ValueError(f"region: expected one of {REGIONS}, found {region!r}")
    labels = np.asarray(labels)
    return (labels == REGIONS.index(region)).reshape(len(labels), -1).mean(-1)


def split_regions(split, images: np.ndarray, background, cfg: RegionConfig = RegionConfig(),
                  depths: np.ndarray | None = None) -> tuple[dict, np.ndarray]:
    """:func:`region_errors` of renders ``images [N, H, W, 3]`` (with their depth maps ``depths``
    ``[N, H, W]``, or ``None``) of a :class:`~ne_jax.data.nerf_synthetic.SceneSplit` (its RGBA images
    are the ground truth, composited on ``background``). Returns ``(report, labels [N, H, W])``."""
    from ne_jax.data.nerf_synthetic import composite, parse_background

    bg = np.asarray(parse_background(background), np.float32)
    truth = composite(split.images, bg).astype(np.float32)
    images = np.asarray(images, np.float32)
    if images.shape != truth.shape:
        raise ValueError(f"images: expected the split's shape {list(truth.shape)}, found {list(images.shape)}")
    alpha = split.images[..., 3]
    if depths is not None and np.shape(depths) != images.shape[:3]:
        raise ValueError(f"depths: expected shape {list(images.shape[:3])}, found {list(np.shape(depths))}")
    depths = [None] * len(images) if depths is None else depths
    labels = np.stack([label_regions(t, a, p, bg, cfg, d) for t, a, p, d in zip(truth, alpha, images, depths)])
    return region_errors(labels, images, truth), labels


def error_map_picture(target: np.ndarray, pred: np.ndarray, labels: np.ndarray, scale: float = 4.0) -> np.ndarray:
    """``[H, 4 W, 3]``: ground truth | render | absolute error (mean over channels, times ``scale``,
    clipped, as a heat map: black -> red -> yellow) | region labels (:data:`COLORS`)."""
    err = np.clip(np.abs(np.asarray(pred, np.float32) - np.asarray(target, np.float32)).mean(-1) * scale, 0.0, 1.0)
    heat = np.stack([np.clip(2.0 * err, 0, 1), np.clip(2.0 * err - 1.0, 0, 1), np.zeros_like(err)], -1)
    return np.concatenate([np.clip(target, 0, 1), np.clip(pred, 0, 1), heat, COLORS[labels]], axis=1)


__all__ = ["COLORS", "REGIONS", "RegionConfig", "error_map_picture", "label_regions", "neighbour_depth",
           "region_errors", "split_regions", "view_shares"]

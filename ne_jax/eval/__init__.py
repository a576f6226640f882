"""Evaluation: PSNR/SSIM, rendering and scoring a split, orbit videos and image folders."""

from ne_jax.eval.metrics import MSE_FLOOR, gaussian_window, psnr, ssim
from ne_jax.eval.views import (
    VIDEO_SUFFIXES,
    evaluate_split,
    orbit_cameras_for,
    render_views,
    save_images,
    write_video,
)

__all__ = [
    "MSE_FLOOR",
    "VIDEO_SUFFIXES",
    "evaluate_split",
    "gaussian_window",
    "orbit_cameras_for",
    "psnr",
    "render_views",
    "save_images",
    "ssim",
    "write_video",
]

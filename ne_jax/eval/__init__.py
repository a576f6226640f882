"""Evaluation: PSNR/SSIM/LPIPS, rendering and scoring a split, orbit videos and image folders."""

from ne_jax.eval.metrics import (
    LPIPS_DEFAULT_NET,
    LPIPS_MIN_SIZE,
    LPIPS_NETS,
    MSE_FLOOR,
    gaussian_window,
    lpips,
    lpips_available,
    lpips_network,
    psnr,
    ssim,
)
from ne_jax.eval.views import (
    VIDEO_SUFFIXES,
    evaluate_model,
    evaluate_split,
    orbit_cameras_for,
    render_views,
    save_images,
    write_video,
)

__all__ = [
    "LPIPS_DEFAULT_NET",
    "LPIPS_MIN_SIZE",
    "LPIPS_NETS",
    "MSE_FLOOR",
    "VIDEO_SUFFIXES",
    "evaluate_model",
    "evaluate_split",
    "gaussian_window",
    "lpips",
    "lpips_available",
    "lpips_network",
    "orbit_cameras_for",
    "psnr",
    "render_views",
    "save_images",
    "ssim",
    "write_video",
]

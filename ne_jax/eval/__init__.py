"""Evaluation: PSNR/SSIM, rendering and scoring a split, orbit videos and image folders."""

from ne_jax.eval.metrics import MSE_FLOOR, gaussian_window, psnr, ssim

__all__ = ["MSE_FLOOR", "gaussian_window", "psnr", "ssim"]

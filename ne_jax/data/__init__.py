"""Cameras, rays and scenes: NeRF-Synthetic-format I/O and the procedural editing benchmark."""

from ne_jax.data.rays import Camera, Rays, camera_rays, pixel_rays

__all__ = ["Camera", "Rays", "camera_rays", "pixel_rays"]

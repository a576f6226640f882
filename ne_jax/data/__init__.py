"""Cameras, rays and scenes on disk: scene folders of every supported layout (:mod:`ne_jax.data.scene`:
NeRF Synthetic, nerfstudio, COLMAP, NSVF, LLFF), their images, and the cameras of the procedural scenes."""

from ne_jax.data.rays import Camera, Rays, camera_rays, pixel_rays

__all__ = ["Camera", "Rays", "camera_rays", "pixel_rays"]

from ne_jax.data.nerf_synthetic import (
    SceneSplit,
    composite,
    downscale_rgba,
    load_scene,
    parse_background,
    split_rays,
    view_rays,
    write_split,
)
from ne_jax.data.png import DataError, read_image, write_image
from ne_jax.data.scene import detect_format, load_split

__all__ += [
    "DataError",
    "SceneSplit",
    "composite",
    "detect_format",
    "downscale_rgba",
    "load_scene",
    "load_split",
    "parse_background",
    "read_image",
    "split_rays",
    "view_rays",
    "write_image",
    "write_split",
]

"""Format readers: a scene folder -> a :class:`~ne_jax.data.capture.Capture`.

Each reader module has ``looks_like(root) -> bool`` (a cheap check for its files) and
``read_<format>(root) -> Capture``; every bad input raises :class:`~ne_jax.data.png.DataError`
naming the file. :data:`READERS` maps format names to ``(looks_like, read)`` in detection order.
"""

from __future__ import annotations

from ne_jax.data.formats import colmap, llff, nerfstudio, nsvf
from ne_jax.data.formats.colmap import read_colmap
from ne_jax.data.formats.llff import read_llff
from ne_jax.data.formats.nerfstudio import read_nerfstudio
from ne_jax.data.formats.nsvf import read_nsvf

# Detection order: a folder that matches several formats is read by the first match. nerfstudio
# comes first because `ns-process-data` leaves its COLMAP model (`colmap/sparse/0`, sometimes
# `sparse/0`) beside `transforms.json`, and the transforms are what such a folder is meant to be
# read as. COLMAP comes before LLFF: the LLFF and mip-NeRF 360 releases hold both `sparse/0` and
# `poses_bounds.npy`, and the model is the richer source (per-camera intrinsics, distortion,
# points), as in multinerf, which reads such scenes' poses from COLMAP.
READERS = {
    "nerfstudio": (nerfstudio.looks_like, read_nerfstudio),
    "colmap": (colmap.looks_like, read_colmap),
    "nsvf": (nsvf.looks_like, read_nsvf),
    "llff": (llff.looks_like, read_llff),
}
"""``{format: (looks_like, read)}`` in detection order."""

__all__ = [
    "READERS",
    "colmap",
    "llff",
    "nerfstudio",
    "nsvf",
    "read_colmap",
    "read_llff",
    "read_nerfstudio",
    "read_nsvf",
]

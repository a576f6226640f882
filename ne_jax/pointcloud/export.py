"""Export a model's point cloud: positions, normals, confidences and a colour per point.

The colour of a point is the model's colour of the point's own feature seen head-on (view
direction ``-normal``; ``-z`` where the point has no normal), i.e. what a ray hitting the surface
there straight on would see, without neighbours or compositing. The ``index`` property keeps each
point's slot, so an exported cloud can be edited and read back as an indexed edit.
"""

from __future__ import annotations

import functools
import os

import jax
import jax.numpy as jnp
import numpy as np

from ne_jax.data.ply import write_ply
from ne_jax.geometry.points import PointState
from ne_jax.render.shading import ShadingConfig, shade


@functools.partial(jax.jit, static_argnums=0)
def point_colors(cfg: ShadingConfig, params: dict, points: PointState) -> jax.Array:
    """``[C, 3]`` colour of every slot's feature seen head-on (dead slots too; mask them)."""
    n = points.normal
    has = jnp.sum(n * n, axis=-1, keepdims=True) > 0
    view = jnp.where(has, -n, jnp.asarray([0.0, 0.0, -1.0], n.dtype))
    normal = jnp.where(has, n, -view) if cfg.effects.uses_point_normals else None
    ist = points.ist if cfg.effects.uses_ist else None
    return shade(cfg, params, points.feature, normal, view, ist).rgb


def export_ply(path: str | os.PathLike, cfg: ShadingConfig, params: dict, points: PointState, frame=None) -> int:
    """Write the alive points to a binary PLY (atomically): ``x y z nx ny nz confidence red green
    blue index`` (colours ``uint8``, see :func:`point_colors`). Returns the number of points.

    ``frame`` (a :class:`~ne_jax.data.scene.Normalisation`, the model's ``frame``): positions and
    normals are written in the capture's coordinates; ``None``: the model's."""
    alive = np.flatnonzero(np.asarray(points.alive))
    xyz = np.asarray(points.xyz, np.float32)[alive]
    nrm = np.asarray(points.normal, np.float32)[alive]
    if frame is not None and not frame.is_identity:
        xyz = frame.to_capture(xyz).astype(np.float32)
        nrm = frame.rotate_to_capture(nrm).astype(np.float32)
    rgb = np.asarray(point_colors(cfg, params, points), np.float32)[alive]
    rgb8 = np.clip(np.round(rgb * 255.0), 0, 255).astype(np.uint8)
    conf = np.asarray(points.confidence, np.float32)[alive]
    write_ply(path, {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "nx": nrm[:, 0], "ny": nrm[:, 1],
                     "nz": nrm[:, 2], "confidence": conf, "red": rgb8[:, 0], "green": rgb8[:, 1],
                     "blue": rgb8[:, 2], "index": alive.astype(np.int32)})
    return int(alive.size)


__all__ = ["export_ply", "point_colors"]

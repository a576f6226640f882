"""Edit fidelity: does an edited model render what the edit means?

For a rigid motion ``T`` of the whole scene there is an exact answer without any ground truth: the
edited model seen from cameras moved by ``T`` must render the unedited model's images from the
original cameras (*equivariance*). A uniform scaling by ``s`` is the same with cameras moved by ``T``
(their orientation kept) and ``near``/``far`` scaled by ``s``. :func:`equivariance` measures it as
the PSNR between the two renders, so what an edit path loses can be told apart from what the model
gets wrong (``experiments/equivariance.py`` runs it over motions and edit paths).

:func:`exact_rigid_points` is the reference edit of the point state for a rigid motion: positions,
normals (``R n``) and ISTs (``IST R^T``) moved exactly, where :func:`~ne_jax.edit.apply.apply_edit`
re-estimates normals and fits ISTs from neighbours.
"""

from __future__ import annotations

from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np

from ne_jax.data.rays import Camera
from ne_jax.eval.views import render_views
from ne_jax.geometry.points import PointState
from ne_jax.render.renderer import PointScene, RenderConfig

EXACT_DB = 120.0
"""PSNR reported for identical renders (an MSE below ``1e-12``)."""


def psnr_between(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR (dB, peak 1) between two images or stacks, capped at :data:`EXACT_DB`."""
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return EXACT_DB if mse < 1e-12 else float(min(EXACT_DB, -10.0 * np.log10(mse)))


def motion_parts(matrix) -> tuple[np.ndarray, np.ndarray, float]:
    """``(R [3, 3], t [3], s)`` of a similarity ``T = [[s R, t], [0, 1]]`` (``[4, 4]``).

    Raises:
        ValueError: ``matrix`` is not ``4x4`` or its linear part is not a positive multiple of a rotation."""
    m = np.asarray(matrix, np.float64)
    if m.shape != (4, 4):
        raise ValueError(f"matrix: expected a [4, 4] similarity, found shape {list(m.shape)}")
    lin = m[:3, :3]
    s = float(np.cbrt(np.linalg.det(lin)))
    rot = lin / s if s > 0 else lin
    if not s > 0 or not np.allclose(rot @ rot.T, np.eye(3), atol=1e-5):
        raise ValueError("matrix: expected s R with s > 0 and R a rotation (a rigid motion or a uniform scaling), "
                         f"found linear part {lin.round(4).tolist()}")
    return rot, m[:3, 3].copy(), s


def moved_camera(camera: Camera, matrix) -> Camera:
    """``camera`` moved with the scene by the similarity ``matrix``: its centre mapped by ``T``, its
    orientation turned by ``R`` (a scaling leaves the orientation and the image as they are)."""
    rot, t, s = motion_parts(matrix)
    c2w = np.asarray(camera.c2w, np.float64)
    out = np.eye(4)
    out[:3, :3] = rot @ c2w[:3, :3]
    out[:3, 3] = s * rot @ c2w[:3, 3] + t
    return camera.replace(c2w=jnp.asarray(out, camera.c2w.dtype))


def exact_rigid_points(points: PointState, matrix) -> PointState:
    """The point state moved exactly by the similarity ``matrix``: ``xyz -> T xyz``, normals ``R n``,
    ISTs ``IST R^T`` (directions of the moved scene mapped back to the original frame)."""
    rot, t, s = motion_parts(matrix)
    r = jnp.asarray(rot, points.xyz.dtype)
    xyz = jnp.asarray(s, points.xyz.dtype) * points.xyz @ r.T + jnp.asarray(t, points.xyz.dtype)
    alive = points.alive[:, None]
    return points.replace(xyz=jnp.where(alive, xyz, points.xyz),
                          normal=jnp.where(alive, points.normal @ r.T, points.normal),
                          ist=jnp.einsum("cij,jk->cik", points.ist, r.T))


def equivariance(cfg: RenderConfig, params: dict, scene: PointScene, edited_cfg: RenderConfig,
                 edited: PointScene, matrix, cameras: Sequence[Camera], background, near: float, far: float,
                 reference: np.ndarray | None = None) -> dict:
    """PSNR between the edited scene seen from ``cameras`` moved by ``matrix`` and the unedited scene
    from ``cameras`` (both rendered with the same colour-model ``params``).

    Args:
        cfg, scene: the unedited model's render config and scene. edited_cfg, edited: the edited ones.
        matrix: the edit's similarity ``T`` ``[4, 4]`` (a uniform scale ``s`` scales ``near``/``far``).
        reference: the unedited renders ``[N, H, W, 3]`` if already made (else rendered here).

    Returns:
        ``{"psnr": over all views' pixels, "psnr_views": per view, "reference": [N, H, W, 3],
        "images": [N, H, W, 3]}``.
    """
    _, _, s = motion_parts(matrix)
    if reference is None:
        reference = render_views(cfg, params, scene, cameras, background, near, far, progress=False)
    moved = [moved_camera(c, matrix) for c in cameras]
    images = render_views(edited_cfg, params, edited, moved, background, s * near, s * far, progress=False)
    return {"psnr": psnr_between(images, reference),
            "psnr_views": [psnr_between(a, b) for a, b in zip(images, reference)],
            "reference": reference, "images": images}


__all__ = ["EXACT_DB", "equivariance", "exact_rigid_points", "motion_parts", "moved_camera", "psnr_between"]

"""The one sample -> KNN -> shade stage that every way of rendering shares.

Samples get the per-point values the scene's declared effects read (:func:`values_needed`: the
features, and the point normals and ISTs only when an effect reads them; with ``aux`` also what the
training losses read, the confidence and the normal moment) by one of three lookups, and are then
shaded by the colour model (:func:`~ne_jax.render.shading.shade`, with the checks of both steps):

* ``integrate`` (:func:`shade_segments`): the quadrature of the KNN-interpolated values over each
  segment's samples (:func:`~ne_jax.geometry.knn.knn_integrate`), one shaded value per segment; the
  renderer;
* ``interpolate`` (:func:`shade_samples`): the KNN-interpolated values per sample
  (:func:`~ne_jax.geometry.knn.knn_interpolate`), each sample shaded on its own; traditional
  sampling (``integration="samples"``) and the growth scan;
* ``own`` (:func:`shade_own`): each point's own values; Naive Plotting.

What a strategy loses to the scene's capacities happens before this stage (traversal and segment
packing, :class:`~ne_jax.geometry.capacity.Lost`) and is reported by the strategy: the lookups
themselves drop nothing (a candidate set is a fixed-size array, and the exact search is global).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from ne_jax.checks import stage_check
from ne_jax.geometry.knn import GATE, knn_integrate, knn_interpolate
from ne_jax.geometry.points import PointState
from ne_jax.render.shading import Effects, shade


@struct.dataclass
class Shaded:
    """What :func:`shade_segments`, :func:`shade_samples` and :func:`shade_own` return
    (``[...]`` = the batch shape: segments ``[B]``, samples ``[..., S]`` or points ``[C]``).

    Attributes:
        sigma: ``[...]`` density per point spacing (times the density gate when the lookup
            returns one: ``cfg.kdtree.density_falloff``, :mod:`ne_jax.geometry.knn`).
        rgb: ``[..., 3]`` colour.
        pred_normal: ``[..., 3]`` the colour model's unit predicted normal.
        shading_normal: ``[..., 3]`` the normal the view was reflected about; ``None`` without one.
        values: the looked-up values, ``{name: [..., ...]}`` (keys of :func:`values_needed`, plus
            ``confidence [..., 1]`` and ``normal_moment [..., 9]`` with ``aux``).
        nearest: ``[...]`` distance to the nearest valid neighbour (``inf`` when none; the
            ``interpolate`` lookup only, else ``None``).
    """

    sigma: jax.Array
    rgb: jax.Array
    pred_normal: jax.Array
    shading_normal: jax.Array | None
    values: dict
    nearest: jax.Array | None = None


def values_needed(points: PointState, effects: Effects, aux: bool = False) -> dict:
    """The per-point arrays ``[C, ...]`` the declared effects read: ``feature``, and ``normal`` and
    ``ist`` only when an effect reads them. With ``aux``, also what the training losses read: the
    confidence ``[C, 1]`` and the confidence-weighted normal moment ``[C, 9]``."""
    values = {"feature": points.feature}
    if effects.uses_point_normals:
        values["normal"] = points.normal
    if effects.uses_ist:
        values["ist"] = points.ist
    if aux:
        conf, n = points.confidence, points.normal
        values["confidence"] = conf[:, None]
        values["normal_moment"] = (conf[:, None, None] * n[:, :, None] * n[:, None, :]).reshape(-1, 9)
    return values


def _shade(cfg, params, values: dict, view_dir, nearest=None, checks: bool | None = None) -> Shaded:
    checks = cfg.checks if checks is None else checks
    stage_check(checks, "interpolation", **{k: values.get(k) for k in ("feature", "normal", "ist")})
    out = shade(cfg.shading, params, values["feature"], values.get("normal"), view_dir, values.get("ist"))
    sigma = out.sigma if GATE not in values else out.sigma * values[GATE][..., 0]
    stage_check(checks, "shading", sigma=sigma, rgb=out.rgb)
    return Shaded(sigma=sigma, rgb=out.rgb, pred_normal=out.pred_normal, shading_normal=out.shading_normal,
                  values=values, nearest=nearest)


def shade_segments(cfg, params, scene, pos: jax.Array, node: jax.Array, weight: jax.Array, view_dir: jax.Array,
                   aux: bool = False) -> Shaded:
    """The ``integrate`` lookup: ``[B]`` segments of ``S`` samples each (``pos [B, S, 3]``, quadrature
    ``weight [B, S]``, candidate voxel ``node [B]``, ray direction ``view_dir [B, 3]``), interpolation
    and quadrature fused, then one shading per segment. ``cfg``: a
    :class:`~ne_jax.render.renderer.RenderConfig`; ``scene``: a :class:`~ne_jax.render.renderer.PointScene`."""
    values = values_needed(scene.points, cfg.shading.effects, aux)
    means = knn_integrate(scene.points, scene.tree, pos, node, weight, values, cfg.kdtree, cfg.exact_knn)
    return _shade(cfg, params, means, view_dir)


def shade_samples(cfg, params, scene, pos: jax.Array, node: jax.Array, view_dir: jax.Array,
                  aux: bool = False) -> Shaded:
    """The ``interpolate`` lookup: samples ``pos [..., S, 3]`` of segments in the voxels
    ``node [...]`` seen along ``view_dir [..., 3]``, each shaded on its own (``[..., S]``), with the
    distance to each sample's nearest neighbour."""
    values = values_needed(scene.points, cfg.shading.effects, aux)
    vals, nb = knn_interpolate(scene.points, scene.tree, pos, node, cfg.kdtree, cfg.exact_knn, values)
    nearest = jnp.min(jnp.where(nb.valid, nb.dist, jnp.inf), axis=-1)
    return _shade(cfg, params, vals, jnp.broadcast_to(view_dir[..., None, :], pos.shape), nearest)


def shade_own(cfg, params, points: PointState, view_dir: jax.Array) -> Shaded:
    """The ``own`` lookup: every point ``[C]`` shaded from its own values, seen along ``view_dir [C, 3]``
    (interpolating over a single point gives the point itself, so confidences do not enter the
    values; with a density gate, ``cfg.kdtree.density_falloff``, the gate at the point is its
    confidence). Without stage checks: Naive Plotting does not run under ``checkify``."""
    values = values_needed(points, cfg.shading.effects)
    if cfg.kdtree.density_falloff is not None:
        values[GATE] = points.confidence[:, None]
    return _shade(cfg, params, values, view_dir, checks=False)


__all__ = ["Shaded", "shade_own", "shade_samples", "shade_segments", "values_needed"]

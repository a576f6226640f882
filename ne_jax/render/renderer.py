"""Rendering rays and images through the K-D voxels (data flow steps 2-7 of docs/design.md, joined).

``render_rays(cfg, params, scene, rays, background)``:

1. ``intersect``: the minimal intersected voxels of every ray, ``M`` sorted segment slots;
2. ``level_samples``: ``s`` evenly spaced samples per segment (``s`` by the segment's level) and the
   quadrature weights of the configured rule;
3. ``knn_integrate``: features (and only what the declared effects read: point normals, IST)
   interpolated at every sample from the K nearest points of the segment's candidate set, and
4. integrated into the segment means ``f_i, n_i, IST_i`` with the static quadrature weights — fused:
   both steps are linear, so the weights are summed per candidate point first and each per-point
   array is gathered once per segment;
5. ``shade``: density and colour per segment;
6. ``composite``: ``alpha = 1 - exp(-sigma * len)`` with ``len`` in units of the point spacing
   (docs/design.md), transmittance in log space, background behind.

A scene that does not declare an effect does not compute it: without ``point_normals`` (or without
``specular``) the normals are never interpolated, without ``ist`` the IST matrices are never
interpolated — they are absent from the compiled program, not multiplied by zero.

:mod:`ne_jax.render.driver` renders any number of rays, and images, in fixed-size chunks on the
host's side (the tail padded), so an image of any size compiles once per chunk size; the chunk size
is the memory knob.

The paper's ablation "- integration + traditional point sampling" is ``RenderConfig.integration =
"samples"`` (default ``"segment"``: steps 3-6 above). The same segments, packing budget and ``s``
samples per segment, but no integration: a segment with ``s`` samples is cut into ``s`` equal
sub-intervals ``[t_lo + j L/s, t_lo + (j+1) L/s]`` and sample ``j`` sits at the midpoint of its
sub-interval (deterministic rules; the quadrature rule's nodes and weights are not used) or
uniformly inside it (``"stochastic"``: the same jitter, for the same key, as the segment mode's
stratified positions). Every sample is shaded on its own — its own KNN-interpolated feature and,
when the effects read them, point normal and IST, so its own density and colour — and composited as
its own interval of length ``L / s`` (the union of a segment's sub-intervals is exactly the
segment), front to back in ray order (segments by entry, samples by position). The depth map uses
the samples' positions. A field that is constant along each segment renders exactly as in the
segment mode (one interval of density ``sigma`` and length ``L`` is ``s`` intervals of length
``L/s``); otherwise the two differ by what integrating before shading changes. Costs: ``s`` times the
shading work, and the compositing arrays are ``[R, M * S]`` (``S = max(samples_per_level)``).
``SegmentAux`` then holds one slot per sample, ``[R, M * S, ...]`` (padded sample slots of
segments with ``s < S`` are invalid), which the training losses read unchanged: their sums over
slots become sums over sub-intervals (the sparsity penalty is then on each sub-interval's optical
thickness).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Literal, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from ne_jax.checks import stage_check
from ne_jax.data.rays import Rays
from ne_jax.geometry.capacity import BUFFERS, Capacities, Lost, LostCounts, fit_packing, grow
from ne_jax.geometry.carry import carry_tree
from ne_jax.geometry.intersect import intersect
from ne_jax.geometry.kdtree import KDTree, KDTreeConfig, build_tree
from ne_jax.geometry.points import PointState
from ne_jax.render.composite import composite
from ne_jax.render.quadrature import QuadratureConfig, level_samples, sample_intervals
from ne_jax.render.shading import ShadingConfig, background_color
from ne_jax.render.stage import shade_samples, shade_segments

INTEGRATIONS: tuple[str, ...] = ("segment", "samples")
"""Values of :attr:`RenderConfig.integration`."""


@dataclasses.dataclass(frozen=True)
class RenderConfig:
    """Static settings of a render (hashable). The buffer sizes of traversal and packing are not
    settings: they are :class:`~ne_jax.geometry.capacity.Capacities`, carried by the
    :class:`PointScene`."""

    kdtree: KDTreeConfig = KDTreeConfig()
    """K-D tree, traversal and KNN (``knn_k``, candidate-set size)."""

    quadrature: QuadratureConfig = QuadratureConfig()
    """Integration rule and samples per level (bottom rendering level first)."""

    shading: ShadingConfig = ShadingConfig()
    """Colour model sizes and the scene's declared effects."""

    exact_knn: bool = False
    """Global brute-force KNN instead of the candidate sets (reference / accuracy studies only)."""

    chunk: int = 4096
    """Rays per compiled call in :func:`render_image` (the memory knob; one compilation per value)."""

    integration: Literal["segment", "samples"] = "segment"
    """``"segment"`` (paper): integrate the interpolated features over each segment with the
    quadrature rule, shade once per segment. ``"samples"``: the paper's ablation "- integration +
    traditional point sampling" — shade each of the segment's ``s`` samples on its own and composite
    it as its own ``1/s`` sub-interval of the segment (see the module docstring)."""

    pixel_samples: int = 1
    """Rays per pixel side: a pixel is the mean of an ``n x n`` regular grid of rays over its area
    (:func:`~ne_jax.data.rays.subpixel_offsets`), as the benchmark's ground truth is made (ray caster:
    a 2 x 2 or 3 x 3 grid; path tracer: random positions). 1: the pixel-centre ray. Rendering an image
    costs ``n**2`` times the rays that meet the scene; training keeps the batch's rays, so a batch
    holds ``batch_size / n**2`` pixels (the photometric loss compares each pixel's mean colour);
    the training batches' grid is ``SamplerConfig.pixel_samples``. Naive Plotting splats points per
    pixel and ignores it."""

    checks: bool = False
    """Runtime finiteness checks (:mod:`ne_jax.checks`): the first NaN / Inf raises
    :class:`~ne_jax.checks.NonFiniteError` naming the stage that produced it (``traversal``,
    ``interpolation``, ``shading``, ``compositing``). Needs ``checkify`` around the render
    (:func:`render_chunked` and the training step do it); off: nothing traced, no cost."""

    def __post_init__(self):
        if self.integration not in INTEGRATIONS:
            raise ValueError(
                f"RenderConfig.integration: expected one of {INTEGRATIONS}, found {self.integration!r}")
        levels = self.kdtree.num_render_levels
        if len(self.quadrature.samples_per_level) < levels:
            raise ValueError(
                f"RenderConfig.quadrature.samples_per_level: expected at least {levels} entries (one per "
                f"rendering level, bottom first), found {self.quadrature.samples_per_level}"
            )
        if self.chunk < 1:
            raise ValueError(f"RenderConfig.chunk: expected a positive integer, found {self.chunk}")
        if int(self.pixel_samples) < 1:
            raise ValueError("RenderConfig.pixel_samples: expected rays per pixel side >= 1, "
                             f"found {self.pixel_samples}")

    def replace(self, **changes) -> RenderConfig:
        return dataclasses.replace(self, **changes)

    def with_effects(self, **changes) -> RenderConfig:
        """The same config with some declared effects changed, e.g. ``with_effects(ist=True)``."""
        effects = dataclasses.replace(self.shading.effects, **changes)
        return self.replace(shading=dataclasses.replace(self.shading, effects=effects))


@struct.dataclass
class PointScene:
    """What a model renders: the point state, the K-D tree over its alive points, and the buffer
    sizes its renders use.

    The tree is built on the points (:meth:`build`), or carried through an edit (:meth:`edited`):
    then ``rest_xyz [C, 3]`` / ``rest_alive [C]`` are the positions and mask it was built on, from
    which a later edit carries it again (nothing in a render reads them). ``capacities`` (static:
    a new value compiles anew) are grown by :func:`~ne_jax.geometry.capacity.grow` from what a
    render lost (:meth:`grown`)."""

    points: PointState
    tree: KDTree
    rest_xyz: jax.Array | None = None
    rest_alive: jax.Array | None = None
    capacities: Capacities = struct.field(pytree_node=False, default=Capacities())

    @classmethod
    def build(cls, points: PointState, cfg: RenderConfig, capacities: Capacities = Capacities()) -> PointScene:
        """Build the tree of ``points`` (host side) for rendering with ``cfg``."""
        return cls(points=points, tree=build_tree(np.asarray(points.xyz), np.asarray(points.alive), cfg.kdtree),
                   capacities=capacities)

    @classmethod
    def carried(cls, rest_xyz, rest_alive, points: PointState, cfg: RenderConfig,
                capacities: Capacities = Capacities(), **carry) -> PointScene:
        """The scene of ``points`` with the tree built on ``rest_xyz``/``rest_alive`` carried to them
        (:func:`~ne_jax.geometry.carry.carry_tree`; ``carry``: its keyword arguments)."""
        rest_xyz, rest_alive = np.asarray(rest_xyz), np.asarray(rest_alive)
        tree = carry_tree(build_tree(rest_xyz, rest_alive, cfg.kdtree), rest_xyz, np.asarray(points.xyz),
                          np.asarray(points.alive), cfg.kdtree, **carry)
        return cls(points=points, tree=tree, rest_xyz=jnp.asarray(rest_xyz), rest_alive=jnp.asarray(rest_alive),
                   capacities=capacities)

    def grown(self, lost: Lost | LostCounts, buffers: tuple[str, ...] = BUFFERS) -> PointScene | None:
        """This scene with capacities grown by what a render of it lost, or ``None`` if nothing was
        (:func:`~ne_jax.geometry.capacity.grow`; ``buffers``: the ones that may grow)."""
        bigger = grow(self.capacities, lost, buffers)
        return None if bigger is None else self.replace(capacities=bigger)

    def fitted(self, cfg: RenderConfig, rays: Rays, headroom: float = 1.25) -> PointScene:
        """This scene with a packing budget that holds ``headroom`` times the mean segments per ray of
        ``rays`` (a probe batch; :func:`~ne_jax.geometry.capacity.fit_packing`), never lowered."""
        if self.capacities.segments_per_ray is None:
            return self
        mean = float(jnp.mean(intersect(self.tree, rays, cfg.kdtree, self.capacities).num_segments))
        return self.replace(capacities=fit_packing(self.capacities, mean, headroom))

    def edited(self, points: PointState, cfg: RenderConfig, carry: bool = True, **carry_kw) -> PointScene:
        """The scene of ``points``, an edit of this scene's points (same capacity and indices): the
        tree carried from where it was built (``carry``; see :mod:`ne_jax.geometry.carry`), or
        rebuilt on the edited cloud (the paper's behaviour)."""
        if not carry:
            return PointScene.build(points, cfg, self.capacities)
        if self.rest_xyz is None:  # a built tree: this scene's points are its rest
            tree = carry_tree(self.tree, np.asarray(self.points.xyz), np.asarray(points.xyz),
                              np.asarray(points.alive), cfg.kdtree, **carry_kw)
            return PointScene(points=points, tree=tree, rest_xyz=self.points.xyz, rest_alive=self.points.alive,
                              capacities=self.capacities)
        return PointScene.carried(self.rest_xyz, self.rest_alive, points, cfg, self.capacities, **carry_kw)


@struct.dataclass
class RenderOut:
    """Per-ray results. ``rgb`` ``[R, 3]``, ``opacity``/``depth`` ``[R]``, ``normal`` ``[R, 3]``
    (opacity-weighted shading normal; zeros when the scene shades without normals),
    ``num_segments`` ``[R]`` segments rendered. What was lost to the scene's capacities is counted,
    never silent: ``lost`` (:class:`~ne_jax.geometry.capacity.Lost`, ``[R]`` per field);
    ``lost.count`` 0 everywhere: the render is complete."""

    rgb: jax.Array
    opacity: jax.Array
    depth: jax.Array
    normal: jax.Array
    num_segments: jax.Array
    lost: Lost


@struct.dataclass
class SegmentAux:
    """Per-segment quantities of a render, for training losses (``[R, M, ...]``, ``M`` the segment
    slots per ray; zeros in slots without a rendered segment). With ``integration="samples"`` a
    slot is a sample's sub-interval instead: ``[R, M * S, ...]`` (``S`` the padded samples per
    segment; slots ordered by segment, then sample), and "segment" below reads "sub-interval".

    Attributes:
        valid: ``[R, M]`` bool, the slot holds a rendered segment.
        weights: ``[R, M]`` compositing weights ``T_i alpha_i``.
        sigma: ``[R, M]`` density per point-spacing unit.
        lengths: ``[R, M]`` segment length in point spacings (0 in empty slots).
        pred_normal: ``[R, M, 3]`` unit predicted normal of the colour model.
        shading_normal: ``[R, M, 3]`` the normal the view direction was reflected about (zeros when
            the scene shades without one).
        view_dir: ``[R, M, 3]`` unit ray direction (camera towards the scene).
        confidence: ``[R, M]`` integrated ``sum_k w_k c_k`` (KNN weights ``w``, point confidences ``c``).
        normal_moment: ``[R, M, 3, 3]`` integrated ``sum_k w_k c_k n_k n_k^T`` of the point normals
            (sign-free: Open3D normals are unoriented); with unit ``p``,
            ``trace(A) - p^T A p = sum_k w_k c_k |n_k|^2 (1 - (p.n_k)^2)``.
    """

    valid: jax.Array
    weights: jax.Array
    sigma: jax.Array
    lengths: jax.Array
    pred_normal: jax.Array
    shading_normal: jax.Array
    view_dir: jax.Array
    confidence: jax.Array
    normal_moment: jax.Array


def render_rays(cfg: RenderConfig, params: dict, scene: PointScene, rays: Rays, background,
                key: jax.Array | None = None) -> RenderOut:
    """Render ``rays`` (``[R]``) of ``scene`` with colour-model ``params``.

    ``background``: ``[3]`` or ``[R, 3]`` colour behind the scene (used by the ``"constant"``
    background; the ``"sphere"`` background is learned). ``key``: needed only by the stochastic
    integration rule. Pure and differentiable in ``params``, the scene's per-point arrays (positions
    through the KNN distances; the tree topology is held fixed) and ``rays``."""
    return _render(cfg, params, scene, rays, background, key, aux=False)[0]


def render_rays_with_aux(cfg: RenderConfig, params: dict, scene: PointScene, rays: Rays, background,
                         key: jax.Array | None = None) -> tuple[RenderOut, SegmentAux]:
    """:func:`render_rays` plus the per-segment :class:`SegmentAux` the training losses need.
    The ``RenderOut`` is the one :func:`render_rays` returns; the extra KNN values (confidence and
    normal moment) are interpolated only here."""
    return _render(cfg, params, scene, rays, background, key, aux=True)


class _Packed(NamedTuple):
    """A batch's live segments packed into ``B`` slots (``B = R * M``, or the packing budget), and
    per slot its ray and its place on it (``[B]``, ``[B, 3]``)."""

    keep: jax.Array  # [R, M] the segment is rendered
    slot: jax.Array  # [B] flat index r * M + m of the packed segment
    live: jax.Array  # [B] the slot holds a segment
    origin: jax.Array
    direction: jax.Array
    t_lo: jax.Array
    t_hi: jax.Array
    node: jax.Array
    level_index: jax.Array  # 0 = bottom rendering level

    def unpack(self, v: jax.Array, per_slot: int = 0) -> jax.Array:
        """``[B, *inner, ...]`` -> ``[R, M * prod(inner), ...]`` (``per_slot`` inner axes, e.g. the
        samples of a segment), zeros in slots without a live segment."""
        r, m = self.keep.shape
        target = jnp.where(self.live, self.slot, r * m)
        full = jnp.zeros((r * m,) + v.shape[1:], v.dtype).at[target].set(v, mode="drop")
        inner = v.shape[1:1 + per_slot]
        return full.reshape((r, m * int(np.prod(inner))) + v.shape[1 + per_slot:])


def _pack(scene: PointScene, rays: Rays, seg) -> _Packed:
    """The valid segments ``seg`` (``[R, M]``) in the scene's packing budget (all slots without one)."""
    r, m = seg.valid.shape
    budget = scene.capacities.segment_budget(r)
    flat = lambda a: a.reshape((r * m,) + a.shape[2:])  # noqa: E731
    if budget is None or budget >= r * m:
        keep = seg.valid
        slot = jnp.arange(r * m)
        live = flat(seg.valid)
    else:  # pack the valid segments of the whole batch into `budget` slots
        (slot,) = jnp.nonzero(flat(seg.valid), size=budget, fill_value=0)
        live = jnp.arange(budget) < jnp.sum(seg.valid)
        keep = flat(jnp.zeros_like(seg.valid)).at[jnp.where(live, slot, r * m)].set(True, mode="drop").reshape(r, m)
    ray = slot // m
    return _Packed(keep=keep, slot=slot, live=live, origin=rays.origin[ray], direction=rays.direction[ray],
                   t_lo=flat(seg.t_lo)[slot], t_hi=flat(seg.t_hi)[slot], node=flat(seg.node)[slot],
                   level_index=(scene.tree.depth - 1) - flat(seg.level)[slot])


def _along(p: _Packed, t: jax.Array) -> jax.Array:
    """Positions ``[B, S, 3]`` at distances ``t [B, S]`` along the slots' rays."""
    return p.origin[:, None, :] + t[..., None] * p.direction[:, None, :]


def _render(cfg: RenderConfig, params: dict, scene: PointScene, rays: Rays, background, key,
            aux: bool) -> tuple[RenderOut, SegmentAux | None]:
    seg = intersect(scene.tree, rays, cfg.kdtree, scene.capacities)
    stage_check(cfg.checks, "traversal", origin=rays.origin, direction=rays.direction)
    stage_check(cfg.checks, "traversal", where=seg.valid, t_lo=seg.t_lo, t_hi=seg.t_hi)
    p = _pack(scene, rays, seg)
    if cfg.integration == "samples":
        return _render_samples(cfg, params, scene, rays, background, key, aux, seg, p)
    t, w = level_samples(cfg.quadrature, p.t_lo, p.t_hi, p.level_index, key)  # [B, S]
    sh = shade_segments(cfg, params, scene, _along(p, t), p.node, w, p.direction, aux)
    normal = None if sh.shading_normal is None else p.unpack(sh.shading_normal)
    extra = None
    if aux:
        extra = {"pred_normal": p.unpack(sh.pred_normal), "confidence": p.unpack(sh.values["confidence"][..., 0]),
                 "normal_moment": p.unpack(sh.values["normal_moment"].reshape(-1, 3, 3))}
    return _composite_out(cfg, params, rays, background, seg, p.keep, p.keep, p.unpack(sh.sigma), p.unpack(sh.rgb),
                          (seg.t_hi - seg.t_lo) / scene.tree.spacing, 0.5 * (seg.t_lo + seg.t_hi), normal, extra)


def _composite_out(cfg: RenderConfig, params, rays: Rays, background, seg, keep, valid, sigma, rgb, lengths, depth_t,
                   normals, extra) -> tuple[RenderOut, SegmentAux | None]:
    """Composite ``valid [R, N]`` slots (segments, or samples) front to back: ``sigma``, ``rgb``,
    ``lengths`` (point spacings), ``depth_t`` and optional shading ``normals`` ``[R, N, ...]``; the
    counts come from the segments (``keep [R, M]``: rendered; ``seg``: overflow, valid). With
    ``extra`` (``pred_normal``, ``confidence``, ``normal_moment`` ``[R, N, ...]``) also the
    :class:`SegmentAux` of the slots."""
    bg = background_color(cfg.shading, params, rays.origin, rays.direction, background)
    comp = composite(sigma, rgb, lengths, valid, depth_t, bg, normals=normals)
    stage_check(cfg.checks, "compositing", rgb=comp.rgb, opacity=comp.opacity, depth=comp.depth)
    normal_map = comp.normal if comp.normal is not None else jnp.zeros_like(comp.rgb)
    out = RenderOut(rgb=comp.rgb, opacity=comp.opacity, depth=comp.depth, normal=normal_map,
                    num_segments=jnp.sum(keep, axis=-1),
                    lost=seg.lost(packing=jnp.sum(seg.valid & ~keep, axis=-1).astype(jnp.int32)))
    if extra is None:
        return out, None
    seg_aux = SegmentAux(
        valid=valid, weights=comp.weights, sigma=sigma, lengths=jnp.where(valid, lengths, 0.0),
        pred_normal=extra["pred_normal"],
        shading_normal=jnp.zeros(valid.shape + (3,), comp.rgb.dtype) if normals is None else normals,
        view_dir=jnp.where(valid[..., None], rays.direction[:, None, :], 0.0),
        confidence=extra["confidence"], normal_moment=extra["normal_moment"])
    return out, seg_aux


def _render_samples(cfg: RenderConfig, params: dict, scene: PointScene, rays: Rays, background, key,
                    aux: bool, seg, p: _Packed) -> tuple[RenderOut, SegmentAux | None]:
    """The ``integration="samples"`` half of :func:`_render`, from the packed segments on: every
    sample shaded on its own and composited as its own sub-interval (module docstring)."""
    ns = cfg.quadrature.max_samples
    t, inside, s_count = sample_intervals(cfg.quadrature, p.t_lo, p.t_hi, p.level_index, key)  # [B, S], [B, 1]
    sh = shade_samples(cfg, params, scene, _along(p, t), p.node, p.direction, aux)  # [B, S]
    sub_len = jnp.where(inside, (p.t_hi - p.t_lo)[:, None] / scene.tree.spacing / s_count, 0.0)  # [B, S]
    unpack = functools.partial(p.unpack, per_slot=1)  # [B, S, ...] -> [R, M * S, ...]
    ok = jnp.repeat(p.keep, ns, axis=1) & unpack(inside)  # [R, M * S]
    mask = lambda v: jnp.where(ok.reshape(ok.shape + (1,) * (v.ndim - 2)), v, 0.0)  # noqa: E731
    normal = None if sh.shading_normal is None else mask(unpack(sh.shading_normal))
    extra = None
    if aux:
        moment = sh.values["normal_moment"].reshape(t.shape + (3, 3))
        extra = {"pred_normal": mask(unpack(sh.pred_normal)),
                 "confidence": mask(unpack(sh.values["confidence"][..., 0])), "normal_moment": mask(unpack(moment))}
    return _composite_out(cfg, params, rays, background, seg, p.keep, ok, mask(unpack(sh.sigma)), unpack(sh.rgb),
                          mask(unpack(sub_len)), unpack(t), normal, extra)

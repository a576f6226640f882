"""Buffer sizes of traversal and packing, and the one rule that grows them (docs/geometry.md).

Traversal and segment packing write into fixed-size buffers: static shapes, so one compiled program
per size. These sizes are not model settings: they decide only what is lost when a buffer is full,
and what is lost is counted, never silent. So they live apart from the configs that define a model
(and its config key):

- :class:`Capacities`, one static object carried by the scene
  (:attr:`~ne_jax.render.renderer.PointScene.capacities`) and saved with a run;
- :class:`Lost`, what a call lost to them, per ray, returned by every render
  (:attr:`~ne_jax.render.renderer.RenderOut.lost`) and by the traversal
  (:meth:`~ne_jax.geometry.intersect.Segments.lost`);
- :func:`grow`, the one rule that sizes them up from what was lost (host side), used by image
  renders, training epochs, the growth scan and differentiable edits alike, and
  :func:`fit_packing`, which sizes the packing budget from a probe batch before training.

The same rays rendered with larger capacities give the same segments, only fewer of them lost (the
traversal and the packing keep the first segments in ray order), so growing never changes a
complete result.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from ne_jax.fields import require


@dataclasses.dataclass(frozen=True)
class Capacities:
    """Buffer sizes of a render (hashable; a static argument). Grown by :func:`grow`."""

    frontier: int = 64
    """Nodes kept per ray and level during traversal; more are dropped (their subtrees are not
    visited) and counted in :attr:`Lost.frontier`."""

    first_pass_frontier: int | None = None
    """Two-pass traversal (``None``: one pass): every ray is walked first with this narrower frontier,
    and the rays that overflow it are walked again at :attr:`frontier`, at most
    ``ceil(retry_share * R)`` of them per call (the first ones). While the retries fit, the segments
    equal one pass at :attr:`frontier`; a ray beyond the share keeps the narrow pass's segments and its
    loss is counted. Most rays of a surface-like cloud need few nodes per level, and the traversal's
    cost follows the frontier's width."""

    retry_share: float = 1.0 / 16.0
    """Two-pass traversal: the share of a call's rays that may be walked again at full width."""

    max_segments: int = 32
    """Segment slots per ray (:class:`~ne_jax.geometry.intersect.Segments`); more are counted in
    :attr:`Lost.slots`."""

    segments_per_ray: float | None = 4.0
    """Packing budget: the valid segments of a ray batch are packed into
    ``ceil(R * segments_per_ray)`` slots before sampling, KNN and shading, so work follows the
    segments that exist, not the ``max_segments`` slots per ray (most rays of an image hit nothing).
    Segments beyond it are dropped and counted in :attr:`Lost.packing`. ``None``: no packing."""

    def __post_init__(self):
        def need(cond, name, expected):
            require(self, cond, name, expected)

        need(self.frontier >= 2, "frontier", "an integer >= 2")
        if self.first_pass_frontier is not None:
            need(2 <= self.first_pass_frontier < self.frontier, "first_pass_frontier",
                 f"None or an integer in [2, frontier) = [2, {self.frontier})")
        need(0 < self.retry_share <= 1, "retry_share", "a share in (0, 1]")
        need(self.max_segments >= 1, "max_segments", "an integer >= 1")
        need(self.segments_per_ray is None or self.segments_per_ray > 0, "segments_per_ray", "None or > 0")

    def replace(self, **changes) -> Capacities:
        return dataclasses.replace(self, **changes)

    def segment_budget(self, num_rays: int) -> int | None:
        """Packed segment slots for a batch of ``num_rays`` rays (``None``: no packing)."""
        if self.segments_per_ray is None:
            return None
        return max(1, int(np.ceil(num_rays * self.segments_per_ray)))


@struct.dataclass
class Lost:
    """What a call lost to its :class:`Capacities`, per ray (``[R]`` int32 each; any leading shape).

    Attributes:
        frontier: nodes dropped from a full traversal frontier (their subtrees were not visited).
        slots: segments found beyond the ``max_segments`` slots of the ray.
        packing: segments beyond the packing budget (``segments_per_ray``).
        emitted: segments the traversal found (rendered, or lost to slots or packing).
    All of ``frontier``, ``slots`` and ``packing`` zero: nothing was lost.
    """

    frontier: jax.Array
    slots: jax.Array
    packing: jax.Array
    emitted: jax.Array

    @property
    def count(self) -> jax.Array:
        """Per ray: frontier nodes and segments lost (0 where the ray is complete)."""
        return self.frontier + self.slots + self.packing

    @classmethod
    def none(cls, shape) -> Lost:
        """Nothing lost (a renderer without capacities, e.g. Naive Plotting)."""
        zero = jnp.zeros(shape, jnp.int32)
        return cls(frontier=zero, slots=zero, packing=zero, emitted=zero)

    def counts(self) -> LostCounts:
        """Host side: the totals :func:`grow` reads (one transfer)."""
        v = jax.device_get(jnp.stack([jnp.sum(self.frontier), jnp.sum(self.slots), jnp.sum(self.packing),
                                      jnp.max(self.emitted, initial=0), jnp.sum(self.emitted)]))
        return LostCounts(frontier=int(v[0]), slots=int(v[1]), packing=int(v[2]), max_emitted=int(v[3]),
                          emitted=int(v[4]), rays=int(np.prod(self.emitted.shape)))


@dataclasses.dataclass(frozen=True)
class LostCounts:
    """Totals of one or more :class:`Lost` records over ``rays`` rays (host numbers): nodes and
    segments lost, the most segments one ray found and the segments found in all."""

    frontier: int = 0
    slots: int = 0
    packing: int = 0
    max_emitted: int = 0
    emitted: int = 0
    rays: int = 0

    @property
    def total(self) -> int:
        return self.frontier + self.slots + self.packing

    def __add__(self, other: LostCounts) -> LostCounts:
        return LostCounts(frontier=self.frontier + other.frontier, slots=self.slots + other.slots,
                          packing=self.packing + other.packing, max_emitted=max(self.max_emitted, other.max_emitted),
                          emitted=self.emitted + other.emitted, rays=self.rays + other.rays)

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


def _next_pow2(x: float) -> int:
    return 2 ** max(0, math.ceil(math.log2(max(x, 1.0))))


BUFFERS: tuple[str, ...] = ("frontier", "slots", "packing")
"""The buffers :func:`grow` sizes, named as the fields of :class:`Lost` that count their losses."""


def grow(cap: Capacities, lost: Lost | LostCounts, buffers: tuple[str, ...] = BUFFERS) -> Capacities | None:
    """The capacities after ``lost`` (host side), or ``None`` when nothing was lost (or nothing that
    lost can grow). ``buffers``: the ones the caller lets grow (default all; training grows only the
    packing budget, see docs/geometry.md). One rule for every
    buffer, each grown only when it lost something:

    - frontier nodes dropped: a two-pass walk retries twice the share of rays (up to all of them),
      then the frontier doubles;
    - segments beyond the slots: ``max_segments`` to the next power of two that holds the most any
      ray found (at least twice as many);
    - segments beyond the packing budget: ``segments_per_ray`` times the power of two (at least 2)
      that holds the mean segments per ray found.

    Growth is by powers of two, so a run meets few distinct sizes (one compilation each)."""
    unknown = set(buffers) - set(BUFFERS)
    if unknown:
        raise ValueError(f"grow: expected buffers among {BUFFERS}, found {sorted(unknown)}")
    c = lost.counts() if isinstance(lost, Lost) else lost
    if c.total == 0:
        return None
    start = cap
    if c.frontier > 0 and "frontier" in buffers:
        if cap.first_pass_frontier is not None and cap.retry_share < 1:
            cap = cap.replace(retry_share=min(1.0, 2 * cap.retry_share))
        else:
            cap = cap.replace(frontier=2 * cap.frontier)
    if c.slots > 0 and "slots" in buffers:
        cap = cap.replace(max_segments=max(2 * cap.max_segments, _next_pow2(c.max_emitted)))
    if c.packing > 0 and "packing" in buffers and cap.segments_per_ray is not None:
        needed = c.emitted / max(c.rays, 1)
        cap = cap.replace(segments_per_ray=cap.segments_per_ray * max(2, _next_pow2(needed / cap.segments_per_ray)))
    return None if cap == start else cap


PACKING_STEP = 2.0
""":func:`fit_packing` sizes the budget in multiples of this many segments per ray (a training
step's time follows its budget: docs/decisions.md, the packing budget)."""


def fit_packing(cap: Capacities, mean_segments: float, headroom: float = 1.25) -> Capacities:
    """``cap`` with a packing budget that holds ``headroom`` times ``mean_segments`` (the mean segments
    per ray of a probe batch): the smallest multiple of :data:`PACKING_STEP` that does, never lowered.
    Sized before training, where a batch's dropped segments would leave their rays training on the
    background; each new size compiles the step once more."""
    need = headroom * mean_segments
    if cap.segments_per_ray is None or cap.segments_per_ray >= need:
        return cap
    return cap.replace(segments_per_ray=PACKING_STEP * math.ceil(need / PACKING_STEP))


__all__ = ["BUFFERS", "Capacities", "Lost", "LostCounts", "fit_packing", "grow"]

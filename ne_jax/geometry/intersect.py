"""Ray / K-D-voxel traversal (data flow step 2 of docs/design.md).

``intersect`` walks the tree top-down, level by level, keeping for every ray a fixed-capacity
frontier of the nodes its segment ``[near, far]`` hits, and emits the *minimal intersected voxels*
of the rendering levels: a node at a rendering level is emitted when the ray hits its box but none
of its children's boxes; at the bottom rendering level every hit node is emitted (its children are
single points, not voxels). Above the rendering levels nothing is emitted (the ray's part there is
empty space). Only valid boxes are emitted; invalid ("too spread out") boxes are still descended
through, as in the released code. Segments come out sorted by entry distance; boxes of one level are
disjoint and a child's box lies in its parent's, so the segments of a ray never overlap (except on
shared faces, where a ray lying exactly in the face plane sees both neighbours).

Hit rule (exact, no epsilon in the slab test itself): per axis, a direction component that is
``0.0`` or ``-0.0`` (or smaller in magnitude than ``sqrt(tiny)`` of the dtype: float32 ~1.1e-19,
float64 ~1.5e-154, below which the derivative ``-1/d^2`` of the slab distances overflows) makes the
ray parallel to that slab: inside iff ``lo <= origin <= hi`` (closed). Such a component moves the
ray by less than ``1e-19 * far`` across the slab, so only an origin within that distance of a face
can decide differently from the exact test. Otherwise the slab is ``[(lo-o)/d, (hi-o)/d]`` (ordered).
The ray hits the box iff the clipped interval ``[max(enter, near), min(exit, far)]`` is longer than
``MIN_HIT_FACTOR * tree.spacing`` (released code: ``unit_len / 16``). Rays through an edge or a
corner, grazing a box, or tangent to a curved cluster are then deterministic misses; a ray lying in a
face plane (parallel axis, origin on the face) counts as inside.

A tree carried through an edit (:mod:`ne_jax.geometry.carry`) keeps the boxes of each subtree below
its frame level in the frame the subtree's points had when the tree was built: there the ray is
mapped into that frame (``x -> frame_rot @ x + frame_shift``, a similarity, so ``t`` keeps its
meaning) before the slab test, and a ray is cut where the same ray was cut before the edit. A built
tree has no frames and traces none of this.

Buffer sizes come from :class:`~ne_jax.geometry.capacity.Capacities` (``frontier``,
``max_segments``; static); what does not fit is counted per ray (``frontier_overflow``: nodes dropped
from a frontier, whose whole subtree is lost; ``segment_overflow``: emitted segments beyond the
slots; :meth:`Segments.lost`). ``intersect_checked`` (host) grows them with
:func:`~ne_jax.geometry.capacity.grow` and retries until nothing is lost. With
``first_pass_frontier`` every ray is walked at that narrower width first and only the rays that
overflow it are walked again at full width (a share ``retry_share`` of the call's rays at most),
which gives the full width's segments at a fraction of its cost.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
from flax import struct
from jax import lax

from ne_jax.data.rays import Rays
from ne_jax.geometry.capacity import Capacities, Lost, grow
from ne_jax.geometry.kdtree import MIN_HIT_FACTOR, KDTree, KDTreeConfig
from ne_jax.numerics import safe_reciprocal, stable_ranks, tiny


@struct.dataclass
class Segments:
    """Per ray ``M`` segment slots, sorted by ``t_lo`` (valid slots first).

    Attributes:
        t_lo, t_hi: ``[R, M]`` entry / exit distance along the ray (0 in invalid slots).
        node: ``[R, M]`` int32 heap index of the voxel's node (0 in invalid slots).
        level: ``[R, M]`` int32 tree level of the node (``-1`` in invalid slots).
        valid: ``[R, M]`` bool.
        frontier_overflow: ``[R]`` int32 nodes dropped from a full frontier (their subtrees were
            not visited); ``> 0`` means the segment list is incomplete.
        segment_overflow: ``[R]`` int32 emitted segments that did not fit into the ``M`` slots.
        num_emitted: ``[R]`` int32 segments found (valid + segment overflow).
    """

    t_lo: jax.Array
    t_hi: jax.Array
    node: jax.Array
    level: jax.Array
    valid: jax.Array
    frontier_overflow: jax.Array
    segment_overflow: jax.Array
    num_emitted: jax.Array

    @property
    def overflow(self) -> jax.Array:
        """``[R]`` total overflow count (0 everywhere means complete and exact)."""
        return self.frontier_overflow + self.segment_overflow

    @property
    def num_segments(self) -> jax.Array:
        return jnp.sum(self.valid, axis=-1)

    def lost(self, packing: jax.Array | None = None) -> Lost:
        """What the traversal lost, per ray, plus ``packing`` ``[R]`` segments a later packing
        dropped (default none)."""
        return Lost(frontier=self.frontier_overflow, slots=self.segment_overflow,
                    packing=jnp.zeros_like(self.num_emitted) if packing is None else packing,
                    emitted=self.num_emitted)


def slab_intersect(lo, hi, origin, inv_dir, parallel, near, far, min_len):
    """Ray-box test; all arguments broadcast (boxes ``[..., 3]``, ray quantities ``[3]`` / ``[]``).

    ``parallel = |direction| < sqrt(tiny)``, ``inv_dir = safe_reciprocal(direction)`` (0 where parallel:
    see :func:`_parallel_and_inverse`). Returns
    ``(t_lo, t_hi, hit)`` with ``t_lo = max(enter, near)``, ``t_hi = min(exit, far)`` and
    ``hit = t_lo + min_len < t_hi``. Never NaN; gradients finite (see the module docstring)."""
    return _slab_axes(_axes(lo), _axes(hi), _axes(origin), _axes(inv_dir), _axes(parallel), near, far, min_len)


def _axes(a):
    """``(a[..., 0], a[..., 1], a[..., 2])``."""
    return tuple(a[..., k] for k in range(3))


def _slab_axes(lo, hi, origin, inv_dir, parallel, near, far, min_len):
    """:func:`slab_intersect` with the boxes and the ray given per axis (tuples of three arrays):
    elementwise code only. XLA:CPU does not vectorise arithmetic over a minor axis of size 3; per
    axis it does (what the render gains: docs/studies/profile.md)."""
    enter = exit_ = None
    for lo_a, hi_a, o, inv, par in zip(lo, hi, origin, inv_dir, parallel):
        t1 = (lo_a - o) * inv
        t2 = (hi_a - o) * inv
        inside = (lo_a <= o) & (o <= hi_a)
        big = jnp.asarray(jnp.inf, t1.dtype)
        tmin = jnp.where(par, jnp.where(inside, -big, big), jnp.minimum(t1, t2))
        tmax = jnp.where(par, jnp.where(inside, big, -big), jnp.maximum(t1, t2))
        enter = tmin if enter is None else jnp.maximum(enter, tmin)
        exit_ = tmax if exit_ is None else jnp.minimum(exit_, tmax)
    t_lo = jnp.maximum(enter, near)
    t_hi = jnp.minimum(exit_, far)
    return t_lo, t_hi, t_lo + min_len < t_hi


def _parallel_and_inverse(direction):
    """``(parallel, inv_dir)`` for the slab test. Components below ``sqrt(tiny)`` in magnitude are
    parallel and get ``inv_dir = 0`` with a zero gradient (double ``where``): ``safe_reciprocal``'s
    derivative ``-1/d^2`` overflows to ``inf`` there, and the zero cotangent of a slab bound that is
    not the active one turned it into NaN (``0 * inf``) in the gradient of any ray with such a
    component (bug found by ``tests/hard_cases/test_traversal.py``)."""
    par = jnp.abs(direction) < jnp.sqrt(tiny(direction.dtype))
    inv = jnp.where(par, 0.0, safe_reciprocal(jnp.where(par, 1.0, direction)))
    return par, inv


def _prefix_count(mask):
    """``cumsum(mask)`` of a bool vector ``[n]`` as int32, by a product with a triangular matrix of
    ones (exact in float32 below 2**24), a matmul where XLA:CPU lowers ``cumsum`` to a
    reduce-window."""
    n = mask.shape[-1]
    tri = jnp.triu(jnp.ones((n, n), jnp.float32))
    return jnp.dot(mask.astype(jnp.float32), tri, precision=lax.Precision.HIGHEST).astype(jnp.int32)


def _stable_sort_by(key, values):
    """``values`` (tuple of ``[n]`` arrays) ordered by ``key [n]``, equal keys in their order: the
    entries moved to their :func:`~ne_jax.numerics.stable_ranks` by masked sums, elementwise work
    that XLA:CPU vectorises, where ``lax.sort`` runs a comparator per pair."""
    slot = jnp.arange(key.shape[0])
    to = stable_ranks(key)[None, :] == slot[:, None]  # [position, entry]
    return tuple(jnp.sum(jnp.where(to, v[None, :], jnp.zeros((), v.dtype)), axis=1) for v in values)


def _compact(mask, values, capacity):
    """Move the entries of ``values`` (tuple of ``[n, ...]`` arrays) where ``mask [n]`` to the front
    of ``capacity`` slots (stable). Returns ``(compacted, kept_mask, total)``."""
    pos = _prefix_count(mask) - 1
    target = jnp.where(mask & (pos < capacity), pos, capacity)
    out = tuple(jnp.zeros((capacity + 1,) + v.shape[1:], v.dtype).at[target].set(v)[:capacity] for v in values)
    total = jnp.sum(mask, dtype=jnp.int32)  # int32 under x64 too (scan carry)
    kept = jnp.arange(capacity) < total
    return out, kept, total


def _ray_in_frame(tree: KDTree, node, origin, direction):
    """The ray in the carried frame of ``node`` (heap indices at ``tree.frame_level``, any shape):
    ``(origin, inv_dir, parallel)`` ``[..., 3]`` for :func:`slab_intersect`. A similarity keeps
    ``t`` the same distance along the ray."""
    row = node - (2**tree.frame_level - 1)
    rot, shift = tree.frame_rot[row], tree.frame_shift[row]
    o = jnp.sum(rot * origin, axis=-1) + shift
    par, inv = _parallel_and_inverse(jnp.sum(rot * direction, axis=-1))
    return o, inv, par


def _traverse_one(tree: KDTree, origin, direction, near, far, cfg: KDTreeConfig, first_emit: int, f_cap: int,
                  m_cap: int):
    dtype = origin.dtype
    depth = tree.depth
    par, inv = _parallel_and_inverse(direction)
    min_len = (MIN_HIT_FACTOR * tree.spacing).astype(dtype)
    world = (origin, inv, par)
    # Levels at and below a carried tree's frame level are tested in their subtree's frame: the ray
    # is mapped once per frontier node entering that level, and its children inherit it.
    frame_level = tree.frame_level if tree.has_frames else depth

    lo_axes, hi_axes = _axes(tree.lo), _axes(tree.hi)  # per-axis tables: see _slab_axes

    def test(node, ray):
        o, i, p = ray
        return _slab_axes(tuple(a[node] for a in lo_axes), tuple(a[node] for a in hi_axes),
                          _axes(o), _axes(i), _axes(p), near, far, min_len)

    def kids_in_world(kids, ray):  # -> (the ray each kid's box is tested with, what the frontier keeps)
        return world, None

    def kids_enter_frames(kids, ray):
        ray = _ray_in_frame(tree, kids, origin, direction)
        return ray, ray

    def kids_inherit_frames(kids, ray):
        ray = tuple(r[:, None, :] for r in ray)
        return ray, tuple(jnp.broadcast_to(r, kids.shape + (3,)) for r in ray)

    root = jnp.zeros((), jnp.int32)
    root_ray = _ray_in_frame(tree, root, origin, direction) if frame_level == 0 else world
    _, _, r_hit = test(root, root_ray)
    r_hit = r_hit & (tree.count[0] > 0)
    # The frontier (nodes, live mask, and each node's ray once frames are entered) starts as the
    # root alone and doubles per level until it is f_cap wide: a level of at most f_cap nodes keeps
    # every kid (dead ones masked), with no compaction. A node's span along the ray is computed
    # again where it is emitted rather than carried (fewer arrays to compact).
    front = (jnp.zeros((1,), jnp.int32), r_hit[None], tuple(r[None] for r in root_ray) if frame_level == 0 else None)
    out = (
        jnp.zeros((m_cap + 1,), dtype),
        jnp.zeros((m_cap + 1,), dtype),
        jnp.zeros((m_cap + 1,), jnp.int32),
        jnp.full((m_cap + 1,), -1, jnp.int32),
    )
    zero = jnp.zeros((), jnp.int32)

    def emit(out, n_out, level, node, ray, mask):
        t_lo, t_hi, _ = test(node, world if ray is None else ray)  # as when the node was tested
        pos = n_out + _prefix_count(mask) - 1
        target = jnp.where(mask & (pos < m_cap), pos, m_cap)
        lev = jnp.full(node.shape, level, jnp.int32)
        out = tuple(o.at[target].set(v) for o, v in zip(out, (t_lo, t_hi, node, lev)))
        return out, n_out + jnp.sum(mask, dtype=jnp.int32)

    def step(kid_rays, emits, carry, level):
        (node, live, ray), out, n_out, f_over = carry
        kids = jnp.stack([2 * node + 1, 2 * node + 2], axis=-1)  # [F, 2]
        k_ray, keep_ray = kid_rays(kids, ray)
        _, _, k_hit = test(kids, k_ray)
        k_hit = k_hit & live[:, None] & (tree.count[kids] > 0)
        if emits:  # a rendering level (or the growing level): emit the hit nodes none of whose kids is hit
            leaf_parent = ~jnp.any(k_hit, axis=-1)
            mask = live & tree.valid[node] & leaf_parent
            out, n_out = emit(out, n_out, level, node, ray, mask)
        kept_rays = () if keep_ray is None else tuple(r.reshape(-1, 3) for r in keep_ray)
        values = (kids.reshape(-1), *kept_rays)
        if kids.size <= f_cap:  # every kid fits: keep them all, in order
            (node, *ray), kept = values, k_hit.reshape(-1)
        else:
            (node, *ray), kept, total = _compact(k_hit.reshape(-1), values, f_cap)
            f_over = f_over + jnp.maximum(total - f_cap, 0)
        return ((node, kept, tuple(ray) if ray else None), out, n_out, f_over), None

    carry = (front, out, zero, zero)
    # Parents at levels [a, b), in runs of levels that share the kids' rays and whether they emit
    # (the levels above the first emitting one do no emission work at all).
    for kid_rays, a, b in ((kids_in_world, 0, frame_level - 1), (kids_enter_frames, frame_level - 1, frame_level),
                           (kids_inherit_frames, frame_level, depth - 1)):
        a, b = max(a, 0), min(b, depth - 1)
        for lo_, hi_, emits in ((a, min(b, first_emit), False), (max(a, first_emit), b, True)):
            if lo_ >= hi_:
                continue
            body = functools.partial(step, kid_rays, emits)
            # Levels whose frontier is still narrower than f_cap (it doubles per level, and the
            # kids' rays join it when they enter frames) change the carry's shapes: one step each.
            while lo_ < hi_ and (carry[0][0].shape[0] < f_cap or kid_rays is kids_enter_frames):
                carry, _ = body(carry, jnp.asarray(lo_, jnp.int32))
                lo_ += 1
            if lo_ < hi_:
                carry, _ = lax.scan(body, carry, jnp.arange(lo_, hi_, dtype=jnp.int32))
    (node, live, ray), out, n_out, f_over = carry
    mask = live & tree.valid[node]
    out, n_out = emit(out, n_out, depth - 1, node, ray, mask)

    o_lo, o_hi, o_node, o_level = (o[:m_cap] for o in out)
    valid = jnp.arange(m_cap) < n_out
    key = jnp.where(valid, o_lo, jnp.inf)  # valid segments have finite entries: they come first
    o_lo, o_hi, o_node, o_level = _stable_sort_by(key, (o_lo, o_hi, o_node, o_level))
    o_valid = valid
    seg_over = jnp.maximum(n_out - m_cap, 0)
    return (
        jnp.where(o_valid, o_lo, 0),
        jnp.where(o_valid, o_hi, 0),
        jnp.where(o_valid, o_node, 0),
        jnp.where(o_valid, o_level, -1),
        o_valid,
        f_over,
        seg_over,
        n_out,
    )


def _check_rays(rays: Rays):
    o, d = rays.origin, rays.direction
    if o.ndim != 2 or o.shape[-1] != 3:
        raise ValueError(f"rays.origin: expected shape [R, 3], found shape {o.shape}")
    if d.shape != o.shape:
        raise ValueError(f"rays.direction: expected shape {o.shape} (as origin), found shape {d.shape}")
    for name in ("near", "far"):
        a = getattr(rays, name)
        if a.shape != o.shape[:1]:
            raise ValueError(f"rays.{name}: expected shape [R={o.shape[0]}], found shape {a.shape}")


@functools.partial(jax.jit, static_argnames=("cfg", "capacities", "include_grow_level"))
def intersect(tree: KDTree, rays: Rays, cfg: KDTreeConfig = KDTreeConfig(),
              capacities: Capacities = Capacities(), include_grow_level: bool = False) -> Segments:
    """Minimal intersected voxels of every ray (see the module docstring). Jit-compiled; ``cfg``,
    ``capacities`` (the frontier and segment slots; its packing budget is not read here) and
    ``include_grow_level`` (also emit the growing level's minimal voxels) are static.

    Args:
        tree: from :func:`~ne_jax.geometry.kdtree.build_tree` (``cfg.num_render_levels`` must match).
        rays: ``origin``/``direction`` ``[R, 3]`` (direction need not be unit: ``t`` is in units of
            its length), ``near``/``far`` ``[R]`` finite.
    """
    _check_rays(rays)
    if tree.num_render_levels != cfg.num_render_levels:
        raise ValueError(
            f"cfg.num_render_levels: expected the tree's value {tree.num_render_levels}, found {cfg.num_render_levels}"
        )
    first = tree.depth - cfg.num_render_levels - (1 if include_grow_level else 0)
    dtype = rays.origin.dtype
    args = (rays.origin, rays.direction.astype(dtype), rays.near.astype(dtype), rays.far.astype(dtype))
    cap = capacities

    def walk(width, *ray_args):
        return Segments(*jax.vmap(
            lambda o, d, n, f: _traverse_one(tree, o, d, n, f, cfg, first, width, cap.max_segments))(*ray_args))

    if cap.first_pass_frontier is None:
        return walk(cap.frontier, *args)
    narrow = walk(cap.first_pass_frontier, *args)
    n = rays.num_rays
    retry = jnp.nonzero(narrow.frontier_overflow > 0, size=min(n, math.ceil(cap.retry_share * n)), fill_value=n)[0]
    wide = walk(cap.frontier, *(a[jnp.minimum(retry, n - 1)] for a in args))
    # unused retry slots hold index n: their writes are dropped
    return jax.tree_util.tree_map(lambda a, b: a.at[retry].set(b, mode="drop"), narrow, wide)


def intersect_checked(
    tree: KDTree,
    rays: Rays,
    cfg: KDTreeConfig = KDTreeConfig(),
    capacities: Capacities = Capacities(),
    include_grow_level: bool = False,
    max_tries: int = 8,
) -> tuple[Segments, Capacities]:
    """Host-side: run :func:`intersect`, and while any ray loses something, grow the capacities
    (:func:`~ne_jax.geometry.capacity.grow`) and retry. Returns the complete segments and the
    capacities that fit (reuse them for later batches: the same capacities mean no recompilation).

    Raises:
        RuntimeError: still losing segments after ``max_tries`` attempts.
    """
    cap = capacities
    for _ in range(max_tries):
        seg = intersect(tree, rays, cfg, cap, include_grow_level)
        bigger = grow(cap, seg.lost())
        if bigger is None:
            return seg, cap
        cap = bigger
    raise RuntimeError(f"intersect_checked: still losing segments after {max_tries} tries ({cap})")

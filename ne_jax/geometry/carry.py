"""Carrying a built K-D tree through an edit, so that voxels move with their points.

Rebuilding the tree after an edit re-partitions the cloud: the node boxes, the candidate sets and
so the segments a ray is cut into all change, and the deterministic integration is not additive
over a segment cut differently, so a rigid motion of a whole trained scene no longer renders what the
unedited model showed from the moved cameras (docs/editing.md, "Edit fidelity"). ``carry_tree``
keeps what the model was trained with instead:

* **partition and candidate sets** are kept (node membership by index; dead points are masked by
  the KNN, as after pruning);
* **boxes move with their points**: every subtree under a node of the *frame level* (the growing
  level, ``depth - num_render_levels - 1``: the growing and rendering levels lie below it) gets the
  similarity ``y = s R x + t`` that best maps its points' positions at build time to their edited
  positions (Umeyama, over the subtree's alive members and its candidate set; ``s`` within 1e-5 of
  1 counts as 1). Its boxes stay as
  built, in the frame of the build, and a ray is tested there (``KDTree.frame_rot/frame_shift``):
  a ray is cut where the same ray was cut before the edit. Under a smooth deformation a point may
  leave its boxes by up to the fit's residual (below ``tear_factor`` spacings); the boxes are not
  grown for it, since neighbouring subtrees' voxels would then overlap and a ray would integrate
  their density twice; the point still reaches the samples of the voxels around it through their
  candidate sets;
* **deletions** shrink the boxes of the nodes that lost points to their alive members (plus the
  level's margin), as a rebuild would, and empty nodes are skipped;
* **torn subtrees** (residual above ``tear_factor`` point spacings: a cut, a part moved away) are
  rebuilt locally: their members (the same slots) split again on their edited positions, with world
  boxes as :func:`~ne_jax.geometry.kdtree.build_tree` makes them, and new candidate sets;
* levels above the frame level hold world boxes bounding their children's (traversal only culls
  with them), and ``spacing`` (the density's length unit) is scaled by the median of the subtrees'
  scales: kept for rigid motions and smooth deformations, scaled with a uniform scaling.

For a whole-scene rigid motion (or uniform scaling) and cameras moved with it, every segment,
sample and neighbour is the unedited one up to rounding (tested: ``tests/geometry/test_carry.py``).

``oriented=False`` and ``recompute_candidates=True`` are analysis switches for the equivariance
study (``experiments/equivariance.py``): world boxes around the moved members for every subtree
(the partition kept, the boxes re-fitted), and candidate sets re-chosen around the moved boxes.

What every carry of one built tree shares (the validity limit of its rest cloud, which the local
rebuilds use) is a :class:`CarryContext`: made once by :func:`carry_context`, held by the caller
and passed back to every :func:`carry_tree` of the same tree (computed on the spot when not given).
"""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np
from scipy.spatial import cKDTree

from ne_jax.geometry.kdtree import (
    KDTree,
    KDTreeConfig,
    _cell_boxes,
    _level_margin_growth,
    _spacing_and_limit,
    _split_levels,
)


@dataclasses.dataclass(frozen=True, eq=False)
class CarryContext:
    """What every carry of one built tree shares, computed once from its rest cloud (host side) by
    :func:`carry_context` and passed back to :func:`carry_tree`.

    Attributes:
        held: ``[n, 3]`` float64 rest positions of the tree's points, in slot order (read-only): the
            cloud the context was made for, checked on every use.
        cfg: the tree config it was made with.
        limit: the validity threshold ``lim`` of ``held`` (the "too spread out" rule,
            :mod:`~ne_jax.geometry.kdtree`) that the boxes of local rebuilds are held to.
    """

    held: np.ndarray
    cfg: KDTreeConfig
    limit: float


def held_points(tree: KDTree) -> np.ndarray:
    """``[C]`` bool: the slots ``tree`` holds (for a tree from ``build_tree(xyz, alive)``, ``alive``)."""
    held = np.zeros(tree.capacity + 1, bool)
    held[np.asarray(tree.perm)] = True
    return held[: tree.capacity]


def _rest_limit(held_xyz: np.ndarray, cfg: KDTreeConfig) -> float:
    return _spacing_and_limit(held_xyz, cKDTree(held_xyz), cfg)[1]


def carry_context(rest_xyz, held, cfg: KDTreeConfig) -> CarryContext:
    """The :class:`CarryContext` of a tree built with ``cfg`` on ``rest_xyz [C, 3]`` that holds the
    slots ``held [C]`` bool (:func:`held_points`; for ``build_tree(rest_xyz, alive)``: ``alive``)."""
    rest = np.asarray(rest_xyz, np.float64)
    held = np.asarray(held, bool)
    if rest.ndim != 2 or rest.shape[1] != 3 or held.shape != rest.shape[:1]:
        raise ValueError(f"carry_context: expected rest_xyz [C, 3] and held [C], found shapes {list(rest.shape)} "
                         f"and {list(held.shape)}")
    pts = rest[np.flatnonzero(held)]
    pts.flags.writeable = False
    return CarryContext(held=pts, cfg=cfg, limit=_rest_limit(pts, cfg))


def _check_context(context: CarryContext, held_xyz: np.ndarray, cfg: KDTreeConfig) -> None:
    if context.cfg != cfg:
        raise ValueError("context: expected a CarryContext made with this tree's config, found one made with another "
                         "(make it with carry_context(rest_xyz, held, cfg) of this tree's config)")
    if context.held.shape != held_xyz.shape or not np.array_equal(context.held, held_xyz, equal_nan=True):
        what = (f"{context.held.shape[0]} points, the tree holds {held_xyz.shape[0]}"
                if context.held.shape != held_xyz.shape else "the same number of points at other positions")
        raise ValueError(f"context: expected the CarryContext of this tree's rest cloud, found one made for another "
                         f"cloud ({what}); make it with carry_context(rest_xyz, held_points(tree), cfg) of the "
                         "tree's rest positions")


def _similarity_fit(x: np.ndarray, y: np.ndarray, w: np.ndarray):
    """Weighted fits ``y ~ s R x + t`` (a rotation and a uniform scale; Umeyama) of ``[N, n, 3]``
    point sets (weights ``w [N, n]``). Sets with fewer than 3 weighted points get ``R = I``, ``s = 1``
    and the mean translation. Returns ``(R [N, 3, 3], s [N], t [N, 3])``."""
    ws = w.sum(axis=1)
    safe = np.maximum(ws, 1e-300)[:, None]
    cx = np.einsum("nk,nka->na", w, x) / safe
    cy = np.einsum("nk,nka->na", w, y) / safe
    xc = x - cx[:, None]
    h = np.einsum("nk,nka,nkb->nab", w, xc, y - cy[:, None])
    u, sv, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(np.einsum("nba,ncb->nac", vt, u)))
    d = np.where(d == 0, 1.0, d)
    fix = np.ones((x.shape[0], 3))
    fix[:, 2] = d
    rot = np.einsum("nba,nb,ncb->nac", vt, fix, u)  # V diag(1, 1, d) U^T
    var = np.einsum("nk,nka,nka->n", w, xc, xc)
    scale = np.where(var > 0, (sv * fix).sum(axis=1) / np.where(var > 0, var, 1.0), 1.0)
    few = ((w > 0).sum(axis=1) < 3) | ~(scale > 0)
    rot[few], scale[few] = np.eye(3), 1.0
    scale[np.abs(scale - 1.0) < 1e-5] = 1.0  # a rigid motion's fit, up to rounding
    return rot, scale, cy - scale[:, None] * np.einsum("nab,nb->na", rot, cx)


def _level_boxes(pos: np.ndarray, ok: np.ndarray, depth: int, first: int):
    """Per level ``first .. depth``: bounding boxes ``(lo, hi)`` ``[2**l, 3]`` and counts of the
    slot positions ``pos [P, 3]`` where ``ok [P]`` (NaN boxes where empty)."""
    p_lo = np.where(ok[:, None], pos, np.inf)
    p_hi = np.where(ok[:, None], pos, -np.inf)
    out = []
    for level in range(first, depth + 1):
        shape = (2**level, 2 ** (depth - level), 3)
        lo, hi = p_lo.reshape(shape).min(axis=1), p_hi.reshape(shape).max(axis=1)
        cnt = ok.reshape(shape[:2]).sum(axis=1)
        empty = (cnt == 0)[:, None]
        out.append((np.where(empty, np.nan, lo), np.where(empty, np.nan, hi), cnt))
    return out


def carry_tree(tree: KDTree, rest_xyz, xyz, alive, cfg: KDTreeConfig, *, tear_factor: float = 2.0,
               oriented: bool = True, recompute_candidates: bool = False,
               context: CarryContext | None = None) -> KDTree:
    """``tree`` (built on ``rest_xyz``) carried to the edited positions ``xyz`` (host side; see the
    module docstring): :func:`carry_tree_with_report` without its report."""
    return carry_tree_with_report(tree, rest_xyz, xyz, alive, cfg, tear_factor=tear_factor, oriented=oriented,
                                  recompute_candidates=recompute_candidates, context=context)[0]


def carry_tree_with_report(tree: KDTree, rest_xyz, xyz, alive, cfg: KDTreeConfig, *, tear_factor: float = 2.0,
                           oriented: bool = True, recompute_candidates: bool = False,
                           context: CarryContext | None = None) -> tuple[KDTree, dict]:
    """``tree`` (built on ``rest_xyz``) carried to the edited positions ``xyz`` (host side; see the
    module docstring), and what the carry did: ``(tree, report)``.

    Args:
        tree: built by :func:`~ne_jax.geometry.kdtree.build_tree` on ``rest_xyz`` (without frames).
        rest_xyz, xyz: ``[C, 3]`` positions at build time and after the edit (same indices).
        alive: ``[C]`` bool after the edit: a subset of the tree's points (an edit that adds points
            needs a rebuild).
        cfg: the tree's config (margins, candidate-set width).
        tear_factor: a subtree whose similarity fit leaves a member farther than this many point
            spacings from its edited position is torn: rebuilt locally, with new candidate sets.
        oriented, recompute_candidates: analysis switches (module docstring).
        context: :func:`carry_context` of ``tree`` and ``rest_xyz`` (made on the spot when ``None``).

    Returns:
        The carried tree and a dict: ``subtrees``, ``torn``, ``max_residual`` (in spacings),
        ``scale`` (the length unit's factor) and ``emptied`` (nodes that lost all their points).

    Raises:
        ValueError: shapes, non-finite edited positions, alive points the tree does not hold, or a
            ``context`` made for another rest cloud or config.
    """
    if tree.has_frames:
        raise ValueError("tree: expected a tree built on rest_xyz (no frames), found a carried tree; "
                         "carry the built tree from the original rest positions")
    cap, depth = tree.capacity, tree.depth
    rest = np.asarray(rest_xyz, np.float64)
    new = np.asarray(xyz, np.float64)
    alive = np.asarray(alive)
    for name, a, shape in (("rest_xyz", rest, (cap, 3)), ("xyz", new, (cap, 3)), ("alive", alive, (cap,))):
        if a.shape != shape:
            raise ValueError(f"{name}: expected shape {list(shape)} (the tree's capacity), found {list(a.shape)}")
    if alive.dtype != np.bool_:
        raise ValueError(f"alive: expected a bool mask, found dtype {alive.dtype}")
    perm = np.asarray(tree.perm)
    in_tree = np.zeros(cap + 1, bool)
    in_tree[perm] = True
    outside = alive & ~in_tree[:cap]
    if outside.any():
        raise ValueError(f"alive: expected the tree's points or a subset of them, found {int(outside.sum())} alive "
                         f"points the tree does not hold (first at index {int(np.flatnonzero(outside)[0])}); an "
                         "edit that adds points needs build_tree")
    bad = alive & ~np.isfinite(new).all(axis=1)
    if bad.any():
        raise ValueError(f"xyz: expected finite positions for alive points, found {int(bad.sum())} with NaN/inf "
                         f"(first at index {int(np.flatnonzero(bad)[0])})")
    rest_alive = np.flatnonzero(in_tree[:cap])
    if context is not None:
        _check_context(context, rest[rest_alive], cfg)

    f = depth - tree.num_render_levels - 1  # the frame level = the growing level
    nf, span = 2**f, 2 ** (depth - f)
    spacing = float(tree.spacing)
    kc = tree.candidates.shape[1]
    slot_pt = np.minimum(perm, cap - 1)
    slot_ok = (perm < cap) & alive[slot_pt]  # [P]
    live = np.append(alive, False)

    # Similarity fit per frame-level subtree, over its alive members and its candidate set.
    cand = np.asarray(tree.candidates)
    fit_idx = np.concatenate([perm.reshape(nf, span), cand[:nf]], axis=1)  # [nf, span + kc]
    fit_w = live[fit_idx].astype(np.float64)
    safe_idx = np.minimum(fit_idx, cap - 1)
    rot, scale, shift = _similarity_fit(rest[safe_idx], new[safe_idx], fit_w)
    moved = scale[:, None, None] * np.einsum("nab,nkb->nka", rot, rest[slot_pt].reshape(nf, span, 3)) + shift[:, None]
    err = np.linalg.norm(moved - new[slot_pt].reshape(nf, span, 3), axis=-1)
    residual = np.where(slot_ok.reshape(nf, span), err, 0.0).max(axis=1)  # [nf], world units
    occupied = slot_ok.reshape(nf, span).any(axis=1)
    # the length unit follows the edit's typical scale (exactly s for a uniform scaling by s)
    unit = float(np.median(scale[occupied])) if occupied.any() else 1.0
    spacing_world = spacing * unit
    torn = residual > tear_factor * spacing_world
    framed = ~torn if oriented else np.zeros(nf, bool)

    # Positions in the frame each slot's boxes live in: the build frame (framed) or the world.
    frame_pos = np.einsum("nba,nkb->nka", rot, new[slot_pt].reshape(nf, span, 3) - shift[:, None]) \
        / scale[:, None, None]
    pos = np.where(framed[:, None, None], frame_pos, new[slot_pt].reshape(nf, span, 3)).reshape(-1, 3)
    boxes = _level_boxes(pos, slot_ok, depth, f)
    count_built = np.asarray(tree.count)

    margin0 = cfg.margin_factor * spacing / math.sqrt(3.0)  # in the build's frame
    margin0_world = margin0 * unit
    lo_all, hi_all = np.asarray(tree.lo, np.float64).copy(), np.asarray(tree.hi, np.float64).copy()
    count_all = count_built.copy()
    for level in range(f, depth + 1):
        (b_lo, b_hi, cnt), g0 = boxes[level - f], 2**level - 1
        sl = slice(g0, g0 + 2**level)
        sub = np.repeat(np.arange(nf), 2 ** (level - f))  # each node's frame-level ancestor
        growth = _level_margin_growth(cfg, 2 ** (depth - level))
        m, m_world = margin0 * growth, margin0_world * growth
        lo_b, hi_b = lo_all[sl], hi_all[sl]  # the built boxes, in their frame
        lost = (cnt < count_built[sl])[:, None]  # shrink to what is left, as a rebuild would
        lo_f = np.where(lost, np.maximum(lo_b, b_lo - m), lo_b)
        hi_f = np.where(lost, np.minimum(hi_b, b_hi + m), hi_b)
        world = ~framed[sub][:, None]
        lo_new = np.where(world, b_lo - m_world, lo_f)
        hi_new = np.where(world, b_hi + m_world, hi_f)
        empty = (cnt == 0)[:, None]
        lo_all[sl] = np.where(empty, 0.0, lo_new)
        hi_all[sl] = np.where(empty, 0.0, hi_new)
        count_all[sl] = cnt

    # Torn subtrees are split again on their members' edited positions (a local rebuild: the same
    # slots, boxes of partition cells as build_tree makes them).
    perm_new = perm.copy()
    split_axis, split_value = np.asarray(tree.split_axis).copy(), np.asarray(tree.split_value, np.float64).copy()
    valid = np.asarray(tree.valid).copy()  # emptied nodes are cleared below, once every count is final
    sub_depth = depth - f
    resplit = np.flatnonzero(torn & oriented)
    if resplit.size:  # the released code's "too spread out" rule for the boxes made here
        lim = unit * (context.limit if context is not None else _rest_limit(rest[rest_alive], cfg))
    for i in resplit:
        ids = perm[i * span : (i + 1) * span]
        ids = ids[ids < cap]
        ids = ids[alive[ids]]
        if ids.size == 0:
            continue
        axes, values, leaf, (b_lo, b_hi, cnt) = _split_levels(new[ids], sub_depth)
        lo_l, hi_l = _cell_boxes(cfg, axes, values, b_lo, b_hi, cnt, sub_depth, margin0_world)
        perm_new[i * span : (i + 1) * span] = np.where(leaf >= 0, ids[np.maximum(leaf, 0)], cap)
        for level in range(sub_depth + 1):
            g = 2 ** (f + level) - 1 + i * 2**level
            sl = slice(g, g + 2**level)
            lo_all[sl], hi_all[sl], count_all[sl], valid[sl] = lo_l[level], hi_l[level], cnt[level], cnt[level] > 0
            if level > 0:  # rendering levels
                valid[sl] &= np.linalg.norm(hi_l[level] - lo_l[level], axis=1) <= 2.0 * lim
            if level < sub_depth:
                split_axis[sl], split_value[sl] = axes[level], values[level]

    # Levels above: world boxes bounding the children's (the frame level's boxes mapped to the world).
    corners = np.stack(np.meshgrid([0, 1], [0, 1], [0, 1], indexing="ij"), -1).reshape(8, 3)
    g0 = nf - 1
    c_lo, c_hi = lo_all[g0 : g0 + nf], hi_all[g0 : g0 + nf]
    box_pts = np.where(corners[None] == 0, c_lo[:, None], c_hi[:, None])  # [nf, 8, 3] in each frame
    world_pts = np.where(framed[:, None, None],
                         scale[:, None, None] * np.einsum("nab,nkb->nka", rot, box_pts) + shift[:, None], box_pts)
    full = count_all[g0 : g0 + nf] > 0
    up_lo = np.where(full[:, None], world_pts.min(axis=1), np.inf)
    up_hi = np.where(full[:, None], world_pts.max(axis=1), -np.inf)
    for level in range(f - 1, -1, -1):
        up_lo = up_lo.reshape(-1, 2, 3).min(axis=1)
        up_hi = up_hi.reshape(-1, 2, 3).max(axis=1)
        g0 = 2**level - 1
        cnt = count_all[2 * g0 + 1 : 2 * g0 + 1 + 2 ** (level + 1)].reshape(-1, 2).sum(axis=1)
        count_all[g0 : g0 + 2**level] = cnt
        ok = (cnt > 0)[:, None]
        lo_all[g0 : g0 + 2**level] = np.where(ok, up_lo, 0.0)
        hi_all[g0 : g0 + 2**level] = np.where(ok, up_hi, 0.0)

    # Candidate sets: kept, or re-chosen around the boxes (torn subtrees always).
    cand_new = cand.copy()
    first = 2**f - 1
    rows = np.arange(cand.shape[0])
    level_of = np.floor(np.log2(rows + first + 1)).astype(int)
    sub_of = (rows + first + 1) // 2 ** (level_of - f) - nf
    redo = np.ones_like(rows, bool) if recompute_candidates else torn[sub_of]
    redo &= count_all[first + rows] > 0
    if redo.any():
        idx = np.flatnonzero(alive)
        kd = cKDTree(new[idx])
        center = 0.5 * (lo_all[first + rows[redo]] + hi_all[first + rows[redo]])
        frame = framed[sub_of[redo]]
        j = sub_of[redo]
        center = np.where(frame[:, None],  # framed boxes: their centre in the world
                          scale[j, None] * np.einsum("nab,nb->na", rot[j], center) + shift[j], center)
        k = min(kc, idx.size)
        _, near = kd.query(center, k=k, workers=-1)
        near = idx[np.reshape(near, (-1, k))]
        cand_new[redo] = np.concatenate([near, np.full((near.shape[0], kc - k), cap)], axis=1)

    valid &= count_all > 0
    report = dict(subtrees=int(nf), torn=int(torn.sum()), max_residual=float(residual.max() / spacing_world),
                  scale=unit, emptied=int(((count_all == 0) & (count_built > 0)).sum()))
    dtype = np.asarray(tree.lo).dtype
    frames = {}
    if framed.any():
        inv_rot = np.where(framed[:, None, None], np.transpose(rot, (0, 2, 1)) / scale[:, None, None], np.eye(3))
        inv_shift = np.where(framed[:, None], -np.einsum("nab,nb->na", inv_rot, shift), 0.0)
        frames = dict(frame_rot=jnp.asarray(inv_rot.astype(dtype)), frame_shift=jnp.asarray(inv_shift.astype(dtype)),
                      frame_level=f)
    return tree.replace(lo=jnp.asarray(lo_all.astype(dtype)), hi=jnp.asarray(hi_all.astype(dtype)),
                        count=jnp.asarray(count_all.astype(np.int32)), valid=jnp.asarray(valid),
                        perm=jnp.asarray(perm_new.astype(np.int32)),
                        split_axis=jnp.asarray(split_axis.astype(np.int32)),
                        split_value=jnp.asarray(split_value.astype(dtype)),
                        candidates=jnp.asarray(cand_new.astype(np.int32)),
                        spacing=jnp.asarray(spacing_world, dtype), **frames), report


__all__ = ["CarryContext", "carry_context", "carry_tree", "carry_tree_with_report", "held_points"]

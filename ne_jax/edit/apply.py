"""Applying an edit to a model's point state: ``apply_edit(points, edit) -> points``.

1. The edit's target (:func:`~ne_jax.edit.targets.edit_target`): new positions of the alive
   points, deletions as ``alive = False`` (capacity and indices unchanged).
2. Normals re-estimated with Open3D on the edited cloud (unoriented), then oriented by the IST
   (the sign that keeps each local frame's handedness, :mod:`ne_jax.edit.ist`), so an edited normal
   points to the same side of the surface as the original one did. Points whose neighbourhood did
   not move keep their normal (and so the identity IST), also next to a deletion.
3. The IST of every point. Editing an already edited state composes: the new IST maps the newest
   space to the previous one, and the stored IST (to the original space) is ``IST_old @ IST_new``.

Features and confidences (the model's parameters) are untouched: the edited state renders
zero-shot with the same colour model, with the ``ist`` effect declared
(:func:`edited_render_config`), and can be fine-tuned.

Differentiable editing: :func:`plan_edit` fixes the discrete choices (deletions, IST frame pairs and
neighbours, the edited normals) on the host; :func:`edited_points` then maps new positions to the
edited state in pure JAX, differentiable w.r.t. the positions (and whatever parameters produced
them). Rebuild the K-D tree on the host between gradient steps; the tree is constant under ``grad``.

What the edits of one unedited cloud share (the IST's neighbour table, the carried tree's validity
limit) is an :class:`EditContext`: made once by :func:`edit_context`, held by the caller (the
viewer's session, a sweep of edits, a morph) and passed back to every edit; an edit without one
computes it on the spot.
"""

from __future__ import annotations

import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from ne_jax.edit.ist import ISTConfig, ISTPlan, NeighborTable, ist_from_plan, ist_neighbors, plan_ist
from ne_jax.edit.targets import EditSource, edit_target
from ne_jax.geometry.carry import CarryContext, carry_context, held_points
from ne_jax.geometry.points import PointState
from ne_jax.pointcloud.normals import NormalConfig, estimate_normals
from ne_jax.render.renderer import PointScene, RenderConfig


@dataclasses.dataclass(frozen=True)
class EditConfig:
    """Static settings of :func:`apply_edit`."""

    ist: ISTConfig = ISTConfig()
    """How the IST is computed."""
    normals: NormalConfig = NormalConfig(orient="none")
    """Normal estimation on the edited cloud (orientation comes from the IST, not from cameras)."""
    reestimate_normals: bool = True
    """Off: every point keeps its original normal, unrotated (an analysis switch: what the normals
    re-estimated on the edited cloud contribute; the IST is still computed from them)."""
    rebuild_tree: bool = False
    """The edited scene's K-D tree (:meth:`~ne_jax.render.renderer.PointScene.edited`): off, the
    trained tree is carried, its partition and candidate sets kept and its boxes moved with their
    points (:mod:`ne_jax.geometry.carry`); on, a new tree is built on the edited cloud (the paper)."""
    tear_factor: float = 2.0
    """Carried tree: a subtree whose points its best similarity fit misses by more than this many
    point spacings is torn (rebuilt locally on the edited positions)."""

    def __post_init__(self):
        if not self.tear_factor > 0:
            raise ValueError(f"EditConfig.tear_factor: expected a value > 0, found {self.tear_factor}")

    def scene(self, base: PointScene, points: PointState, render: RenderConfig,
              context: EditContext | None = None) -> PointScene:
        """The edited scene of ``points`` (an edit of ``base.points``) with this config's tree;
        ``context``: :func:`edit_context` of ``base`` (its carry context), if held."""
        carry = None if context is None else context.carry
        return base.edited(points, render, carry=not self.rebuild_tree, tear_factor=self.tear_factor, context=carry)


@dataclasses.dataclass(frozen=True, eq=False)
class EditContext:
    """What the edits of one unedited cloud share (host side), made once by :func:`edit_context`
    and passed back to :func:`apply_edit` and :meth:`EditConfig.scene` for every edit of it.

    Attributes:
        neighbors: the IST's neighbour table of the cloud for the points alive after the edits
            (:func:`~ne_jax.edit.ist.ist_neighbors`); an edit that deletes other points makes its own.
        carry: the carried tree's rest (:func:`~ne_jax.geometry.carry.carry_context`), or ``None``
            (no scene given, or ``rebuild_tree``): a carry then computes it on the spot.
    """

    neighbors: NeighborTable
    carry: CarryContext | None = None

    def for_alive(self, cfg: EditConfig, alive) -> EditContext:
        """This context for edits that leave ``alive [C]`` bool alive: itself when its neighbour
        table was made for them, else with a new table (the carry context is kept)."""
        table = ist_neighbors(cfg.ist, self.neighbors.xyz0, alive, self.neighbors)
        return self if table is self.neighbors else dataclasses.replace(self, neighbors=table)


@struct.dataclass
class EditPlan:
    """What :func:`edited_points` holds fixed: ``alive [C]`` after the edit, the edited normals
    ``normal [C, 3]`` (unoriented, Open3D) and the IST plan."""

    alive: jax.Array
    normal: jax.Array
    ist: ISTPlan


def _edited_normals(cfg: EditConfig, xyz: np.ndarray, alive: np.ndarray) -> np.ndarray:
    normals = np.zeros(xyz.shape, np.float32)
    idx = np.flatnonzero(alive)
    normals[idx] = estimate_normals(cfg.normals, xyz[idx])
    return normals


def edit_context(cfg: EditConfig, points: PointState, scene: PointScene | None = None,
                 render: RenderConfig | None = None, alive=None) -> EditContext:
    """The :class:`EditContext` of edits of ``points`` (the unedited state every edit starts from).

    Args:
        cfg: the edits' config (its ``ist.candidates``, ``rebuild_tree``).
        points: the unedited point state.
        scene, render: the unedited scene whose tree the edits carry and its render config (its
            ``kdtree``); without them, or with ``cfg.rebuild_tree``, no carry context is made.
        alive: ``[C]`` bool the points alive after the edits (default ``points.alive``: edits that
            move points and delete none).
    """
    alive = np.asarray(points.alive if alive is None else alive, bool)
    table = ist_neighbors(cfg.ist, points.xyz, alive)
    carry = None
    if scene is not None and render is not None and not cfg.rebuild_tree:
        if scene.rest_xyz is None:  # a built tree: the scene's points are its rest (PointScene.edited)
            carry = carry_context(scene.points.xyz, held_points(scene.tree), render.kdtree)
        else:
            carry = carry_context(scene.rest_xyz, scene.rest_alive, render.kdtree)
    return EditContext(neighbors=table, carry=carry)


def plan_edit(cfg: EditConfig, points: PointState, xyz, deleted, context: EditContext | None = None) -> EditPlan:
    """Host-side choices for the edit ``points -> (xyz [C, 3], deleted [C])``; ``context``:
    :func:`edit_context` of ``points``, if held."""
    xyz = np.asarray(xyz)
    alive = np.asarray(points.alive) & ~np.asarray(deleted, bool)
    xyz0, normal0, conf = np.asarray(points.xyz), np.asarray(points.normal), np.asarray(points.confidence)
    normals = _edited_normals(cfg, xyz, alive)
    # a point whose neighbourhood did not move keeps its normal: re-estimating it next to a deletion
    # would only tilt it (a truncated neighbourhood), and its IST must stay the identity
    table = ist_neighbors(cfg.ist, xyz0, alive, None if context is None else context.neighbors)
    nbrs, used = table.neighbors, table.valid
    moved = np.any(xyz != xyz0, axis=1)
    still = alive & ~moved & ~np.any(moved[nbrs] & used, axis=1)
    normals[still] = normal0[still]
    plan = plan_ist(cfg.ist, xyz0, normal0, xyz, normals, alive, conf, neighbors=table)
    return EditPlan(alive=jnp.asarray(alive), normal=jnp.asarray(normals, points.normal.dtype), ist=plan)


def edited_points(cfg: EditConfig, plan: EditPlan, points: PointState, xyz: jax.Array) -> tuple[PointState, dict]:
    """The edited state for new positions ``xyz [C, 3]`` under a fixed ``plan`` (pure JAX,
    differentiable in ``xyz``): ``(points, counts)``. Dead slots keep their old positions."""
    xyz = jnp.where(plan.alive[:, None], jnp.asarray(xyz, points.xyz.dtype), points.xyz)
    ist, sign, counts = ist_from_plan(cfg.ist, plan.ist, points.xyz, points.normal, xyz, plan.normal)
    composed = jnp.einsum("cij,cjk->cik", points.ist, ist)
    oriented = sign[:, None] * plan.normal if cfg.reestimate_normals else points.normal
    normal = jnp.where(plan.alive[:, None], oriented, 0.0)
    return points.replace(xyz=xyz, alive=plan.alive, normal=normal, ist=composed), counts


def apply_edit(points: PointState, edit: EditSource, cfg: EditConfig = EditConfig(),
               context: EditContext | None = None) -> PointState:
    """Move and delete points by ``edit``: :func:`apply_edit_with_report` without its report."""
    return apply_edit_with_report(points, edit, cfg, context)[0]


def apply_edit_with_report(points: PointState, edit: EditSource, cfg: EditConfig = EditConfig(),
                           context: EditContext | None = None) -> tuple[PointState, dict]:
    """Move and delete points by ``edit`` (an :class:`~ne_jax.edit.deformations.Edit`, a ``.npy`` or
    ``.ply`` file, an array, or a sequence of them; see :mod:`ne_jax.edit.targets`), re-estimate the
    normals and compute the IST. Features and confidences are unchanged. ``context``:
    :func:`edit_context` of ``points``, if held.

    Returns ``(points, report)``; ``report``: ``moved`` (alive points whose position changed),
    ``deleted``, ``alive``, the IST counts ``good``/``filled``/``identity`` and ``seconds``.

    Raises:
        EditError: a bad edit (named source, expectation, what was found).
        ValueError: a ``context`` made for another cloud or config.
    """
    t0 = time.perf_counter()
    target = edit_target(points, edit)
    plan = plan_edit(cfg, points, target.xyz, target.deleted, context)
    edited, counts = edited_points(cfg, plan, points, jnp.asarray(target.xyz, points.xyz.dtype))
    before = np.asarray(points.alive)
    moved = before & ~target.deleted & np.any(target.xyz != np.asarray(points.xyz), axis=1)
    report = dict(moved=int(moved.sum()), deleted=int(target.deleted.sum()),
                  alive=int(np.asarray(edited.alive).sum()), **{k: int(v) for k, v in counts.items()},
                  seconds=round(time.perf_counter() - t0, 3))
    return edited, report


def edited_render_config(render: RenderConfig, ist: bool = True) -> RenderConfig:
    """The render config of an edited model: the ``ist`` effect declared (or not, for the "without
    IST" variant). The colour model's parameters are the same either way."""
    return render.with_effects(ist=ist)


__all__ = ["EditConfig", "EditContext", "EditPlan", "apply_edit", "apply_edit_with_report", "edit_context",
           "edited_points", "edited_render_config", "plan_edit"]

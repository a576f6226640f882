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
"""

from __future__ import annotations

import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from ne_jax.edit.ist import ISTConfig, ISTPlan, ist_from_plan, ist_neighbors, plan_ist
from ne_jax.edit.targets import EditSource, edit_target
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
    compute_ist: bool = True
    """Off: the IST is left as it was (the "without IST" variant renders with the effect off anyway)."""
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

    def scene(self, base: PointScene, points: PointState, render: RenderConfig) -> PointScene:
        """The edited scene of ``points`` (an edit of ``base.points``) with this config's tree."""
        return base.edited(points, render, carry=not self.rebuild_tree, tear_factor=self.tear_factor)


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


def plan_edit(cfg: EditConfig, points: PointState, xyz, deleted) -> EditPlan:
    """Host-side choices for the edit ``points -> (xyz [C, 3], deleted [C])``."""
    xyz = np.asarray(xyz)
    alive = np.asarray(points.alive) & ~np.asarray(deleted, bool)
    xyz0, normal0, conf = np.asarray(points.xyz), np.asarray(points.normal), np.asarray(points.confidence)
    normals = _edited_normals(cfg, xyz, alive)
    # a point whose neighbourhood did not move keeps its normal: re-estimating it next to a deletion
    # would only tilt it (a truncated neighbourhood), and its IST must stay the identity
    nbrs, used = ist_neighbors(cfg.ist, xyz0, alive)
    moved = np.any(xyz != xyz0, axis=1)
    still = alive & ~moved & ~np.any(moved[nbrs] & used, axis=1)
    normals[still] = normal0[still]
    plan = plan_ist(cfg.ist, xyz0, normal0, xyz, normals, alive, conf, neighbors=(nbrs, used))
    return EditPlan(alive=jnp.asarray(alive), normal=jnp.asarray(normals, points.normal.dtype), ist=plan)


def edited_points(cfg: EditConfig, plan: EditPlan, points: PointState, xyz: jax.Array) -> tuple[PointState, dict]:
    """The edited state for new positions ``xyz [C, 3]`` under a fixed ``plan`` (pure JAX,
    differentiable in ``xyz``): ``(points, counts)``. Dead slots keep their old positions."""
    xyz = jnp.where(plan.alive[:, None], jnp.asarray(xyz, points.xyz.dtype), points.xyz)
    if not cfg.compute_ist:
        normal = plan.normal if cfg.reestimate_normals else jnp.where(plan.alive[:, None], points.normal, 0.0)
        return points.replace(xyz=xyz, alive=plan.alive, normal=normal), {}
    ist, sign, counts = ist_from_plan(cfg.ist, plan.ist, points.xyz, points.normal, xyz, plan.normal)
    composed = jnp.einsum("cij,cjk->cik", points.ist, ist)
    oriented = sign[:, None] * plan.normal if cfg.reestimate_normals else points.normal
    normal = jnp.where(plan.alive[:, None], oriented, 0.0)
    return points.replace(xyz=xyz, alive=plan.alive, normal=normal, ist=composed), counts


def apply_edit(points: PointState, edit: EditSource, cfg: EditConfig = EditConfig(),
               report: dict | None = None) -> PointState:
    """Move and delete points by ``edit`` (an :class:`~ne_jax.edit.deformations.Edit`, a ``.npy`` or
    ``.ply`` file, an array, or a sequence of them; see :mod:`ne_jax.edit.targets`), re-estimate the
    normals and compute the IST. Features and confidences are unchanged.

    ``report`` (optional dict) receives: ``moved`` (alive points whose position changed),
    ``deleted``, ``alive``, the IST counts ``good``/``filled``/``identity`` and ``seconds``.

    Raises:
        EditError: a bad edit (named source, expectation, what was found).
    """
    t0 = time.perf_counter()
    target = edit_target(points, edit)
    plan = plan_edit(cfg, points, target.xyz, target.deleted)
    edited, counts = edited_points(cfg, plan, points, jnp.asarray(target.xyz, points.xyz.dtype))
    if report is not None:
        before = np.asarray(points.alive)
        moved = before & ~target.deleted & np.any(target.xyz != np.asarray(points.xyz), axis=1)
        report.update(moved=int(moved.sum()), deleted=int(target.deleted.sum()),
                      alive=int(np.asarray(edited.alive).sum()), **{k: int(v) for k, v in counts.items()},
                      seconds=round(time.perf_counter() - t0, 3))
    return edited


def edited_render_config(render: RenderConfig, ist: bool = True) -> RenderConfig:
    """The render config of an edited model: the ``ist`` effect declared (or not, for the "without
    IST" variant). The colour model's parameters are the same either way."""
    return render.with_effects(ist=ist)


__all__ = ["EditConfig", "EditPlan", "apply_edit", "edited_points", "edited_render_config", "plan_edit"]

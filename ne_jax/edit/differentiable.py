"""Differentiable editing: ``jax.grad`` of an image loss w.r.t. the parameters of a deformation.

The chain, all in JAX and differentiated end to end::

    theta --deform--> xyz [C, 3] --edited_points (IST under a fixed plan)--> PointState
          --render_rays (fixed K-D tree)--> rgb [R, 3] --MSE--> loss

``deform(theta, xyz [C, 3]) -> [C, 3]`` is any deformation written in ``jax.numpy`` whose parameters
``theta`` are a pytree of float arrays (a scalar angle, a vector, a dict...); :func:`bend_deformation`
wraps :func:`~ne_jax.edit.deformations.bend_points` with the angle as ``theta``.

What is held fixed inside a gradient (the *topology*, :class:`EditTopology`): the discrete choices
of the edit (:func:`~ne_jax.edit.apply.plan_edit`: deletions, the IST frame pairs and neighbours)
and the K-D tree of the edited cloud (its permutation, partition, candidate sets and point spacing).
Positions reach the render through the KNN distances and, by default, through the node boxes, which
are translated with their points (:func:`follow_boxes`: the segments' end points move with the
geometry; with the boxes frozen the density could not move and the gradient would see only the KNN
weights); the IST depends on them through the frames of the moved points. The loss is smooth in
``theta`` between discrete events that the fixed topology does not remove (a point entering a
sample's K nearest, a voxel becoming minimal for a ray). :func:`recover_parameter` re-plans and
rebuilds the tree on the host every few steps at the current estimate, so the topology follows the
descent piecewise.

Edited normals (``normals=``): ``"deform"`` (default) takes the edited point normals through the
deformation, ``n' = normalize(J^-T n)`` with ``J = d deform / d xyz`` at the original point, so the
IST (whose rotation is mostly set by the normal) depends on ``theta`` completely. ``"plan"`` keeps
the normals :func:`~ne_jax.edit.apply.plan_edit` estimated with Open3D at the plan's estimate, as
:func:`~ne_jax.edit.apply.apply_edit` does; then only the tangent frame vectors carry the IST's
dependence on ``theta`` (a partial derivative, exact again after each re-plan).

The render config must declare the ``ist`` effect (``render_cfg.with_effects(ist=True)``, see
:func:`~ne_jax.edit.apply.edited_render_config`); otherwise the IST is absent from the compiled
graph and :func:`make_edit_loss` raises.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from typing import Any, Literal

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct
from jax.flatten_util import ravel_pytree

from ne_jax.compiles import count_compiles
from ne_jax.data.rays import Rays
from ne_jax.edit.apply import EditConfig, EditContext, EditPlan, edit_context, edited_points, plan_edit
from ne_jax.edit.deformations import bend_points, jacobian_normals
from ne_jax.geometry.capacity import Capacities, grow
from ne_jax.geometry.kdtree import KDTree, build_tree
from ne_jax.geometry.points import PointState
from ne_jax.render.renderer import PointScene, RenderConfig, render_rays

Deformation = Callable[[Any, jax.Array], jax.Array]
"""``deform(theta, xyz [C, 3]) -> [C, 3]``, pure ``jax.numpy``, differentiable in ``theta``."""


def bend_deformation(center, along, toward, length: float) -> Deformation:
    """The bend of :func:`~ne_jax.edit.deformations.bend_points` with the angle (radians) as
    ``theta``: ``deform(angle, xyz) = bend_points(xyz, center, along, toward, angle, length)``."""
    def deform(theta, xyz):
        return bend_points(xyz, center, along, toward, theta, length)
    return deform


@struct.dataclass
class EditTopology:
    """What a gradient holds fixed: the edit's plan and the K-D tree of the edited cloud, both built
    on the host at one estimate ``theta`` (:meth:`EditLoss.topology`), and the buffer sizes the
    edited scene renders with (static; grown by :func:`recover_parameter` when a render loses
    segments)."""

    plan: EditPlan
    tree: KDTree
    xyz: jax.Array | None = None
    """``[C, 3]`` edited positions the tree was built on (the reference of :func:`follow_boxes`)."""
    capacities: Capacities = struct.field(pytree_node=False, default=Capacities())


def _level_bounds(tree: KDTree, xyz: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Per-node bounding boxes ``[2P-1, 3]`` (heap order) of the points ``xyz`` assigned to each
    node by the tree's fixed permutation; a huge finite value in empty nodes."""
    big = jnp.asarray(1e30, xyz.dtype)
    ok = (tree.perm < xyz.shape[0])[:, None]
    pts = xyz[jnp.minimum(tree.perm, xyz.shape[0] - 1)]
    p_lo, p_hi = jnp.where(ok, pts, big), jnp.where(ok, pts, -big)
    los, his = [], []
    for level in range(tree.depth + 1):
        shape = (2**level, 2 ** (tree.depth - level), 3)
        los.append(jnp.min(p_lo.reshape(shape), axis=1))
        his.append(jnp.max(p_hi.reshape(shape), axis=1))
    return jnp.concatenate(los), jnp.concatenate(his)


def follow_boxes(tree: KDTree, xyz: jax.Array, xyz_ref: jax.Array) -> KDTree:
    """The tree with its node boxes moved with the points, topology fixed: each non-empty node's box
    is translated, face by face, by how far its points' bounding box moved from ``xyz_ref`` (the
    positions the tree was built on) to ``xyz`` (both ``[C, 3]``). Exact at ``xyz = xyz_ref``; a
    first-order stand-in for a rebuild elsewhere (the partition planes, candidate sets and spacing
    stay). Differentiable in ``xyz``: the segments' end points, hence the densities' extents, follow
    the points, which the KNN weights alone would not tell the gradient."""
    lo, hi = _level_bounds(tree, xyz)
    lo_ref, hi_ref = _level_bounds(tree, jax.lax.stop_gradient(xyz_ref))
    full = (tree.count > 0)[:, None]
    return tree.replace(lo=tree.lo + jnp.where(full, lo - lo_ref, 0.0), hi=tree.hi + jnp.where(full, hi - hi_ref, 0.0))


def deformed_normals(deform: Deformation, theta, xyz: jax.Array, normal: jax.Array) -> jax.Array:
    """Normals carried by ``deform(theta, .)`` (:func:`~ne_jax.edit.deformations.jacobian_normals`)
    at ``xyz [C, 3]``. ``[C, 3]``."""
    return jacobian_normals(lambda x: deform(theta, x), xyz, normal)


@dataclasses.dataclass(frozen=True)
class EditLoss:
    """A bundle of pure functions for one ``(render config, deformation)`` (:func:`make_edit_loss`).

    Attributes:
        render_cfg: the render config (``ist`` effect declared).
        edit_cfg: the edit's static settings (IST configuration).
        deform: the deformation ``deform(theta, xyz) -> xyz'``.
        normals: ``"deform"`` or ``"plan"`` (module docstring).
        mode: ``"forward"`` or ``"reverse"`` differentiation (:func:`make_edit_loss`).
        boxes: whether the tree's boxes follow the points (:func:`follow_boxes`).
        scene: ``(theta, points, topology) -> PointScene``, the edited scene (pure JAX).
        loss: ``(theta, params, points, topology, rays, targets, background) -> (mse, RenderOut)``.
        value_and_grad: ``jax.jit`` of ``loss``'s value and gradient w.r.t. ``theta``:
            ``-> ((mse, RenderOut), grad)``. Compiles once per shape of its inputs; a rebuilt
            topology of the same alive set has the same shapes and does not recompile.
    """

    render_cfg: RenderConfig
    edit_cfg: EditConfig
    deform: Deformation
    normals: str
    mode: str
    boxes: bool
    scene: Callable
    loss: Callable
    value_and_grad: Callable

    def topology(self, points: PointState, theta, deleted=None,
                 capacities: Capacities = Capacities(), context: EditContext | None = None) -> EditTopology:
        """Host side: plan the edit ``points -> deform(theta, points.xyz)`` (deleting ``deleted [C]``,
        decided in the original space and independent of ``theta``) and build the K-D tree of the
        edited cloud at this estimate, to render with ``capacities``. ``context``:
        :func:`~ne_jax.edit.apply.edit_context` of ``points`` for these deletions, held across
        re-plans (made on the spot when ``None``)."""
        xyz = np.asarray(self.deform(theta, points.xyz))
        deleted = np.zeros(points.capacity, bool) if deleted is None else np.asarray(deleted, bool)
        plan = plan_edit(self.edit_cfg, points, xyz, deleted, context)
        edited = self.scene(theta, points, EditTopology(plan=plan, tree=None))
        tree = build_tree(np.asarray(edited.points.xyz), np.asarray(edited.points.alive), self.render_cfg.kdtree)
        return EditTopology(plan=plan, tree=tree, xyz=edited.points.xyz, capacities=capacities)


def make_edit_loss(render_cfg: RenderConfig, deform: Deformation, edit_cfg: EditConfig = EditConfig(),
                   normals: Literal["deform", "plan"] = "deform",
                   mode: Literal["forward", "reverse"] = "forward", boxes: bool = True) -> EditLoss:
    """The image loss of an edit as a function of the deformation's parameters (an :class:`EditLoss`).

    ``loss(theta, params, points, topology, rays, targets, background)`` maps ``theta`` to edited
    positions ``deform(theta, points.xyz)``, to the edited state (:func:`~ne_jax.edit.apply.edited_points`:
    IST under ``topology.plan``), renders ``rays`` (``[R]``) through ``topology.tree`` with colour
    model ``params`` and returns the mean squared error against ``targets [R, 3]`` (over rays and
    channels) and the :class:`~ne_jax.render.renderer.RenderOut` (check its ``lost``).
    ``points`` is the *unedited* model's state.

    ``mode``: how ``value_and_grad`` differentiates. ``"forward"`` (default): one JVP per scalar in
    ``theta`` (``jax.jvp`` vmapped over the basis), the cheap way for a few deformation parameters
    (no reverse-mode residuals of the render are stored). ``"reverse"``: ``jax.value_and_grad``
    (the better choice for many parameters). Both give the same numbers (tested).

    ``boxes``: move the tree's boxes with the points (:func:`follow_boxes`; default). Off, positions
    reach the render only through the KNN weights inside the fixed voxels: the density stays where
    the tree was built, and the gradient says little about where the geometry should go.

    Raises:
        ValueError: ``render_cfg`` does not declare the ``ist`` effect (or the colour model does not
            read it), or ``normals`` is not ``"deform"``/``"plan"``.
    """
    if not render_cfg.shading.effects.uses_ist:
        raise ValueError("make_edit_loss: expected a render config that declares the IST effect "
                         "(render_cfg.with_effects(ist=True), with a view-dependent colour head), found "
                         f"{render_cfg.shading.effects}")
    if normals not in ("deform", "plan"):
        raise ValueError(f"make_edit_loss: normals must be 'deform' or 'plan', found {normals!r}")
    if mode not in ("forward", "reverse"):
        raise ValueError(f"make_edit_loss: mode must be 'forward' or 'reverse', found {mode!r}")

    def scene(theta, points: PointState, topology: EditTopology) -> PointScene:
        xyz = deform(theta, points.xyz)
        plan = topology.plan
        if normals == "deform":
            n = deformed_normals(deform, theta, points.xyz, points.normal)
            plan = plan.replace(normal=jnp.where(plan.alive[:, None], n, 0.0).astype(points.normal.dtype))
        edited, _ = edited_points(edit_cfg, plan, points, xyz)
        tree = topology.tree
        if boxes and tree is not None:
            tree = follow_boxes(tree, edited.xyz, topology.xyz)
        return PointScene(points=edited, tree=tree, capacities=topology.capacities)

    def loss(theta, params, points, topology, rays: Rays, targets, background):
        out = render_rays(render_cfg, params, scene(theta, points, topology), rays, background)
        return jnp.mean((out.rgb - targets) ** 2), out

    def forward_value_and_grad(theta, *args):
        flat, unravel = ravel_pytree(theta)

        def f(x):
            return loss(unravel(x), *args)

        def along(v):
            (value, out), (dvalue, _) = jax.jvp(f, (flat,), (v,))
            return value, out, dvalue

        value, out, grad = jax.vmap(along)(jnp.eye(flat.size, dtype=flat.dtype))
        return (value[0], jax.tree_util.tree_map(lambda a: a[0], out)), unravel(grad)

    vg = jax.value_and_grad(loss, has_aux=True) if mode == "reverse" else forward_value_and_grad
    return EditLoss(render_cfg=render_cfg, edit_cfg=edit_cfg, deform=deform, normals=normals, mode=mode, boxes=boxes,
                    scene=scene, loss=loss, value_and_grad=jax.jit(vg))


@dataclasses.dataclass
class Trajectory:
    """The descent of :func:`recover_parameter`, one entry per evaluated step (``steps + 1``: the
    last entry is the final estimate's loss, with its gradient, after the last update).

    Attributes:
        theta: estimates (numpy, ``theta``'s structure as a flat float array per step).
        loss: MSE at each estimate (under the topology in force at that step).
        grad: gradient w.r.t. ``theta`` at each estimate.
        rebuilt: whether the plan and tree were rebuilt at that step (at that estimate).
        lost: what the render lost at that step, after any growth
            (:class:`~ne_jax.geometry.capacity.LostCounts` as a dict; ``total`` 0: complete).
        grown: whether the render's capacities were grown at that step (a recompilation).
        seconds: wall time since the start, at the end of each step.
        compiles: compilations of the loss's ``value_and_grad`` over the descent.
        capacities: the capacities in force at the end.
        problem: the :class:`EditLoss` (its compiled ``value_and_grad`` warm).
    """

    theta: list = dataclasses.field(default_factory=list)
    loss: list = dataclasses.field(default_factory=list)
    grad: list = dataclasses.field(default_factory=list)
    rebuilt: list = dataclasses.field(default_factory=list)
    lost: list = dataclasses.field(default_factory=list)
    grown: list = dataclasses.field(default_factory=list)
    seconds: list = dataclasses.field(default_factory=list)
    compiles: int = 0
    capacities: Capacities | None = None
    problem: EditLoss | None = None

    def to_dict(self) -> dict:
        """JSON-ready lists."""
        def flat(xs):
            return [np.asarray(x, np.float64).ravel().tolist() for x in xs]

        return {"theta": flat(self.theta), "loss": [float(v) for v in self.loss], "grad": flat(self.grad),
                "rebuilt": [bool(v) for v in self.rebuilt], "lost": list(self.lost),
                "grown": [bool(v) for v in self.grown],
                "seconds": [round(float(v), 3) for v in self.seconds],
                "compiles": int(self.compiles)}


def recover_parameter(problem: EditLoss, params, points: PointState, theta0, rays: Rays, targets, background, *,
                      deleted=None, steps: int = 40, optimizer: optax.GradientTransformation | None = None,
                      learning_rate: float = 0.05, rebuild_every: int = 5, max_grow: int = 3,
                      capacities: Capacities = Capacities(),
                      callback: Callable[[int, Trajectory], None] | None = None) -> tuple[Any, Trajectory]:
    """Gradient descent on ``theta`` to fit the edited model's render of ``rays`` to ``targets``.

    Every ``rebuild_every`` steps (and at the start) the edit's plan and the K-D tree are rebuilt on
    the host at the current estimate (:meth:`EditLoss.topology`); in between, and inside every
    gradient, that topology is held constant: the gradient is that of the loss under the current
    topology, not of the (piecewise constant in the topology) true loss. The edited scene renders
    with ``capacities``; a render that loses segments is re-run with them grown
    (:func:`~ne_jax.geometry.capacity.grow`; one more compilation each, at most ``max_grow`` times),
    and later steps keep the grown ones; losses that remain are recorded in the trajectory.

    Args:
        problem: from :func:`make_edit_loss`.
        params: colour-model parameters; ``points``: the unedited point state.
        theta0: the starting estimate (pytree of floats, float32).
        rays, targets, background: ``[R]`` rays, ``[R, 3]`` target colours, ``[3]`` or ``[R, 3]``.
        deleted: ``[C]`` bool points the edit deletes (independent of ``theta``), or ``None``.
        steps: optimiser updates.
        optimizer: an optax transformation (default ``optax.adam(learning_rate)``).
        rebuild_every: steps between re-plans/tree rebuilds (``0``: only at the start).
        callback: called as ``callback(step, trajectory)`` after each evaluated step.

    Returns:
        ``(theta, trajectory)``: the final estimate and the :class:`Trajectory`.
    """
    optimizer = optax.adam(learning_rate) if optimizer is None else optimizer
    theta = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float32), theta0)
    opt_state = optimizer.init(theta)
    traj = Trajectory()
    t0 = time.perf_counter()
    targets = jnp.asarray(targets)
    background = jnp.asarray(background)
    topology = None
    fn = problem.value_and_grad
    # every re-plan edits the same cloud with the same deletions: its neighbour table is made once
    kept = np.asarray(points.alive) if deleted is None else np.asarray(points.alive) & ~np.asarray(deleted, bool)
    context = edit_context(problem.edit_cfg, points, alive=kept)
    for step in range(steps + 1):
        rebuild = topology is None or (rebuild_every > 0 and step % rebuild_every == 0)
        if rebuild:
            topology = problem.topology(points, theta, deleted, capacities, context)
        with count_compiles() as compiled:  # around fn only: topology and updates compile eager operations
            (value, out), grad = fn(theta, params, points, topology, rays, targets, background)
        traj.compiles += compiled.count
        grown = False
        for _ in range(max_grow):
            bigger = grow(capacities, out.lost)
            if bigger is None:
                break
            capacities, grown = bigger, True
            topology = topology.replace(capacities=capacities)
            with count_compiles() as compiled:
                (value, out), grad = fn(theta, params, points, topology, rays, targets, background)
            traj.compiles += compiled.count
        traj.theta.append(np.asarray(ravel_pytree(theta)[0]))
        traj.loss.append(float(value))
        traj.grad.append(np.asarray(ravel_pytree(grad)[0]))
        traj.rebuilt.append(bool(rebuild))
        traj.lost.append(out.lost.counts().as_dict())
        traj.grown.append(grown)
        traj.seconds.append(time.perf_counter() - t0)
        if callback is not None:
            callback(step, traj)
        if step == steps:
            break
        updates, opt_state = optimizer.update(grad, opt_state, theta)
        theta = optax.apply_updates(theta, updates)
    traj.capacities, traj.problem = capacities, problem
    return theta, traj


__all__ = ["Deformation", "EditLoss", "EditTopology", "Trajectory", "bend_deformation", "deformed_normals",
           "follow_boxes", "make_edit_loss", "recover_parameter"]

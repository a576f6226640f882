"""Differentiable editing (ne_jax.edit.differentiable): the gradient of an image loss w.r.t. a bend
angle is finite (identity angle, deletions), matches a central difference and reverse mode,
recovers a known angle from a nearby start, and the descent compiles once.

The scene: points on a vertical cylinder (bendable), features a smooth function of position, a
random colour model; the target is rendered by the same pipeline at a known angle. Every
evaluation renders the fixture's ``R`` rays, so the forward- and reverse-mode programs compile
once each for the whole file (rendering cost grows with ``R``: 128 rays keep the descent
well posed)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ne_jax.data.rays import Rays
from ne_jax.edit.apply import EditConfig
from ne_jax.edit.differentiable import (
    bend_deformation,
    follow_boxes,
    make_edit_loss,
    recover_parameter,
)
from ne_jax.edit.ist import ISTConfig
from ne_jax.geometry import PointState
from ne_jax.render.shading import init_color_model

from tests.mini_presets import tiny_caps, tiny_render

CFG = tiny_render().with_effects(ist=True)
CAPS = tiny_caps(frontier=32, max_segments=32, segments_per_ray=None)
N, CAP, R = 700, 768, 128
TRUE = 0.6  # radians
DEFORM = bend_deformation((0, 0, -0.8), (0, 0, 1), (1, 0, 0), 1.6)
EDIT = EditConfig(ist=ISTConfig(polar_iters=6, fill_passes=1))  # a smaller graph: faster compiles


@pytest.fixture(scope="module")
def world():
    rng = np.random.default_rng(0)
    z, phi = rng.uniform(-0.8, 0.8, N), rng.uniform(0, 2 * np.pi, N)
    xyz = np.stack([0.3 * np.cos(phi), 0.3 * np.sin(phi), z], 1)
    normal = np.stack([np.cos(phi), np.sin(phi), 0 * z], 1)
    pts = PointState.from_numpy(xyz, CAP, 32, normal=normal, key=jax.random.key(0))
    w = 2.0 * rng.normal(size=(3, 32))
    feature = np.sin(np.vstack([xyz, np.zeros((CAP - N, 3))]) @ w)
    pts = pts.replace(feature=jnp.asarray(feature, jnp.float32), conf_logit=jnp.full((CAP,), 2.0))
    params = init_color_model(CFG.shading, jax.random.key(1))
    aim = np.stack([rng.uniform(-0.5, 0.6, R), rng.uniform(-0.35, 0.35, R), rng.uniform(-0.8, 0.8, R)], 1)
    d = rng.normal(size=(R, 3))
    d[:, 2] *= 0.3
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    rays = Rays(origin=jnp.asarray(aim - 3 * d, jnp.float32), direction=jnp.asarray(d, jnp.float32),
                near=jnp.full((R,), 1.0), far=jnp.full((R,), 5.0))
    bg = jnp.ones(3)
    problem = make_edit_loss(CFG, DEFORM, EDIT)
    topo = problem.topology(pts, TRUE, capacities=CAPS)
    (_, out), _ = problem.value_and_grad(jnp.float32(TRUE), params, pts, topo, rays, jnp.zeros((R, 3)), bg)
    assert float(jnp.mean(out.opacity)) > 0.3 and int(jnp.sum(out.lost.count)) == 0
    return {"points": pts, "params": params, "rays": rays, "bg": bg, "problem": problem, "targets": out.rgb,
            "reverse": make_edit_loss(CFG, DEFORM, EDIT, mode="reverse")}


def _value_and_grad(w, theta, deleted=None, topo_at=None):
    p = w["problem"]
    topo = p.topology(w["points"], theta if topo_at is None else topo_at, deleted, capacities=CAPS)
    (value, out), grad = p.value_and_grad(jnp.float32(theta), w["params"], w["points"], topo, w["rays"],
                                          w["targets"], w["bg"])
    return float(value), float(grad), out, topo


@pytest.mark.parametrize("theta", [0.0, 0.3, TRUE])
def test_gradient_is_finite(world, theta):
    value, grad, _, _ = _value_and_grad(world, theta)
    assert np.isfinite(value) and np.isfinite(grad)
    if theta != TRUE:
        assert value > 0 and grad != 0.0


def test_gradient_matches_central_difference_and_reverse_mode(world):
    """At a fixed topology the loss is smooth between discrete events (a KNN or minimal-voxel switch
    as the points and boxes move; with many rays some fall within ``1e-4`` of most angles): on 8
    rays, with central differences at steps ``h`` and ``2h``. Where the two agree (no event inside
    ``[theta - 2h, theta + 2h]``) the forward-mode derivative must match them within 3% + 1e-4
    (float32 loss ~1e-2, ``h = 1e-4``: rounding ~1e-5); an event may spoil one of the five angles.
    The loss values come from the reverse-mode program (``jax.value_and_grad`` of ``loss``): at every
    angle its value equals the forward-mode value and its gradient the forward-mode JVP. The 8 rays
    are repeated to the fixture's ``R`` rays: the same loss (a mean over copies) and the same events,
    and both programs are the ones the other tests use (no compile for 8 rays)."""
    w, p = world, world["problem"]
    idx = np.tile(np.arange(8), R // 8)
    rays, targets = w["rays"].take(idx), w["targets"][idx]
    checked = 0
    for theta in (0.2, 0.35, 0.45, 0.55, 0.7):
        topo = p.topology(w["points"], theta, capacities=CAPS)
        args = (w["params"], w["points"], topo, rays, targets, w["bg"])
        (value, _), grad = p.value_and_grad(jnp.float32(theta), *args)
        (value_r, _), grad_r = w["reverse"].value_and_grad(jnp.float32(theta), *args)
        assert abs(float(value_r) - float(value)) <= 1e-6 * max(1.0, float(value))
        np.testing.assert_allclose(float(grad_r), float(grad), rtol=1e-3, atol=1e-6)

        def f(t, args=args):
            return float(w["reverse"].value_and_grad(jnp.float32(t), *args)[0][0])

        h = 1e-4
        fd1, fd2 = (f(theta + h) - f(theta - h)) / (2 * h), (f(theta + 2 * h) - f(theta - 2 * h)) / (4 * h)
        if abs(fd1 - fd2) <= 0.02 * max(abs(fd1), 1e-2):
            np.testing.assert_allclose(float(grad), fd1, rtol=0.03, atol=1e-4)
            checked += 1
    assert checked >= 4


def test_descent_recovers_the_angle_without_recompiling(world):
    """From 0.2 rad off the true angle, 8 Adam steps with the plan and tree rebuilt every 3 steps
    at least halve the angle error and the loss. Steps at a fixed tree and steps after a rebuild
    (same alive set, same shapes) reuse the executable the fixture compiled."""
    fn = world["problem"].value_and_grad
    before = fn._cache_size()
    start = TRUE - 0.2
    theta, traj = recover_parameter(world["problem"], world["params"], world["points"], start, world["rays"],
                                    world["targets"], world["bg"], steps=8, learning_rate=0.05, rebuild_every=3,
                                    capacities=CAPS)
    assert abs(float(theta) - TRUE) < 0.5 * abs(start - TRUE)
    assert traj.loss[-1] < 0.5 * traj.loss[0]
    assert len(traj.theta) == 9 and traj.rebuilt == [step % 3 == 0 for step in range(9)]
    assert all(np.isfinite(g).all() for g in traj.grad)
    assert before >= 1 and fn._cache_size() == before and traj.compiles == 0


def test_boxes_follow_points_exactly_at_the_reference(world):
    topo = world["problem"].topology(world["points"], 0.3, capacities=CAPS)
    follow = jax.jit(follow_boxes)  # one program for both calls
    same = follow(topo.tree, topo.xyz, topo.xyz)
    np.testing.assert_array_equal(np.asarray(same.lo), np.asarray(topo.tree.lo))
    shifted = follow(topo.tree, topo.xyz + jnp.array([0.1, 0.0, 0.0]), topo.xyz)
    full = np.asarray(topo.tree.count) > 0
    np.testing.assert_allclose(np.asarray(shifted.hi - topo.tree.hi)[full], [[0.1, 0, 0]] * int(full.sum()), atol=1e-6)


def test_render_config_must_declare_ist():
    with pytest.raises(ValueError, match="IST effect"):
        make_edit_loss(tiny_render(), DEFORM)


def test_gradient_with_deleted_points_is_finite_and_matches_reverse_mode(world):
    """With deleted points (and at the identity angle with them) the forward-mode gradient is finite;
    ``jax.value_and_grad`` through the same chain (``mode="reverse"``) gives its value and number
    (the JVP). Without deletions the two modes are compared in
    :func:`test_gradient_matches_central_difference_and_reverse_mode`."""
    w = world
    deleted = np.asarray(w["points"].xyz)[:, 2] > 0.5
    value, grad, _, topo = _value_and_grad(w, 0.3, deleted=deleted)
    assert not np.asarray(topo.plan.alive)[deleted].any()
    assert np.isfinite(value) and np.isfinite(grad) and grad != 0.0
    args = (w["params"], w["points"], topo, w["rays"], w["targets"], w["bg"])
    (value_r, _), grad_r = w["reverse"].value_and_grad(jnp.float32(0.3), *args)
    assert np.isfinite(float(grad_r))
    np.testing.assert_allclose(float(value_r), value, rtol=1e-6)
    np.testing.assert_allclose(float(grad_r), grad, rtol=1e-3, atol=1e-6)
    _, grad0, _, _ = _value_and_grad(w, 0.0, deleted=deleted)  # identity angle with deletions
    assert np.isfinite(grad0)

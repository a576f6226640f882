"""Stage training step (``make_train_step``, jitted: render with aux -> loss terms -> per-term and
total gradients -> Adam -> the non-finite guard) on the fixed tiny scene of ``render_scene.py`` and
on a cloud of coincident points.

Hard inputs: a batch in which every ray misses the scene (no segments at all), confidences at
+-30 logits (1e-13 and 1 - 1e-13), huge densities (density bias + 1e4, features x100: opaque at the
first sample), points that coincide (few distinct positions, each repeated).

Asserted: the step is applied (``ok``, every ``finite/*`` flag True), the loss and every updated
trainable, Adam moment and metric are finite. Reference (float64 numpy): when every ray misses, the
rendered colour is the background, so ``loss/photometric`` equals ``mean (bg - target)^2`` (float32
1e-6, float64 1e-12, relative) and the features get exactly zero gradient, so Adam leaves them
bit-identical. Refusal: a NaN target pixel (photometric term NaN), a NaN confidence logit of one
alive point (confidence term NaN) and a NaN feature in a dead slot (no term reads it: zero gradient,
the update is NaN) are each refused, named by their ``finite/*`` flag, and leave the state
bit-identical except ``skipped + 1``. (A NaN feature of a seen point is tests/train/test_step.py's.)

One compiled step for the whole file: every batch is ``N_RAYS`` rays, every cloud ``CAPACITY`` slots.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ne_jax.render.renderer import PointScene
from ne_jax.train import TrainConfig, init_train_state, make_train_step
from ne_jax.train.sampler import Batch

from .common import DTYPE, X64, aimed_rays, assert_finite, make_cloud, make_rays, make_state
from .render_scene import CAPACITY, CAPS, CFG, N_POINTS, N_RAYS, build, scene_inputs

TCFG = TrainConfig()
SCHEDULE_STEPS = 100
"""The length of the learning-rate schedule (a run's ``total_steps``)."""
STEP = make_train_step(TCFG, CFG, total_steps=SCHEDULE_STEPS)
PHOTO_RTOL = 1e-12 if X64 else 1e-6


@pytest.fixture(scope="module")
def inputs():
    return scene_inputs(0)


def make_train_state(scene: PointScene, params=None):
    state = init_train_state(TCFG, CFG, scene.points, jax.random.key(0), total_steps=SCHEDULE_STEPS)
    if params is not None:  # Adam's moments in the params' dtype
        state = state.replace(params=params,
                              opt_state=TCFG.optimizer(SCHEDULE_STEPS).init({"params": params, "points": state.points}))
    return state


def make_batch(rays, bg, seed=0):
    rng = np.random.default_rng(seed)
    target = np.concatenate([rng.uniform(size=(rays.num_rays, 3)), np.ones((rays.num_rays, 1))], 1)
    return Batch(rays=rays.replace(target=jnp.asarray(target, DTYPE)),
                 pixel=jnp.arange(rays.num_rays, dtype=jnp.int32),
                 in_band=jnp.zeros(rays.num_rays, bool), background=jnp.asarray(bg, DTYPE))


def step_ok(state, scene, batch):
    new, m = STEP(state, scene, batch)
    bad = [k for k, v in m.items() if k.startswith("finite/") and not bool(v)]
    assert bool(m["ok"]) and not bad, bad
    assert int(new.step) == int(state.step) + 1 and int(new.skipped) == int(state.skipped)
    assert_finite(m, "metrics ")
    assert_finite((new.params, new.points, new.opt_state), "state ")
    assert np.isfinite(float(m["loss/total"]))
    assert int(m["lost/frontier"]) == 0 and int(m["lost/slots"]) == 0 and int(m["lost/packing"]) == 0
    return new, m


def assert_refused(state, scene, batch, flag):
    new, m = STEP(state, scene, batch)
    assert not bool(m["ok"]) and not bool(m[flag]), flag
    assert int(new.skipped) == int(state.skipped) + 1 and int(new.step) == int(state.step)
    keep = lambda s: (s.params, s.points, s.opt_state, jax.random.key_data(s.key))  # noqa: E731
    for a, b in zip(jax.tree_util.tree_leaves(keep(state)), jax.tree_util.tree_leaves(keep(new))):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))  # nothing written (NaN == NaN here)
    return m


def test_every_ray_misses_the_scene(inputs):
    params, scene, rays, bg = build(inputs)
    far = 10.0 * np.ones((N_RAYS, 3)) + np.random.default_rng(2).normal(size=(N_RAYS, 3))
    away = far / np.linalg.norm(far, axis=1, keepdims=True)  # from outside, looking away from the cloud
    rays = make_rays(far, away, near=0.0, far=20.0)
    batch = make_batch(rays, bg)
    state = make_train_state(scene, params)
    new, m = step_ok(state, scene, batch)
    assert float(m["opacity"]) == 0.0
    ref = np.mean((np.asarray(bg, np.float64) - np.asarray(batch.rays.target, np.float64)[:, :3]) ** 2)
    np.testing.assert_allclose(float(m["loss/photometric"]), ref, rtol=PHOTO_RTOL)
    # nothing is seen: the features get exactly zero gradient and Adam leaves them as they were
    np.testing.assert_array_equal(np.asarray(new.points["feature"]), np.asarray(state.points["feature"]))


def test_confidences_near_zero_and_one(inputs):
    conf = np.where(np.arange(CAPACITY) % 2 == 0, 30.0, -30.0)  # 1 - 1e-13 and 1e-13
    params, scene, rays, bg = build(inputs, conf_logit=conf)
    state = make_train_state(scene, params)
    new, m = step_ok(state, scene, make_batch(rays, bg))
    assert float(m["opacity"]) > 0 and float(m["grad_norm"]) > 0
    step_ok(new, scene, make_batch(rays, bg, seed=1))  # and a second step from the updated moments


def test_huge_densities(inputs):
    alive = np.arange(CAPACITY) < N_POINTS
    alive[::3] = False  # a third of the slots dead after the build
    params, scene, rays, bg = build(inputs, alive=alive)
    dens = params["shader"]["density"]
    params["shader"]["density"] = dict(dens, bias=dens["bias"] + 1e4)  # sigma ~ 1e4 per spacing
    scene = scene.replace(points=scene.points.replace(feature=scene.points.feature * 100.0))
    state = make_train_state(scene, params)
    new, m = step_ok(state, scene, make_batch(rays, bg))
    assert float(m["opacity"]) > 0.5


def test_coincident_points(inputs):
    xyz, alive = make_cloud("duplicates", N_POINTS, seed=3)  # ~33 positions, each ~6 times
    assert len(np.unique(xyz[alive], axis=0)) < alive.sum() // 3
    points = make_state(xyz, alive, seed=3, feature_dim=CFG.shading.feature_dim)
    scene = PointScene.build(points, CFG, CAPS)
    rng = np.random.default_rng(4)
    origin, direction = aimed_rays(xyz, alive, rng, N_RAYS, jitter=0.01)
    batch = make_batch(make_rays(origin, direction, near=0.0, far=20.0), [1.0, 1.0, 1.0])
    new, m = step_ok(make_train_state(scene, build(inputs)[0]), scene, batch)
    assert float(m["opacity"]) > 0


def test_non_finite_terms_are_refused_and_named(inputs):
    params, scene, rays, bg = build(inputs)
    state = make_train_state(scene, params)
    batch = make_batch(rays, bg)
    # a NaN target pixel: the photometric term is NaN, the confidence regulariser is not
    target = batch.rays.target.at[5, 1].set(jnp.nan)
    m = assert_refused(state, scene, batch.replace(rays=batch.rays.replace(target=target)), "finite/photometric")
    assert bool(m["finite/confidence"])
    # a NaN confidence logit of an alive point: the confidence regulariser reads it directly
    j = int(np.flatnonzero(np.asarray(scene.points.alive))[7])
    bad = state.replace(points={**state.points, "conf_logit": state.points["conf_logit"].at[j].set(jnp.nan)})
    assert_refused(bad, scene, batch, "finite/confidence")
    # a NaN feature in a dead slot: no term reads it (zero gradient), but the update would write it
    dead = int(np.flatnonzero(~np.asarray(scene.points.alive))[0])
    bad = state.replace(points={**state.points, "feature": state.points["feature"].at[dead, 0].set(jnp.nan)})
    m = assert_refused(bad, scene, batch, "finite/update")
    assert all(bool(v) for k, v in m.items() if k.startswith("finite/") and k != "finite/update"), m
    # the clean state still steps, with the same executable
    step_ok(state, scene, batch)
    assert STEP._cache_size() == 1

"""Runtime finiteness checks (``ne_jax.checks``, ``RenderConfig.checks``): off, a NaN renders silently
and nothing is traced; on, the first non-finite value raises ``NonFiniteError`` naming the first
stage that saw it (traversal, interpolation, shading, compositing; in the training step also
``loss/<term>``, ``backward``, ``update``), and a finite render equals the unchecked one (to float32
rounding: two compiled programs).

Scene: the fixed tiny scene of ``tests/hard_cases/render_scene.py`` (64 rays, one chunk).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ne_jax.checks import NonFiniteError, checked, stage_check
from ne_jax.render.driver import render_chunked
from ne_jax.render.shading import init_color_model
from ne_jax.train import make_train_step

from hard_cases.render_scene import CFG, N_RAYS, build, scene_inputs
from hard_cases.test_train_step import SCHEDULE_STEPS, TCFG, make_batch, make_train_state

OFF = CFG.replace(chunk=N_RAYS)
ON = OFF.replace(checks=True)


@pytest.fixture(scope="module")
def world():
    return build(scene_inputs(0))


def nan_feature(scene):
    """The scene with one alive point's feature NaN (a point the rays see)."""
    j = int(np.flatnonzero(np.asarray(scene.points.alive))[0])
    return scene.replace(points=scene.points.replace(feature=scene.points.feature.at[j].set(jnp.nan)))


def raises_at(stage, cfg, params, scene, rays, bg):
    with pytest.raises(NonFiniteError, match=f"non-finite value at stage '{stage}'") as info:
        render_chunked(cfg, params, scene, rays, bg)
    return str(info.value)


def test_stage_check_unit():
    x = jnp.array([[1.0, 2.0], [3.0, jnp.inf]])
    mask = jnp.array([True, False])

    def f(a, on):
        stage_check(on, "demo", a=a, tree={"p": a, "q": a})
        stage_check(on, "masked", where=mask, a=a)
        return a * 2

    # off: nothing traced (the mask included)
    assert str(jax.make_jaxpr(lambda a: f(a, False))(x)) == str(jax.make_jaxpr(lambda a: a * 2)(x))
    g = checked(lambda a: f(a, True))
    with pytest.raises(NonFiniteError) as info:
        g(x)
    assert str(info.value).startswith("non-finite value at stage 'demo': a[shape (2, 2)] first at flat index 3 = inf")
    # pytree leaves named by path, the index relative to the first bad leaf
    with pytest.raises(NonFiniteError,
                       match=r"stage 'demo': tree\['q'\]\[shape \(2, 2\)\] first at flat index 3 = inf"):
        checked(lambda a: stage_check(True, "demo", tree={"p": a[0], "q": a}))(x)
    # masked slots are not checked
    np.testing.assert_array_equal(checked(lambda a: (stage_check(True, "m", where=mask, a=a), a)[1])(x), x)


def test_off_renders_nan_silently(world):
    params, scene, rays, bg = world
    out = render_chunked(OFF, params, nan_feature(scene), rays, bg)
    assert np.isnan(np.asarray(out.rgb)).any()


def assert_same_render(a, b):
    """``b`` equals ``a``: floats to float32 rounding (``rtol = atol = 1e-6``: a few ulp of values of
    order one, depths up to 5 included), integers and the structure exactly."""
    assert jax.tree_util.tree_structure(a) == jax.tree_util.tree_structure(b)
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        x, y = np.asarray(x), np.asarray(y)
        assert x.dtype == y.dtype and x.shape == y.shape
        if np.issubdtype(x.dtype, np.floating):
            np.testing.assert_allclose(y, x, rtol=1e-6, atol=1e-6)
        else:
            np.testing.assert_array_equal(y, x)


def test_on_finite_render_is_unchanged(world):
    """The checks add no arithmetic, but the checked render is a differently compiled program, and two
    programs are not bit-equal on every CPU: at XLA's optimisation level 0 an AMD EPYC gave one of
    192 values 6e-8 apart. So they agree to float32 rounding; a real change of the render is far
    larger: features 1e-4 larger move colours and depths by about 1e-5, and fail the comparison."""
    params, scene, rays, bg = world
    off = render_chunked(OFF, params, scene, rays, bg)
    assert_same_render(off, render_chunked(ON, params, scene, rays, bg))
    nudged = scene.replace(points=scene.points.replace(feature=scene.points.feature * (1 + 1e-4)))
    with pytest.raises(AssertionError):
        assert_same_render(off, render_chunked(ON, params, nudged, rays, bg))


def test_nan_feature_names_interpolation(world):
    params, scene, rays, bg = world
    msg = raises_at("interpolation", ON, params, nan_feature(scene), rays, bg)
    assert "feature[shape" in msg and "= nan" in msg
    # the ablation's per-sample path has the same stages
    raises_at("interpolation", ON.replace(integration="samples"), params, nan_feature(scene), rays, bg)


def test_nan_origin_names_traversal(world):
    params, scene, rays, bg = world
    bad = rays.replace(origin=rays.origin.at[5, 0].set(jnp.nan))
    msg = raises_at("traversal", ON, params, scene, bad, bg)
    assert "origin[shape (64, 3)] first at flat index 15 = nan" in msg


def test_inf_density_names_shading(world):
    params, scene, rays, bg = world
    dens = params["shader"]["density"]
    bad = dict(params, shader=dict(params["shader"], density=dict(dens, bias=dens["bias"] + jnp.inf)))
    msg = raises_at("shading", ON, bad, scene, rays, bg)
    assert "sigma[shape" in msg and "= inf" in msg


def test_train_step_names_the_stage(world):
    """The checked training step names the stage of a NaN target (``loss/photometric``) and of a NaN
    feature (``interpolation``). Its colour model has no specular branch: the stages are the same, the
    program to trace and compile about half the size."""
    _, scene, rays, bg = world
    cfg = ON.with_effects(specular=False)
    params = init_color_model(cfg.shading, jax.random.key(0))
    step = make_train_step(TCFG, cfg, total_steps=SCHEDULE_STEPS)
    state, batch = make_train_state(scene, params), make_batch(rays, bg)
    new, m = step(state, scene, batch)  # finite: applied as without checks
    assert bool(m["ok"]) and int(new.step) == int(state.step) + 1
    target = batch.rays.target.at[5, 1].set(jnp.nan)
    with pytest.raises(NonFiniteError, match="non-finite value at stage 'loss/photometric': photometric"):
        step(state, scene, batch.replace(rays=batch.rays.replace(target=target)))
    # a NaN feature of a seen point: the render's first stage that reads it
    bad = state.replace(points={**state.points, "feature": nan_feature(scene).points.feature})
    with pytest.raises(NonFiniteError, match="stage 'interpolation'"):
        step(bad, scene, batch)

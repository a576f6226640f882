"""Stage 7, render end to end (``render_rays`` under ``jit``: intersect -> samples -> KNN ->
quadrature -> shade -> composite) on the fixed tiny scene of ``render_scene.py``.

* float32 vs float64: the same model and rays rendered by a second process with the other dtype
  (``JAX_ENABLE_X64`` flipped). Bound: ``|rgb_32 - rgb_64| <= 1e-5`` and ``|opacity_32 - opacity_64|
  <= 1e-5`` on every ray whose segment count agrees, and the counts agree on at least 95% of the rays
  (a ray within float32 rounding of a box face may cross one voxel more or less).
* scale: the scene and the rays scaled by 1e-4 and 1e4 render the same image (lengths are measured in
  point spacings, the KNN weights are scale free): rgb and opacity within ``TOL["render_scale"]``
  (float32 1e-5, float64 1e-9; measured 1e-6 in float32), depth scaled, on rays with equal segment
  counts (>= 90%).
* hard model: confidences at +-30 logits, a third of the points deleted after the build, densities
  ~1e4 per spacing: outputs finite, gradients with respect to params, positions, features,
  confidences, origins and directions finite, and deleted points get exactly zero gradient.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from .common import DTYPE, TOL, X64, assert_finite
from .render_scene import CAPACITY, CFG, N_POINTS, build, render, render_arrays, scene_inputs

HERE = Path(__file__).resolve().parent
RGB_BOUND_32_64 = 1e-5  # measured 5e-7 (rgb), 1e-6 (opacity)


@pytest.fixture(scope="module")
def inputs():
    return scene_inputs(0)


def test_float32_and_float64_renders_agree(inputs, tmp_path):
    np.savez(tmp_path / "in.npz", **inputs)
    env = dict(os.environ, JAX_ENABLE_X64="0" if X64 else "1", JAX_PLATFORMS="cpu")
    subprocess.run([sys.executable, str(HERE / "render_scene.py"), str(tmp_path / "in.npz"),
                    str(tmp_path / "out.npz")], check=True, env=env, timeout=600)
    with np.load(tmp_path / "out.npz") as f:
        other = dict(f)
    mine = render_arrays(inputs)
    assert other["rgb"].dtype == (np.float32 if X64 else np.float64) and mine["rgb"].dtype == DTYPE
    for out in (mine, other):
        assert_finite(out)
        assert out["lost"].max() == 0
    same = mine["num_segments"] == other["num_segments"]
    assert same.mean() >= 0.95, same.mean()
    assert mine["num_segments"].sum() > 2 * len(same)  # the rays do cross the scene
    err = np.abs(mine["rgb"].astype(np.float64) - other["rgb"].astype(np.float64))[same]
    assert err.max() <= RGB_BOUND_32_64, err.max()
    op = np.abs(mine["opacity"].astype(np.float64) - other["opacity"].astype(np.float64))[same]
    assert op.max() <= RGB_BOUND_32_64, op.max()


@pytest.mark.parametrize("scale", [1e-4, 1e4])
def test_scaled_scene_renders_the_same_image(inputs, scale):
    ref = render(CFG, *build(inputs))
    out = render(CFG, *build(inputs, scale=scale))
    assert_finite((ref, out))
    same = np.asarray(ref.num_segments) == np.asarray(out.num_segments)
    assert same.mean() >= 0.9, same.mean()
    tol = TOL["render_scale"]
    np.testing.assert_allclose(np.asarray(out.rgb)[same], np.asarray(ref.rgb)[same], rtol=0, atol=tol)
    np.testing.assert_allclose(np.asarray(out.opacity)[same], np.asarray(ref.opacity)[same], rtol=0, atol=tol)
    np.testing.assert_allclose(np.asarray(out.depth, np.float64)[same] / scale,
                               np.asarray(ref.depth, np.float64)[same], rtol=10 * tol, atol=10 * tol)


def test_hard_model_values_and_gradients_finite(inputs):
    rng = np.random.default_rng(1)
    alive = np.arange(CAPACITY) < N_POINTS
    dead = np.flatnonzero(alive)[rng.random(N_POINTS) < 1 / 3]
    alive[dead] = False
    conf = rng.choice([-30.0, 30.0], size=CAPACITY)
    params, scene, rays, bg = build(inputs, alive=alive, conf_logit=conf)
    dens = params["shader"]["density"]
    params["shader"]["density"] = dict(dens, bias=dens["bias"] + 1e4)  # sigma ~ 1e4 per spacing
    out = render(CFG, params, scene, rays, bg)
    assert_finite(out)
    assert float(jnp.max(out.opacity)) == 1.0  # opaque surfaces

    def loss(params, xyz, feature, conf_logit, origin, direction):
        pts = scene.points.replace(xyz=xyz, feature=feature, conf_logit=conf_logit)
        o = render(CFG, params, scene.replace(points=pts), rays.replace(origin=origin, direction=direction), bg)
        return jnp.mean((o.rgb - 0.3) ** 2) + 1e-3 * jnp.mean(o.depth)

    p = scene.points
    grads = jax.jit(jax.grad(loss, argnums=tuple(range(6))))(params, p.xyz, p.feature, p.conf_logit,
                                                           rays.origin, rays.direction)
    assert_finite(grads, "grad ")
    for g in grads[1:4]:
        assert np.all(np.asarray(g)[~alive] == 0)
    assert float(jnp.abs(grads[2]).max()) > 0  # features of alive points do get gradient

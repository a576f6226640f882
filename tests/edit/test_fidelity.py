"""Equivariance of edited renders (:mod:`ne_jax.edit.fidelity`): a colour model over a small cloud,
moved rigidly with the tree carried, renders from moved cameras what the unedited model renders
from the original ones, at every tested angle and axis; the camera and point helpers are exact.

Two 16 x 16 views, one render chunk each (no survey pass), and the unedited reference rendered once
for the file."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ne_jax.data.cameras import look_at
from ne_jax.data.rays import Camera
from ne_jax.edit.apply import EditConfig, apply_edit, edited_render_config
from ne_jax.edit.deformations import rigid_motion, rigid_scene
from ne_jax.edit.fidelity import EXACT_DB, equivariance, exact_rigid_points, motion_parts, moved_camera, psnr_between
from ne_jax.eval.views import render_views
from ne_jax.geometry.points import PointState
from ne_jax.pointcloud.normals import NormalConfig, estimate_normals
from ne_jax.render.quadrature import QuadratureConfig
from ne_jax.render.renderer import PointScene
from ne_jax.render.shading import init_color_model

from tests.mini_presets import tiny_render

CFG = tiny_render(quadrature=QuadratureConfig(samples_per_level=(4, 6, 8)), chunk=256)  # a view's rays
NEAR, FAR = 0.5, 6.0


@pytest.fixture(scope="module")
def model():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(1200, 3))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    x[:, 2] *= 0.7
    n = estimate_normals(NormalConfig(orient="none"), x)
    n *= np.sign(np.sum(n * x, axis=1, keepdims=True))
    points = PointState.from_numpy(x, 1280, CFG.shading.feature_dim, normal=n, key=jax.random.key(1))
    noise = jnp.asarray(rng.normal(size=points.feature.shape), jnp.float32)
    points = points.replace(feature=points.feature + 0.5 * noise)
    params = init_color_model(CFG.shading, jax.random.key(2))
    cams = [Camera.from_fov(look_at(3.0 * np.array(e)), 16, 16, 0.9) for e in ([1, 0.3, 0.4], [-0.5, 1, -0.2])]
    scene = PointScene.build(points, CFG)
    reference = render_views(CFG, params, scene, cams, (1.0, 1.0, 1.0), NEAR, FAR, progress=False)
    return params, scene, cams, reference


def test_camera_and_points_move_exactly():
    m = rigid_motion((1.0, 2.0, 0.5), 33.0, pivot=(0.1, 0.2, 0.3), translation=(0.5, 0.0, -0.1))
    rot, t, s = motion_parts(m)
    np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-12)
    assert s == pytest.approx(1.0)
    cam = Camera.from_fov(look_at(np.array([2.0, 1.0, 0.5])), 8, 8, 0.8)
    moved = np.asarray(moved_camera(cam, m).c2w, np.float64)
    np.testing.assert_allclose(moved, m @ np.asarray(cam.c2w, np.float64), atol=1e-5)
    with pytest.raises(ValueError, match="matrix: expected s R"):
        motion_parts(np.diag([1.0, 2.0, 1.0, 1.0]))
    x = np.random.default_rng(1).normal(size=(10, 3))
    pts = PointState.from_numpy(x, 12, 4, normal=x / np.linalg.norm(x, axis=1, keepdims=True))
    ex = exact_rigid_points(pts, m)
    np.testing.assert_allclose(np.asarray(ex.xyz)[:10], x @ rot.T + t, atol=1e-5)
    np.testing.assert_allclose(np.asarray(ex.ist)[:10], np.broadcast_to(rot.T, (10, 3, 3)), atol=1e-6)
    assert psnr_between(np.zeros(3), np.zeros(3)) == EXACT_DB


@pytest.mark.parametrize("axis,angle", [((1.0, 1.0, 2.0), 2.0), ((1.0, 1.0, 2.0), 40.0), ((2.0, -1.0, 0.5), 90.0),
                                        ((0.0, 0.0, 1.0), 180.0)])
def test_carried_tree_renders_rigid_motions_equivariantly(model, axis, angle):
    """The carried tree meets the issue's bar (40 dB) by far (rounding and the IST's own fit remain);
    a tree rebuilt on the edited cloud renders the same scene less exactly (other candidate sets)."""
    params, scene, cams, ref = model
    edit = rigid_scene("turn", axis, angle, pivot=(0.1, -0.1, 0.0), translation=(0.2, 0.0, 0.1))
    render = edited_render_config(CFG, ist=True)
    got = {}
    for tree in ("carry", "rebuild"):
        cfg = EditConfig(rebuild_tree=tree == "rebuild")
        points = apply_edit(scene.points, edit, cfg)
        res = equivariance(CFG, params, scene, render, cfg.scene(scene, points, render), edit.matrix, cams,
                           (1.0, 1.0, 1.0), NEAR, FAR, reference=ref)
        got[tree] = res["psnr"]
    assert got["carry"] >= 45.0, got
    assert 15.0 <= got["rebuild"] < got["carry"], got
    assert np.std(ref) > 0.02  # the reference is an image, not a flat background


def test_edited_scene_keeps_its_rest_and_carries_again(model):
    """A second edit of an edited scene carries the tree from the original rest positions, and the
    two edits compose: turning by 20 then 20 degrees renders as turning by 40."""
    params, scene, cams, ref = model
    render = edited_render_config(CFG, ist=True)
    one = rigid_scene("a", (1.0, 0.0, 1.0), 20.0)
    pts1 = apply_edit(scene.points, one)
    s1 = scene.edited(pts1, render)
    np.testing.assert_array_equal(np.asarray(s1.rest_xyz), np.asarray(scene.points.xyz))
    s2 = s1.edited(apply_edit(pts1, one), render)
    np.testing.assert_array_equal(np.asarray(s2.rest_xyz), np.asarray(scene.points.xyz))
    res = equivariance(CFG, params, scene, render, s2, one.matrix @ one.matrix, cams, (1.0, 1.0, 1.0), NEAR, FAR,
                      reference=ref)
    assert res["psnr"] >= 40.0

"""Blended rendering of two models through one intermediate cloud: the ends are each model's own
render, the blend is the ratio mix of the two colour models, a morph compiles once, held edit
contexts give the scene made without them, and a whole morph writes its frames, video and report
(library and command line)."""

from __future__ import annotations

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ne_jax.benchmark.generate import generate_scene
from ne_jax.cli import main
from ne_jax.data.cameras import orbit_cameras
from ne_jax.data.rays import Camera
from ne_jax.edit.apply import EditConfig
from ne_jax.geometry.points import PointState
from ne_jax.morph import (
    BlendedShading,
    MorphSettings,
    blended_render_config,
    linear_path,
    morph_contexts,
    morph_models,
    morph_scene,
    morph_scene_with_report,
    pair_models,
    render_morph,
)
from ne_jax.pointcloud.normals import NormalConfig, estimate_normals
from ne_jax.render import driver
from ne_jax.render.driver import render_image
from ne_jax.render.quadrature import at_test_time
from ne_jax.render.renderer import PointScene
from ne_jax.render.shading import Effects, init_color_model, shade
from ne_jax.train.model import TrainedModel, save_trained
from ne_jax.train.run import RunConfig
from ne_jax.train.state import init_train_state

from tests.mini_presets import mini_benchmark, tiny_render

N = 400
BG = jnp.ones(3)


def _sphere(n, seed):
    v = np.random.default_rng(seed).normal(size=(n, 3))
    return 0.8 * v / np.linalg.norm(v, axis=1, keepdims=True)


def _cube(n, seed):
    p = np.random.default_rng(seed).uniform(-0.6, 0.6, (n, 3))
    axis = np.arange(n) % 3
    p[np.arange(n), axis] = np.sign(p[np.arange(n), axis]) * 0.6
    return p


def _model(xyz, seed, capacity=None, effects=Effects()) -> TrainedModel:
    render = tiny_render()
    render = render.replace(shading=dataclasses.replace(render.shading, effects=effects))
    run = RunConfig.tiny(render=render)
    normals = estimate_normals(NormalConfig(orient="none"), xyz)
    pts = PointState.from_numpy(xyz, capacity, render.shading.feature_dim, normal=normals,
                                key=jax.random.PRNGKey(seed))
    pts = pts.replace(feature=3.0 * pts.feature)  # colours and densities that differ visibly across points
    state = init_train_state(run.train, render, pts, jax.random.key(seed + 1), total_steps=run.total_steps)
    return TrainedModel(run=run, state=state, scene=PointScene.build(pts, render), scene_dir=None, meta={})


def _camera(size=20) -> Camera:
    return Camera.from_fov(jnp.asarray(orbit_cameras(1, 30.0)[0], jnp.float32), size, size, 0.7)


def _own_render(model, camera):
    cfg = model.run.render.replace(quadrature=at_test_time(model.run.render.quadrature))
    return render_image(cfg, model.state.params, model.scene, camera, BG, 2.0, 6.0).rgb


@pytest.fixture(scope="module")
def models():
    # B: another shape, a diffuse colour model (no normals, no view direction) and spare capacity
    return _model(_sphere(N, 0), 0), _model(_cube(N, 1), 10, capacity=N + 37, effects=Effects(specular=False))


def test_ratio_0_on_a_cloud_renders_a_and_ratio_1_on_b_cloud_renders_b(models):
    a, b = models
    cam = _camera()
    pair = pair_models(a, b)
    own_a, own_b = _own_render(a, cam), _own_render(b, cam)
    assert float(jnp.abs(own_a - own_b).max()) > 0.2  # the two ends differ: the test can fail
    start = render_image(pair.render, pair.params(0.0), morph_scene(pair, pair.cloud_a), cam, BG, 2.0, 6.0).rgb
    end = render_image(pair.render, pair.params(1.0), morph_scene(pair, pair.cloud_b), cam, BG, 2.0, 6.0).rgb
    np.testing.assert_allclose(start, own_a, atol=1e-5)
    np.testing.assert_allclose(end, own_b, atol=1e-5)


def test_blended_shading_mixes_both_color_models_by_the_ratio():
    fa, fb = Effects(), Effects(specular=False)
    ref = tiny_render().shading
    ca, cb = (dataclasses.replace(ref, effects=dataclasses.replace(e, ist=True)) for e in (fa, fb))
    blend = BlendedShading(ca, cb)
    pa, pb = init_color_model(ca, jax.random.PRNGKey(0)), init_color_model(cb, jax.random.PRNGKey(1))
    k = jax.random.split(jax.random.PRNGKey(2), 4)
    feat = jax.random.normal(k[0], (7, ca.feature_dim + cb.feature_dim))
    normal = jax.random.normal(k[1], (7, 2, 3))
    view = jax.random.normal(k[2], (7, 3))
    ist = jnp.broadcast_to(jnp.eye(3), (7, 2, 3, 3)) + 0.1 * jax.random.normal(k[3], (7, 2, 3, 3))
    r = 0.3

    @jax.jit
    def blended_and_ends(ratio, feat):
        """The blend, each end's own shading, and the blend's gradient (one program)."""
        def loss(ratio, feat):
            o = shade(blend, {"a": pa, "b": pb, "ratio": ratio}, feat, normal, view, ist)
            return jnp.sum(o.rgb) + jnp.sum(o.sigma), o

        (_, out), grads = jax.value_and_grad(loss, argnums=(0, 1), has_aux=True)(ratio, feat)
        oa = shade(ca, pa, feat[:, :ca.feature_dim], normal[:, 0], view, ist[:, 0])
        ob = shade(cb, pb, feat[:, ca.feature_dim:], None, view, None)
        return out, oa, ob, grads

    out, oa, ob, (g_r, g_f) = blended_and_ends(jnp.float32(r), feat)
    np.testing.assert_allclose(out.sigma, (1 - r) * oa.sigma + r * ob.sigma, rtol=1e-6)
    np.testing.assert_allclose(out.rgb, (1 - r) * oa.rgb + r * ob.rgb, rtol=1e-6)
    assert np.isfinite(float(g_r)) and float(g_r) != 0.0 and bool(jnp.all(jnp.isfinite(g_f)))


def test_a_morph_compiles_once_and_its_frames_are_finite(models):
    a, b = models
    pair = pair_models(a, b)
    path = linear_path(pair.cloud_a, pair.cloud_b, 4)
    cam = _camera(12)
    render_morph(pair, path[:1], cam, "white", 2.0, 6.0, progress=False, ratios=[0.0])  # compiles
    before = driver._render_chunk._cache_size()
    frames, reports = render_morph(pair, path, cam, "white", 2.0, 6.0, progress=False)
    assert driver._render_chunk._cache_size() == before
    assert frames.shape == (4, 12, 12, 3) and np.isfinite(frames).all()
    assert [r["ratio"] for r in reports] == pytest.approx([0, 1 / 3, 2 / 3, 1])


def test_unequal_clouds_keep_the_most_confident_points_of_the_larger(models):
    a, _ = models
    big = _model(_cube(N + 50, 3), 20)
    conf = np.linspace(-3.0, 3.0, N + 50)
    big.state.points["conf_logit"] = jnp.asarray(conf, jnp.float32)
    pair = pair_models(a, big)
    assert pair.slots_a.size == N
    np.testing.assert_array_equal(np.sort(pair.slots_b), np.arange(50, N + 50))  # the 50 least confident left out


def test_held_edit_contexts_give_the_scene_made_without_them(models):
    a, _ = models
    big = _model(_cube(N + 50, 3), 20)  # the larger cloud: its 50 unmatched points are deleted by every frame
    pair = pair_models(a, big)
    contexts = morph_contexts(pair)
    cloud = 0.5 * (pair.cloud_a + pair.cloud_b)
    held, held_report = morph_scene_with_report(pair, cloud, contexts=contexts)
    spot, spot_report = morph_scene_with_report(pair, cloud)
    jax.tree_util.tree_map(np.testing.assert_array_equal, held, spot)
    def counts(report):
        return {m: {k: v for k, v in r.items() if k != "seconds"} for m, r in report.items()}

    assert counts(held_report) == counts(spot_report) and held_report["b"]["deleted"] == 50
    # the contexts serve every frame: made for the points each edit leaves alive
    assert contexts[0].for_alive(EditConfig(), np.asarray(held.points.alive)) is contexts[0]
    assert int(contexts[1].neighbors.alive.sum()) == N
    jax.tree_util.tree_map(np.testing.assert_array_equal, morph_scene(pair, cloud, contexts=contexts), spot)


def test_models_rendered_differently_and_bad_clouds_are_refused(models):
    a, b = models
    other = a.run.render.replace(kdtree=a.run.render.kdtree.replace(knn_k=4))
    with pytest.raises(ValueError, match="same traversal and integration.*tree"):
        blended_render_config(a.run.render, other)
    pair = pair_models(a, b)
    with pytest.raises(ValueError, match=rf"expected a cloud of shape \({N}, 3\).*found \(3, 3\)"):
        morph_scene(pair, np.zeros((3, 3)))


@pytest.fixture(scope="module")
def run_dirs(models, tmp_path_factory):
    root = tmp_path_factory.mktemp("morph")
    preset = mini_benchmark(resolution=16, train_views=2, detail=0.3, surface_samples=500)
    generate_scene("glossy", preset, root, seed=0)
    a, b = models
    scene = root / "glossy"
    save_trained(a.replace(scene_dir=scene), root / "a")
    save_trained(b.replace(scene_dir=scene), root / "b")
    return root


def test_morph_models_writes_frames_video_strip_and_report(models, tmp_path):
    a, b = models
    report, frames = morph_models(a, b, tmp_path / "m", _camera(12), MorphSettings(steps=3, video="m.gif"),
                                  progress=False)
    assert sorted(p.name for p in (tmp_path / "m").iterdir()) == ["frames", "m.gif", "morph.json", "strip.png"]
    assert len(list((tmp_path / "m" / "frames").glob("frame_*.png"))) == 3 == len(frames)
    saved = json.loads((tmp_path / "m" / "morph.json").read_text())
    sm = saved["smoothness"]
    assert saved["frames"] == 3 and len(sm["step_change"]) == 2 and sm["path_ratio"] >= 1.0 - 1e-9
    assert sm == report["smoothness"]


def test_cli_morph_and_its_errors(run_dirs, capsys):
    out = run_dirs / "out"
    code = main(["morph", str(run_dirs / "a"), str(run_dirs / "b"), "--out", str(out), "--steps", "3",
                 "--format", "gif", "--quiet"])
    assert code == 0 and "morph: 3 frames" in capsys.readouterr().out
    assert (out / "morph.gif").is_file() and (out / "strip.png").is_file()
    assert main(["morph", str(run_dirs / "a"), str(run_dirs / "missing"), "--out", str(run_dirs / "x")]) == 2
    assert "missing: expected a training run directory" in capsys.readouterr().err
    assert main(["morph", str(run_dirs / "a"), str(run_dirs / "b"), "--out", str(run_dirs / "x"), "--view", "5"]) == 2
    assert "--view: expected a view of the test split in [0, 1), found 5" in capsys.readouterr().err
    assert not (run_dirs / "x").exists()  # nothing written half

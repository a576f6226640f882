"""The training step on a tiny generated benchmark scene, the ray sampler, and the loss terms.

The initial cloud of these tests is the benchmark's ground-truth surface samples (``points.ply``)
with their ground-truth normals -- a test fixture, not the method's initialisation."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ne_jax.benchmark.generate import generate_scene
from ne_jax.data.nerf_synthetic import SceneSplit, composite, load_split
from ne_jax.data.ply import read_ply
from ne_jax.data.rays import pixel_rays
from ne_jax.geometry.points import PointState
from ne_jax.render.renderer import PointScene, SegmentAux, render_rays, render_rays_with_aux
from ne_jax.train import (
    SamplerConfig,
    TrainConfig,
    band_mask,
    build_pool,
    confidence_loss,
    init_train_state,
    make_train_step,
    normal_loss,
    normal_mismatch,
    orientation_loss,
    photometric_loss,
    sample_batch,
    sparsity_loss,
)
from ne_jax.train.losses import CONFIDENCE_EPS

from tests.mini_presets import mini_benchmark, tiny_render

MINI = mini_benchmark(resolution=32, train_views=6, detail=0.5, surface_samples=3000)
RCFG = tiny_render()
SCFG = SamplerConfig(batch_size=256, band_width=2, band_fraction=0.1)
TCFG = TrainConfig()
SCHEDULE_STEPS = 1000
"""The length of the learning-rate schedule (a run's ``total_steps``)."""
STEPS = 40
_render = jax.jit(render_rays, static_argnums=0)  # one compilation for every 256-ray render below
STEP_FN = make_train_step(TCFG, RCFG, total_steps=SCHEDULE_STEPS)
"""The training step of ``world``, made once for the module."""


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    root = tmp_path_factory.mktemp("bench")
    generate_scene("blocks", MINI, root, seed=0, edits=())
    split = load_split(root / "blocks", "train")
    ply = read_ply(root / "blocks" / "points.ply")
    gt_xyz = np.stack([ply["x"], ply["y"], ply["z"]], -1)  # ground-truth surface samples (test fixture)
    gt_normal = np.stack([ply["nx"], ply["ny"], ply["nz"]], -1)
    points = PointState.from_numpy(gt_xyz, feature_dim=RCFG.shading.feature_dim, normal=gt_normal,
                                   key=jax.random.key(0))
    scene = PointScene.build(points, RCFG)
    pool = build_pool(SCFG, split, "white")
    return dict(split=split, points=points, scene=scene, pool=pool, step_fn=STEP_FN)


# ---------------------------------------------------------------- sampler


def test_sampler_draws_foreground_and_band_only(world):
    split, pool = world["split"], world["pool"]
    alpha = split.images[..., 3]
    fg = (alpha > 0).ravel()
    band = band_mask(alpha, SCFG.band_width).ravel()
    assert band.any() and fg.any() and not (fg & band).any()
    outside = ~(fg | band)
    assert outside.any()  # the test means something: there are pixels the sampler must avoid

    batch = sample_batch(SCFG, pool, jax.random.key(3))
    pix = np.asarray(batch.pixel)
    assert pix.shape == (SCFG.batch_size,) and batch.rays.origin.shape == (SCFG.batch_size, 3)
    in_band = np.asarray(batch.in_band)
    assert in_band.sum() == round(SCFG.band_fraction * SCFG.batch_size)
    assert fg[pix[~in_band]].all() and band[pix[in_band]].all()

    # targets: RGB composited on the user's background, alpha 1
    rgb = composite(split.images, "white").reshape(-1, 3)
    np.testing.assert_allclose(np.asarray(batch.rays.target[:, :3]), rgb[pix], atol=1e-6)
    np.testing.assert_array_equal(np.asarray(batch.rays.target[:, 3]), 1.0)

    # rays: the same as pixel_rays of the view's camera through the pixel centres
    hw = split.width * split.height
    for b in (0, SCFG.batch_size - 1):
        view, rest = divmod(int(pix[b]), hw)
        row, col = divmod(rest, split.width)
        ref = pixel_rays(split.camera(view), jnp.asarray([[col + 0.5, row + 0.5]]), SCFG.near, SCFG.far)
        np.testing.assert_allclose(np.asarray(batch.rays.direction[b]), np.asarray(ref.direction[0]), atol=1e-5)
        np.testing.assert_allclose(np.asarray(batch.rays.origin[b]), np.asarray(ref.origin[0]), atol=1e-6)


def test_sampler_is_deterministic_for_a_key_and_fixed_in_shape(world):
    pool = world["pool"]
    a = sample_batch(SCFG, pool, jax.random.key(7))
    b = sample_batch(SCFG, pool, jax.random.key(7))
    c = sample_batch(SCFG, pool, jax.random.key(8))
    np.testing.assert_array_equal(np.asarray(a.pixel), np.asarray(b.pixel))
    np.testing.assert_array_equal(np.asarray(a.rays.direction), np.asarray(b.rays.direction))
    assert not np.array_equal(np.asarray(a.pixel), np.asarray(c.pixel))
    assert sample_batch._cache_size() >= 1
    before = sample_batch._cache_size()
    for k in range(3):
        assert sample_batch(SCFG, pool, jax.random.key(100 + k)).pixel.shape == (SCFG.batch_size,)
    assert sample_batch._cache_size() == before


def test_sampler_band_fraction_zero_and_empty_masks():
    rng = np.random.default_rng(0)
    images = np.zeros((2, 8, 8, 4), np.float32)
    images[0, 3:5, 3:5] = np.concatenate([rng.uniform(size=(2, 2, 3)), np.ones((2, 2, 1))], -1)
    split = SceneSplit(name="toy", images=images, c2w=np.tile(np.eye(4, dtype=np.float32), (2, 1, 1)),
                       fx=8.0, fy=8.0, cx=4.0, cy=4.0, camera_angle_x=1.0, file_paths=("a", "b"),
                       image_paths=(Path("a"), Path("b")))
    pool = build_pool(SamplerConfig(batch_size=16, band_width=1, band_fraction=0.0), split, "black")
    batch = sample_batch(SamplerConfig(batch_size=16, band_width=1, band_fraction=0.0), pool, jax.random.key(0))
    assert not np.asarray(batch.in_band).any()
    assert set(np.asarray(batch.pixel).tolist()) <= {3 * 8 + 3, 3 * 8 + 4, 4 * 8 + 3, 4 * 8 + 4}
    empty = dataclasses.replace(split, images=np.zeros_like(images))
    with pytest.raises(ValueError, match="no foreground"):
        build_pool(SamplerConfig(batch_size=16), empty, "black")


def test_sampler_pixel_grid_groups_each_pixels_rays(world):
    """With 2 x 2 rays per pixel: a quarter of the pixels, each pixel's 4 rays consecutive with its
    index and target, through the 4 grid positions of that pixel; a batch that is not a multiple of 4
    rays is refused."""
    split, pool = world["split"], world["pool"]
    batch = sample_batch(SCFG, pool, jax.random.key(3), 2)
    pix = np.asarray(batch.pixel).reshape(-1, 4)
    assert pix.shape == (SCFG.batch_size // 4, 4) and (pix == pix[:, :1]).all()
    target = np.asarray(batch.rays.target).reshape(-1, 4, 4)
    assert (target == target[:, :1]).all()
    assert np.asarray(batch.in_band).reshape(-1, 4)[:, 0].sum() == round(SCFG.band_fraction * SCFG.batch_size / 4)
    hw = split.width * split.height
    for p in (0, SCFG.batch_size // 4 - 1):
        view, rest = divmod(int(pix[p, 0]), hw)
        row, col = divmod(rest, split.width)
        xy = jnp.asarray([[col + a, row + b] for b in (0.25, 0.75) for a in (0.25, 0.75)])
        ref = pixel_rays(split.camera(view), xy, SCFG.near, SCFG.far)
        np.testing.assert_allclose(np.asarray(batch.rays.direction[4 * p:4 * p + 4]), np.asarray(ref.direction),
                                   atol=1e-5)
    with pytest.raises(ValueError, match="not a multiple of the 9 rays"):
        sample_batch(SCFG, pool, jax.random.key(3), 3)


# ---------------------------------------------------------------- render with aux


def test_render_with_aux_matches_render_rays(world):
    scene, pool = world["scene"], world["pool"]
    rays = sample_batch(SCFG, pool, jax.random.key(1)).rays
    params = init_train_state(TCFG, RCFG, world["points"], jax.random.key(1), total_steps=SCHEDULE_STEPS).params
    bg = jnp.ones(3)
    plain = _render(RCFG, params, scene, rays, bg)
    out, aux = jax.jit(render_rays_with_aux, static_argnums=0)(RCFG, params, scene, rays, bg)
    np.testing.assert_allclose(np.asarray(out.rgb), np.asarray(plain.rgb), atol=1e-6)
    np.testing.assert_allclose(np.asarray(jnp.sum(aux.weights, -1)), np.asarray(out.opacity), atol=1e-5)
    assert aux.pred_normal.shape == aux.valid.shape + (3,) and aux.normal_moment.shape == aux.valid.shape + (3, 3)
    v = np.asarray(aux.valid)
    assert v.any() and (~v).any()
    np.testing.assert_array_equal(np.asarray(aux.weights)[~v], 0.0)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(aux.pred_normal)[v], axis=-1), 1.0, atol=1e-5)
    conf = np.asarray(aux.confidence)[v]
    np.testing.assert_allclose(conf, 0.5, atol=1e-5)  # every point starts at confidence 0.5
    # unit ground-truth normals: trace(A) = confidence
    np.testing.assert_allclose(np.trace(np.asarray(aux.normal_moment)[v], axis1=-2, axis2=-1), conf, atol=1e-4)


# ---------------------------------------------------------------- training step


def _eval_mse(state, world, batch):
    scene = state.scene(world["scene"])
    out = _render(RCFG, state.params, scene, batch.rays, batch.background)
    return float(jnp.mean(jnp.square(out.rgb - batch.rays.target[:, :3])))


def test_training_reduces_photometric_loss_without_recompiling(world):
    step_fn, pool, scene = world["step_fn"], world["pool"], world["scene"]
    state = init_train_state(TCFG, RCFG, world["points"], jax.random.key(1), total_steps=SCHEDULE_STEPS)
    held_out = sample_batch(SCFG, pool, jax.random.key(999))
    mse0 = _eval_mse(state, world, held_out)
    key = jax.random.key(2)
    losses = []
    for _ in range(STEPS):
        key, k = jax.random.split(key)
        state, m = step_fn(state, scene, sample_batch(SCFG, pool, k))
        assert bool(m["ok"])
        losses.append(float(m["loss/photometric"]))
    assert step_fn._cache_size() == 1  # compiled once for all steps
    assert int(state.step) == STEPS and int(state.skipped) == 0
    assert all(np.isfinite(losses))
    mse1 = _eval_mse(state, world, held_out)
    # blocks, 32x32, 6 views, 256 rays, 40 steps: the held-out MSE and the per-batch loss at least halve
    assert mse1 < 0.5 * mse0, (mse0, mse1)
    assert np.mean(losses[-5:]) < 0.5 * np.mean(losses[:3]), losses


def test_pixel_grid_step_scores_each_pixels_mean_colour(world):
    """With ``pixel_samples=2`` the photometric term is the mean over pixels of (mean of a pixel's 4
    rays' colours - its target)^2, not the mean over rays, and the step's gradients are finite."""
    cfg = RCFG.replace(pixel_samples=2)
    pool, scene = world["pool"], world["scene"]
    state = init_train_state(TCFG, cfg, world["points"], jax.random.key(1), total_steps=SCHEDULE_STEPS)
    batch = sample_batch(SCFG, pool, jax.random.key(11), 2)
    # the rays' colours: a render reads no pixel_samples (render_image renders every grid at 1), so
    # the one-ray config's compiled render serves
    out = _render(RCFG, state.params, state.scene(scene), batch.rays, batch.background)
    rgb, target = np.asarray(out.rgb, np.float64), np.asarray(batch.rays.target[:, :3], np.float64)
    per_pixel = np.mean(np.square(rgb.reshape(-1, 4, 3).mean(1) - target[::4]))
    per_ray = np.mean(np.square(rgb - target))
    assert per_ray > 1.05 * per_pixel  # the rays of an edge pixel differ: the two rules disagree here
    new, m = make_train_step(TCFG, cfg, total_steps=SCHEDULE_STEPS)(state, scene, batch)
    assert bool(m["ok"]) and int(new.step) == 1
    np.testing.assert_allclose(float(m["loss/photometric"]), per_pixel, rtol=1e-4)
    assert np.isfinite(float(m["grad_norm"])) and float(m["grad_norm"]) > 0


def _nan_target_point(world, state, batch):
    """The point nearest the surface point seen by the first foreground ray of ``batch``."""
    out = _render(RCFG, state.params, state.scene(world["scene"]), batch.rays, batch.background)
    b = int(np.argmax(np.asarray(out.opacity)))
    hit = np.asarray(batch.rays.origin[b] + out.depth[b] * batch.rays.direction[b])
    return int(np.argmin(np.linalg.norm(np.asarray(world["points"].xyz) - hit, axis=-1)))


def test_nan_feature_is_refused_and_named(world):
    step_fn, pool, scene = world["step_fn"], world["pool"], world["scene"]
    state = init_train_state(TCFG, RCFG, world["points"], jax.random.key(1), total_steps=SCHEDULE_STEPS)
    batch = sample_batch(SCFG, pool, jax.random.key(5))
    j = _nan_target_point(world, state, batch)
    bad = state.replace(points={**state.points, "feature": state.points["feature"].at[j, 3].set(jnp.nan)})
    new, m = step_fn(bad, scene, batch)
    assert not bool(m["ok"]) and int(new.skipped) == 1 and int(new.step) == 0
    assert not bool(m["finite/photometric"])
    assert bool(m["finite/confidence"])  # the confidence regulariser does not read features
    assert not bool(m["finite/grad"])
    for a, b in zip(jax.tree_util.tree_leaves((bad.params, bad.points, bad.opt_state)),
                    jax.tree_util.tree_leaves((new.params, new.points, new.opt_state))):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))  # nothing written (NaN == NaN here)
    # the clean state steps normally with the same compiled function
    ok_state, m_ok = step_fn(state, scene, batch)
    assert bool(m_ok["ok"]) and int(ok_state.step) == 1
    assert all(bool(v) for k, v in m_ok.items() if k.startswith("finite/"))
    assert step_fn._cache_size() == 1


def test_step_finite_at_extreme_confidences_and_empty_rays(world):
    """Confidences near 0 and 1, and rays that hit nothing (zero opacity), through the real step."""
    step_fn, pool, scene = world["step_fn"], world["pool"], world["scene"]
    state = init_train_state(TCFG, RCFG, world["points"], jax.random.key(1), total_steps=SCHEDULE_STEPS)
    c = state.points["conf_logit"].shape[0]
    logit = jnp.asarray(np.where(np.arange(c) % 2 == 0, 30.0, -30.0), jnp.float32)  # c ~ 1 - 1e-13, 1e-13
    state = state.replace(points={**state.points, "conf_logit": logit})
    batch = sample_batch(SCFG, pool, jax.random.key(6))
    outward = batch.rays.origin / jnp.linalg.norm(batch.rays.origin, axis=-1, keepdims=True)
    half = jnp.arange(SCFG.batch_size)[:, None] < SCFG.batch_size // 2  # these look away from the scene
    batch = batch.replace(rays=batch.rays.replace(direction=jnp.where(half, outward, batch.rays.direction)))
    new, m = step_fn(state, scene, batch)
    assert bool(m["ok"]), m
    assert all(bool(v) for k, v in m.items() if k.startswith("finite/"))
    assert np.isfinite(float(m["grad_norm"])) and float(m["grad_norm"]) > 0
    assert step_fn._cache_size() == 1


# ---------------------------------------------------------------- loss terms


def _hard_aux(rng, r=5, m=4):
    valid = np.ones((r, m), bool)
    valid[0] = False  # a ray with no segment: zero opacity
    valid[1, 2:] = False
    weights = rng.uniform(size=(r, m)).astype(np.float32) * valid
    weights[2] = 0.0  # segments that are seen with weight exactly 0
    pred = rng.normal(size=(r, m, 3))
    pred /= np.linalg.norm(pred, axis=-1, keepdims=True)
    view = rng.normal(size=(r, m, 3))
    view /= np.linalg.norm(view, axis=-1, keepdims=True)
    pred[3, 0] = -view[3, 0]  # facing the camera exactly
    pred[3, 1] = np.cross(view[3, 1], [0.0, 0.0, 1.0]) / np.linalg.norm(np.cross(view[3, 1], [0.0, 0.0, 1.0]))
    n = rng.normal(size=(r, m, 3, 3))  # three neighbour normals per segment
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    n[4, 0] = 0.0  # points without a normal
    n[4, 1] = pred[4, 1]  # perfectly aligned: mismatch exactly 0
    c = rng.uniform(size=(r, m, 3))
    c[..., 0] = 1e-13  # confidences near 0 and 1
    c[..., 1] = 1.0 - 1e-7
    moment = np.einsum("rmk,rmki,rmkj->rmij", c / 3.0, n, n)
    sigma = rng.uniform(0, 5, size=(r, m)).astype(np.float32)
    sigma[1, 0] = 1e6  # huge density
    f = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    aux = SegmentAux(valid=jnp.asarray(valid), weights=f(weights), sigma=f(sigma),
                     lengths=f(rng.uniform(0, 2, size=(r, m)) * valid), pred_normal=f(pred),
                     shading_normal=f(pred), view_dir=f(view), confidence=f(c.mean(-1)), normal_moment=f(moment))
    return aux, n, c


def test_normal_mismatch_matches_the_per_point_sum():
    aux, n, c = _hard_aux(np.random.default_rng(0))
    p = np.asarray(aux.pred_normal, np.float64)
    dot = np.einsum("rmi,rmki->rmk", p, n)
    ref = np.sum(c / 3.0 * np.sum(n * n, -1) * (1.0 - dot**2), axis=-1)
    np.testing.assert_allclose(np.asarray(normal_mismatch(aux)), ref, atol=1e-5)
    assert float(normal_mismatch(aux)[4, 1]) < 1e-6


def test_every_loss_term_has_finite_gradients_at_hard_inputs():
    aux, _, _ = _hard_aux(np.random.default_rng(1))
    float_fields = {k: v for k, v in aux.__dict__.items() if k != "valid"}

    def terms(fields, rgb, target, logit, alive):
        a = SegmentAux(valid=aux.valid, **fields)
        return {"photometric": photometric_loss(rgb, target), "orientation": orientation_loss(a),
                "normal": normal_loss(a), "confidence": confidence_loss(logit, alive),
                "sparsity": sparsity_loss(a)}

    rgb = jnp.asarray([[0.0, 1.0, 0.5], [1.0, 1.0, 1.0]])
    target = jnp.asarray([[0.0, 1.0, 0.5], [0.0, 0.0, 0.0]])
    logit = jnp.asarray([-1e4, -30.0, -1.0, 0.0, 1e-3, 2.0, 30.0, 1e4, 5.0], jnp.float32)
    alive = jnp.asarray([True] * 8 + [False])  # a dead slot (finite placeholder)
    values = terms(float_fields, rgb, target, logit, alive)
    for name in values:
        g = jax.grad(lambda *a, name=name: terms(*a)[name], argnums=(0, 1, 2, 3))(float_fields, rgb, target, logit,
                                                                                  alive)
        assert np.isfinite(float(values[name])), name
        assert all(np.isfinite(np.asarray(x)).all() for x in jax.tree_util.tree_leaves(g)), name
    # zero-opacity ray contributes nothing and gets zero gradient
    g_w = jax.grad(lambda f: normal_loss(SegmentAux(valid=aux.valid, **f)))(float_fields)["weights"]
    np.testing.assert_array_equal(np.asarray(g_w[0]), 0.0)


def test_confidence_regulariser_pushes_away_from_half_and_stops_at_the_clip():
    eps = CONFIDENCE_EPS
    logit = jnp.asarray([-20.0, -3.0, -0.5, 0.5, 3.0, 20.0])
    alive = jnp.ones(6, bool)
    g = np.asarray(jax.grad(confidence_loss)(logit, alive, eps))
    assert g[1] > 0 and g[2] > 0 and g[3] < 0 and g[4] < 0  # descent moves logits away from 0
    assert g[0] == 0 and g[5] == 0  # beyond logit((1 - eps)) no push
    assert float(confidence_loss(jnp.asarray([50.0, -50.0]), jnp.ones(2, bool), eps)) == pytest.approx(0.0, abs=1e-6)
    half = float(confidence_loss(jnp.zeros(1), jnp.ones(1, bool), eps))
    assert half == pytest.approx(np.log(1 / (4 * eps * (1 - eps))), rel=1e-5)
    assert float(confidence_loss(logit, jnp.zeros(6, bool), eps)) == 0.0


def test_orientation_loss_penalises_only_back_facing_normals():
    aux, _, _ = _hard_aux(np.random.default_rng(2))
    facing = aux.replace(pred_normal=-aux.view_dir)
    assert float(orientation_loss(facing)) == 0.0
    away = aux.replace(pred_normal=aux.view_dir)
    expected = float(jnp.mean(jnp.sum(jnp.where(aux.valid, aux.weights, 0.0), -1)))
    assert float(orientation_loss(away)) == pytest.approx(expected, rel=1e-5)

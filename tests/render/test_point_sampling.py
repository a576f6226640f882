"""The paper's ablation "- integration + traditional point sampling" (``RenderConfig.integration =
"samples"``): every sample of a segment shaded on its own and composited as its own ``1/s``
sub-interval, against the segment (integration) mode, a float64 reference, gradients, compiles and
the training step.

One image is one chunk (``chunk = RES * RES``): :func:`render_all` (one ``render_rays`` call over
every ray of the image), ``render_image`` and ``render_chunked`` run the same compiled chunk for a
given config and capacities."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ne_jax.data import cameras
from ne_jax.data.rays import Camera, Rays, camera_rays
from ne_jax.devices import default_mesh
from ne_jax.geometry.intersect import intersect
from ne_jax.geometry.knn import knn_interpolate
from ne_jax.geometry.points import PointState
from ne_jax.render.driver import _render_chunk, render_chunked, render_image
from ne_jax.render.quadrature import QuadratureConfig, level_samples, sample_intervals
from ne_jax.render.renderer import PointScene, RenderConfig, render_rays, render_rays_with_aux
from ne_jax.render.shading import init_color_model, shade
from ne_jax.train import TrainConfig, init_train_state, make_train_step
from ne_jax.train.sampler import Batch

from tests.mini_presets import tiny_caps, tiny_render
from tests.render.scenes import glossy_model

RES = 16
BG = jnp.array([1.0, 1.0, 1.0])
SAMPLES = "samples"
_render_rays = jax.jit(render_rays, static_argnums=0)
_render_aux = jax.jit(render_rays_with_aux, static_argnums=0)


def render_all(cfg, params, scene, rays, background=BG):
    """One :func:`render_rays` call over every ray (``[RES * RES]``): the program ``render_chunked``
    compiles for a chunk of them (per-ray background, the default mesh)."""
    bg = jnp.broadcast_to(jnp.asarray(background, jnp.float32), (rays.num_rays, 3))
    return _render_chunk(cfg, params, scene, rays, bg, mesh=default_mesh())


def with_caps(scene, **changes):
    return scene.replace(capacities=scene.capacities.replace(**changes))


def _stochastic(cfg: RenderConfig) -> RenderConfig:
    return cfg.replace(quadrature=QuadratureConfig(rule="stochastic",
                                                   samples_per_level=cfg.quadrature.samples_per_level))


@pytest.fixture(scope="module")
def setup():
    cfg = tiny_render(chunk=RES * RES)  # one image = one chunk
    params, scene = glossy_model(cfg)
    # 2 segments per ray hold an image's (1.1 per ray); a starved budget grows into it
    scene = with_caps(scene, segments_per_ray=2.0)
    camera = Camera.from_fov(cameras.orbit_cameras(8)[1], RES, RES, cameras.CAMERA_ANGLE_X)
    return cfg, params, scene, camera


def test_config_validates_the_field():
    with pytest.raises(ValueError, match="integration"):
        RenderConfig(integration="points")
    assert RenderConfig().integration == "segment"
    assert tiny_render(integration=SAMPLES).integration == SAMPLES


def test_sample_positions_are_sub_interval_midpoints_or_stratified():
    q = QuadratureConfig(samples_per_level=(3, 5))
    t_lo = jnp.asarray([1.0, 2.0, 0.5])
    t_hi = jnp.asarray([1.3, 3.0, 0.5])
    level = jnp.asarray([0, 1, 1])
    t, inside, s = sample_intervals(q, t_lo, t_hi, level)
    np.testing.assert_array_equal(np.asarray(s)[:, 0], [3, 5, 5])
    np.testing.assert_array_equal(np.asarray(inside), [[1, 1, 1, 0, 0], [1] * 5, [1] * 5])
    np.testing.assert_allclose(np.asarray(t[0, :3]), 1.0 + 0.3 * (np.arange(3) + 0.5) / 3, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(t[1]), 2.0 + (np.arange(5) + 0.5) / 5, rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(t[2]), 0.5)  # zero-length segment
    # stochastic: one sample inside each sub-interval, the same draws as the segment mode's rule
    qs = QuadratureConfig(rule="stochastic", samples_per_level=(3, 5))
    key = jax.random.key(4)
    ts, inside_s, _ = sample_intervals(qs, t_lo, t_hi, level, key)
    ref, w = level_samples(qs, t_lo, t_hi, level, key)
    np.testing.assert_array_equal(np.asarray(ts), np.asarray(ref))
    np.testing.assert_array_equal(np.asarray(inside_s), np.asarray(w) > 0)
    u = (np.asarray(ts[1]) - 2.0) * 5
    assert np.all((u >= np.arange(5) - 1e-5) & (u <= np.arange(5) + 1 + 1e-5))
    with pytest.raises(ValueError, match="PRNG key"):
        sample_intervals(qs, t_lo, t_hi, level)


@pytest.mark.parametrize("rule", ["hermite", "stochastic"])
def test_field_constant_along_rays_renders_as_the_segment_mode(setup, rule):
    """Every point with the same feature and normal: density and colour are constant along a ray, and
    ``s`` sub-intervals of length ``L/s`` composite exactly like one interval of length ``L``.
    Tolerance 1e-5: float32 rounding of the KNN weights' sum (observed max |diff| ~2e-7)."""
    cfg, params, scene, camera = setup
    if rule == "stochastic":
        cfg = _stochastic(cfg)
    p = scene.points
    f = jnp.asarray(np.random.default_rng(1).normal(0, 0.5, p.feature.shape[1]), jnp.float32)
    n = jnp.asarray([0.6, 0.0, 0.8], jnp.float32)
    const = scene.replace(points=p.replace(feature=jnp.broadcast_to(f, p.feature.shape),
                                           normal=jnp.broadcast_to(n, p.normal.shape)))
    rays = camera_rays(camera, cameras.NEAR, cameras.FAR)
    if rule == "stochastic":
        render = functools.partial(_render_rays, background=BG, key=jax.random.key(2))
    else:  # the compiled chunk of the other tests
        render = render_all
    a = render(cfg, params, const, rays)
    b = render(cfg.replace(integration=SAMPLES), params, const, rays)
    op = np.asarray(a.opacity)
    assert op.max() > 0.5 and (op == 0).any()  # the test means something: surfaces and misses
    for name in ("rgb", "opacity", "normal"):
        np.testing.assert_allclose(np.asarray(getattr(b, name)), np.asarray(getattr(a, name)), atol=1e-5, err_msg=name)
    for name in ("num_segments",):
        np.testing.assert_array_equal(np.asarray(getattr(b, name)), np.asarray(getattr(a, name)))
    for name in ("frontier", "slots", "packing", "emitted"):
        np.testing.assert_array_equal(np.asarray(getattr(b.lost, name)), np.asarray(getattr(a.lost, name)))
    # and with the scene's own (varying) features the two modes do differ: the switch does something
    c = render(cfg, params, scene, rays)
    d = render(cfg.replace(integration=SAMPLES), params, scene, rays)
    assert float(jnp.abs(c.rgb - d.rgb).max()) > 1e-3


# ---------------------------------------------------------------- float64 reference


def _two_plane_scene(cfg):
    """Hand-made: two 12x12 point grids at z = 0 and z = 0.5, random features and confidences."""
    g = (np.arange(12) - 5.5) * 0.1
    xx, yy = np.meshgrid(g, g, indexing="ij")
    xyz = np.concatenate([np.stack([xx.ravel(), yy.ravel(), np.full(xx.size, z)], -1) for z in (0.0, 0.5)])
    rng = np.random.default_rng(3)
    points = PointState.from_numpy(xyz.astype(np.float32), capacity=300, feature_dim=cfg.shading.feature_dim,
                                   normal=np.tile([0.0, 0.0, 1.0], (len(xyz), 1)).astype(np.float32))
    points = points.replace(feature=jnp.asarray(rng.normal(0, 0.7, points.feature.shape), jnp.float32),
                            conf_logit=jnp.asarray(rng.normal(0, 1, points.conf_logit.shape), jnp.float32))
    return PointScene.build(points, cfg, tiny_caps())


_shade = jax.jit(shade, static_argnums=0)


def _two_plane_rays():
    """Four rays straight down at ``x, y`` (the last one misses both planes) and one oblique ray."""
    xy = np.asarray([[0.05, 0.05], [-0.23, 0.31], [0.4, -0.12], [2.0, 2.0]])  # the last one misses
    origin = np.concatenate([xy, np.full((4, 1), 2.0)], -1)
    direction = np.tile([0.0, 0.0, -1.0], (4, 1))
    oblique = np.asarray([0.6, 0.2, -0.75])
    origin = np.concatenate([origin, [[-0.3, -0.1, 1.0]]])
    direction = np.concatenate([direction, [oblique / np.linalg.norm(oblique)]])
    return Rays(origin=jnp.asarray(origin, jnp.float32), direction=jnp.asarray(direction, jnp.float32),
                near=jnp.zeros(5), far=jnp.full(5, 4.0))


def _reference(cfg, params, scene, rays, background):
    """Per-sample compositing in float64 with a plain loop: segments as ``intersect`` emits them,
    sample ``j`` of ``s`` at the midpoint of sub-interval ``j``, its own KNN feature and shading
    (the library's, float32), alpha ``1 - exp(-sigma L / s)`` front to back. Also returns the
    segments."""
    seg = jax.device_get(intersect(scene.tree, rays, cfg.kdtree, scene.capacities))
    spacing = float(scene.tree.spacing)
    depth = int(scene.tree.depth)
    o = np.asarray(rays.origin, np.float64)
    d = np.asarray(rays.direction, np.float64)
    bg = np.asarray(background, np.float64)
    rgb, opacity, dep, weights = [], [], [], []
    for r in range(o.shape[0]):
        trans, color, depth_sum, w_ray = 1.0, np.zeros(3), 0.0, []
        for i in np.flatnonzero(seg.valid[r]):
            lo, hi = float(seg.t_lo[r, i]), float(seg.t_hi[r, i])
            s = cfg.quadrature.samples_per_level[depth - 1 - int(seg.level[r, i])]
            t = lo + (np.arange(s) + 0.5) / s * (hi - lo)
            pos = o[r] + t[:, None] * d[r]
            vals, _ = knn_interpolate(scene.points, scene.tree, jnp.asarray(pos[None], jnp.float32),
                                      jnp.asarray([seg.node[r, i]]), cfg.kdtree, False,
                                      {"feature": scene.points.feature, "normal": scene.points.normal})
            view = jnp.broadcast_to(jnp.asarray(d[r], jnp.float32), (1, s, 3))
            sh = _shade(cfg.shading, params, vals["feature"], vals["normal"], view)
            sigma = np.asarray(sh.sigma[0], np.float64)
            c = np.asarray(sh.rgb[0], np.float64)
            for j in range(s):
                alpha = 1.0 - np.exp(-sigma[j] * (hi - lo) / s / spacing)
                w = trans * alpha
                color += w * c[j]
                depth_sum += w * t[j]
                w_ray.append(w)
                trans *= 1.0 - alpha
        rgb.append(color + trans * bg)
        opacity.append(1.0 - trans)
        dep.append(depth_sum / (1.0 - trans) if trans < 1.0 else 0.0)
        weights.append(np.asarray(w_ray))
    return np.asarray(rgb), np.asarray(opacity), np.asarray(dep), weights, seg


def test_matches_a_float64_per_sample_reference():
    """Unpacked (``segments_per_ray=None``) and packed (8.0) against one reference (the budget changes
    neither the tree nor the segments)."""
    base = tiny_render(integration=SAMPLES)
    scene = _two_plane_scene(base)
    params = init_color_model(base.shading, jax.random.key(5))
    rays = _two_plane_rays()
    bg = jnp.asarray([0.2, 0.4, 0.6])
    ref = _reference(base, params, scene, rays, bg)
    for segments_per_ray in (None, 8.0):
        budget = scene.replace(capacities=scene.capacities.replace(segments_per_ray=segments_per_ray))
        _check_against_reference(base, params, budget, rays, bg, ref)


def _check_against_reference(cfg, params, scene, rays, bg, ref):
    out, aux = _render_aux(cfg, params, scene, rays, bg)
    assert int(out.lost.count.sum()) == 0
    ref_rgb, ref_op, ref_depth, ref_w, seg = ref
    assert (np.asarray(out.num_segments)[:3] >= 2).all() and int(out.num_segments[3]) == 0
    assert 0.05 < ref_op[:3].min() and ref_op[4] > 0.05  # the test means something: partly opaque rays
    np.testing.assert_allclose(np.asarray(out.rgb), ref_rgb, atol=2e-5)
    np.testing.assert_allclose(np.asarray(out.opacity), ref_op, atol=2e-5)
    np.testing.assert_allclose(np.asarray(out.depth), ref_depth, atol=2e-5)
    # aux: one slot per sample, in ray order, the same weights
    m, ns = scene.capacities.max_segments, cfg.quadrature.max_samples
    assert aux.valid.shape == (5, m * ns) and aux.normal_moment.shape == (5, m * ns, 3, 3)
    valid = np.asarray(aux.valid)
    for r in range(5):
        np.testing.assert_allclose(np.asarray(aux.weights)[r][valid[r]], ref_w[r], atol=2e-5)
    np.testing.assert_array_equal(np.asarray(aux.weights)[~valid], 0.0)
    np.testing.assert_array_equal(np.asarray(aux.lengths)[~valid], 0.0)
    np.testing.assert_allclose(np.asarray(jnp.sum(aux.weights, -1)), np.asarray(out.opacity), atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(aux.pred_normal)[valid], axis=-1), 1.0, atol=1e-5)
    conf = np.asarray(aux.confidence)[valid]
    np.testing.assert_allclose(np.trace(np.asarray(aux.normal_moment)[valid], axis1=-2, axis2=-1), conf, atol=1e-5)
    # the sub-intervals of a segment tile it: lengths sum to the segments' lengths (the reference's:
    # the budget changes no segment)
    seg_len = np.where(seg.valid, seg.t_hi - seg.t_lo, 0.0).sum(-1) / float(scene.tree.spacing)
    np.testing.assert_allclose(np.asarray(aux.lengths).sum(-1), seg_len, rtol=1e-5, atol=1e-6)


# ---------------------------------------------------------------- budget, effects, gradients, compiles


def test_packing_drops_are_counted_then_grown(setup):
    """The scene's budget (2 segments per ray) changes nothing; one of 1/16 drops segments, counted
    per ray, and ``render_chunked`` grows it (to 2)."""
    cfg, params, scene, camera = setup
    cfg = cfg.replace(integration=SAMPLES)
    rays = camera_rays(camera, cameras.NEAR, cameras.FAR)
    full = render_all(cfg, params, with_caps(scene, segments_per_ray=None), rays)
    packed = render_all(cfg, params, scene, rays)
    np.testing.assert_allclose(np.asarray(packed.rgb), np.asarray(full.rgb), atol=1e-6)
    starved = render_all(cfg, params, with_caps(scene, segments_per_ray=1 / 16), rays)
    lost = int(starved.lost.packing.sum())
    assert lost > 0 and int(starved.num_segments.sum()) + lost == int(full.num_segments.sum())
    grown = render_chunked(cfg, params, with_caps(scene, segments_per_ray=1 / 16), rays, BG)  # one chunk
    assert int(grown.lost.count.sum()) == 0
    np.testing.assert_allclose(np.asarray(grown.rgb), np.asarray(full.rgb), atol=1e-6)


def test_undeclared_ist_is_not_computed(setup):
    cfg, params, scene, camera = setup
    cfg = cfg.replace(integration=SAMPLES)
    rays = camera_rays(camera, cameras.NEAR, cameras.FAR)
    poisoned = scene.replace(points=scene.points.replace(ist=jnp.full_like(scene.points.ist, jnp.nan)))
    assert np.isfinite(np.asarray(render_all(cfg, params, poisoned, rays).rgb)).all()
    assert not np.isfinite(np.asarray(render_all(cfg.with_effects(ist=True), params, poisoned, rays).rgb)).all()


@pytest.mark.parametrize("rule", ["hermite", "stochastic"])
def test_gradients_are_finite_and_reach_params_and_points(setup, rule):
    cfg, params, scene, camera = setup
    cfg = cfg.replace(integration=SAMPLES)
    if rule == "stochastic":
        cfg = _stochastic(cfg)
    key = jax.random.key(9) if rule == "stochastic" else None
    rays = camera_rays(camera, cameras.NEAR, cameras.FAR)
    target = jnp.full((rays.num_rays, 3), 0.3)

    def loss(params, xyz, feature, conf_logit):
        pts = scene.points.replace(xyz=xyz, feature=feature, conf_logit=conf_logit)
        out = render_rays(cfg, params, scene.replace(points=pts), rays, BG, key)
        return jnp.mean((out.rgb - target) ** 2)

    p = scene.points
    grads = jax.jit(jax.grad(loss, argnums=(0, 1, 2, 3)))(params, p.xyz, p.feature, p.conf_logit)
    for g in jax.tree_util.tree_leaves(grads):
        assert np.isfinite(np.asarray(g)).all()
    g_params, g_xyz, g_feat, g_conf = grads
    assert any(float(jnp.abs(x).max()) > 0 for x in jax.tree_util.tree_leaves(g_params))
    for g in (g_xyz, g_feat, g_conf):
        assert float(jnp.abs(g).max()) > 0


def test_repeated_renders_do_not_recompile(setup):
    """``render_image`` with new poses, features and background, and ``render_rays_with_aux`` (on
    the two-plane scene packed as in the reference test) with new features and rays: nothing
    compiles again."""
    cfg, params, scene, camera = setup
    cfg = cfg.replace(integration=SAMPLES)
    other = Camera.from_fov(cameras.orbit_cameras(8)[5], RES, RES, cameras.CAMERA_ANGLE_X)
    moved = scene.replace(points=scene.points.replace(feature=scene.points.feature * 0.5))
    calls = [(scene, camera, BG), (moved, other, jnp.zeros(3))]
    first = render_image(cfg, params, scene, camera, BG, cameras.NEAR, cameras.FAR)
    assert first.rgb.shape == (RES, RES, 3) and np.isfinite(np.asarray(first.rgb)).all()
    size = _render_chunk._cache_size()
    for args in calls * 2:
        render_image(cfg, params, args[0], args[1], args[2], cameras.NEAR, cameras.FAR)
    assert _render_chunk._cache_size() == size
    base = tiny_render(integration=SAMPLES)
    planes = with_caps(_two_plane_scene(base), segments_per_ray=8.0)
    rays = _two_plane_rays()
    _render_aux(base, params, planes, rays, BG)
    size = _render_aux._cache_size()
    moved_planes = planes.replace(points=planes.points.replace(feature=planes.points.feature * 0.5))
    other_rays = rays.replace(origin=rays.origin + 0.01, direction=rays.direction[::-1])
    _render_aux(base, params, moved_planes, other_rays, jnp.zeros(3))
    assert _render_aux._cache_size() == size


# ---------------------------------------------------------------- training step


def test_training_step_runs_with_point_sampling(setup):
    """The stochastic rule only (the step's one rule-dependent path: the render key it splits off);
    the render's gradients under both rules are checked above."""
    cfg, _, scene, camera = setup
    cfg = _stochastic(cfg.replace(integration=SAMPLES))
    tcfg = TrainConfig()
    state = init_train_state(tcfg, cfg, scene.points, jax.random.key(1), total_steps=100)
    step_fn = make_train_step(tcfg, cfg, total_steps=100)
    rays = camera_rays(camera, cameras.NEAR, cameras.FAR)
    target = jnp.concatenate([jnp.full((rays.num_rays, 3), 0.4), jnp.ones((rays.num_rays, 1))], -1)
    batch = Batch(rays=rays.replace(target=target), pixel=jnp.arange(rays.num_rays, dtype=jnp.int32),
                  in_band=jnp.zeros(rays.num_rays, bool), background=BG)
    losses = []
    for _ in range(3):
        state, metrics = step_fn(state, scene, batch)
        assert bool(metrics["ok"]), metrics
        assert all(bool(v) for k, v in metrics.items() if k.startswith("finite/"))
        losses.append(float(metrics["loss/total"]))
    assert np.isfinite(losses).all() and int(state.step) == 3 and int(state.skipped) == 0
    assert float(metrics["loss/orientation"]) >= 0 and float(metrics["loss/normal"]) >= 0
    assert step_fn._cache_size() == 1

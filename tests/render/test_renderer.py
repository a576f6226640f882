"""The joined renderer (intersect -> samples -> KNN -> integrate -> shade -> composite) on a
benchmark scene with a random model: coverage, packing, overflow, effects, gradients, compiles."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ne_jax.benchmark import raycaster
from ne_jax.benchmark import scenes as S
from ne_jax.compiles import count_compiles
from ne_jax.data import cameras
from ne_jax.data.rays import Camera, Rays, camera_rays
from ne_jax.geometry.capacity import Capacities
from ne_jax.render.driver import _render_chunk, render_chunked, render_image
from ne_jax.render.renderer import RenderConfig, render_rays
from ne_jax.render.shading import init_color_model

from tests.mini_presets import tiny_render
from tests.render.scenes import glossy_model

RES = 24
BG = jnp.array([1.0, 1.0, 1.0])
render = jax.jit(render_rays, static_argnums=0)
"""``render_rays`` as one compiled program (called eagerly it compiles each of its operations)."""


@pytest.fixture(scope="module")
def setup():
    cfg = tiny_render()
    params, scene = glossy_model(cfg)
    c2w = cameras.orbit_cameras(8)[1]
    camera = Camera.from_fov(c2w, RES, RES, cameras.CAMERA_ANGLE_X)
    scene_gt = S.get_scene("glossy", 0.5)
    alpha = raycaster.RayCaster(S.apply_to_mesh(scene_gt.mesh, None), scene_gt.materials).render(
        c2w, RES, RES, cameras.CAMERA_ANGLE_X, ss=1)[..., 3]
    return cfg, params, scene, camera, alpha


def test_random_model_renders_a_benchmark_camera(setup):
    cfg, params, scene, camera, alpha = setup
    out = render_image(cfg, params, scene, camera, BG, cameras.NEAR, cameras.FAR)
    assert out.rgb.shape == (RES, RES, 3) and out.opacity.shape == (RES, RES)
    for leaf in jax.tree_util.tree_leaves(out):
        assert np.all(np.isfinite(np.asarray(leaf, np.float64)))
    op = np.asarray(out.opacity)
    assert op[alpha == 1].mean() > 0.5 and op[alpha == 0].mean() < 0.05
    empty = np.asarray(out.num_segments) == 0
    assert empty.sum() > RES * RES / 4
    np.testing.assert_array_equal(np.asarray(out.rgb)[empty], np.ones((empty.sum(), 3)))  # pure background
    np.testing.assert_array_equal(op[empty], 0.0)
    assert int(jnp.max(out.lost.count)) == 0


def test_packing_changes_nothing_and_drops_are_counted_then_grown(setup):
    cfg, params, scene, camera, _ = setup
    rays = camera_rays(camera, cameras.NEAR, cameras.FAR)
    def budget(b):
        return scene.replace(capacities=scene.capacities.replace(segments_per_ray=b))

    full = render(cfg, params, budget(None), rays, BG)
    packed = render(cfg, params, budget(8.0), rays, BG)
    np.testing.assert_allclose(np.asarray(packed.rgb), np.asarray(full.rgb), atol=1e-6)
    assert int(packed.lost.packing.sum()) == 0
    starved = render(cfg, params, budget(0.05), rays, BG)
    lost = int(starved.lost.packing.sum())
    assert lost > 0 and int(starved.num_segments.sum()) + lost == int(full.num_segments.sum())
    assert int(starved.lost.frontier.sum()) == 0 and int(starved.lost.slots.sum()) == 0
    grown = render_chunked(cfg.replace(chunk=RES * RES), params, budget(0.05), rays, BG)
    assert int(grown.lost.count.sum()) == 0
    np.testing.assert_allclose(np.asarray(grown.rgb), np.asarray(full.rgb), atol=1e-6)


def test_traversal_overflow_is_reported_then_grown(setup):
    cfg, params, scene, camera, _ = setup
    rays = camera_rays(camera, cameras.NEAR, cameras.FAR)
    def slots(m):
        return scene.replace(capacities=scene.capacities.replace(max_segments=m))

    out = render(cfg, params, slots(2), rays, BG)
    assert int(out.lost.slots.max()) > 0
    ref = render(cfg, params, slots(64), rays, BG)
    grown = render_chunked(cfg.replace(chunk=RES * RES), params, slots(2), rays, BG, max_grow=6)
    assert int(grown.lost.count.max()) == 0
    np.testing.assert_allclose(np.asarray(grown.rgb), np.asarray(ref.rgb), atol=1e-6)


def test_undeclared_effects_are_not_computed(setup):
    """Poison the arrays an undeclared effect would read: NaN would reach the image even if the
    branch were only multiplied by zero."""
    cfg, params, scene, camera, _ = setup
    rays = camera_rays(camera, cameras.NEAR, cameras.FAR)
    poisoned = scene.replace(points=scene.points.replace(ist=jnp.full_like(scene.points.ist, jnp.nan)))
    out = render(cfg, params, poisoned, rays, BG)  # tiny preset: IST not declared
    assert np.isfinite(np.asarray(out.rgb)).all()
    diffuse = cfg.with_effects(specular=False)
    p_diffuse = init_color_model(diffuse.shading, jax.random.key(0))
    no_normals = poisoned.replace(points=poisoned.points.replace(normal=jnp.full_like(scene.points.normal, jnp.nan)))
    assert np.isfinite(np.asarray(render(diffuse, p_diffuse, no_normals, rays, BG).rgb)).all()
    # and the declared effect does read them
    assert not np.isfinite(np.asarray(render(cfg.with_effects(ist=True), params, poisoned, rays, BG).rgb)).all()


def test_identity_ist_renders_like_no_ist(setup):
    cfg, params, scene, camera, _ = setup
    rays = camera_rays(camera, cameras.NEAR, cameras.FAR)
    a = render(cfg, params, scene, rays, BG)
    b = render(cfg.with_effects(ist=True), params, scene, rays, BG)
    # KNN-weighted means of identities are identity up to rounding of the weights' sum.
    np.testing.assert_allclose(np.asarray(b.rgb), np.asarray(a.rgb), atol=2e-6)


def test_gradients_are_finite_and_reach_everything(setup):
    cfg, params, scene, camera, alpha = setup
    rays = camera_rays(camera, cameras.NEAR, cameras.FAR)
    hit = np.flatnonzero(alpha.reshape(-1) == 1)[:64]
    miss = np.flatnonzero(alpha.reshape(-1) == 0)[:8]
    rays = rays.take(jnp.asarray(np.concatenate([hit, miss])))
    target = jnp.full((rays.num_rays, 3), 0.3)

    def loss(params, xyz, feature, conf_logit, origin):
        pts = scene.points.replace(xyz=xyz, feature=feature, conf_logit=conf_logit)
        out = render_rays(cfg, params, scene.replace(points=pts), rays.replace(origin=origin), BG)
        return jnp.mean((out.rgb - target) ** 2)

    p = scene.points
    grads = jax.jit(jax.grad(loss, argnums=(0, 1, 2, 3, 4)))(params, p.xyz, p.feature, p.conf_logit, rays.origin)
    for g in jax.tree_util.tree_leaves(grads):
        assert np.isfinite(np.asarray(g)).all()
    g_params, g_xyz, g_feat, g_conf, g_origin = grads
    assert any(float(jnp.abs(x).max()) > 0 for x in jax.tree_util.tree_leaves(g_params))
    for g in (g_xyz, g_feat, g_conf, g_origin):
        assert float(jnp.abs(g).max()) > 0


def test_repeated_renders_do_not_recompile(setup):
    """Same capacities, new poses, features and background: the compiled chunk is reused (a chunk
    that overflowed may add one compile for its grown budget, once)."""
    cfg, params, scene, camera, _ = setup
    other = Camera.from_fov(cameras.orbit_cameras(8)[5], RES, RES, cameras.CAMERA_ANGLE_X)
    moved = scene.replace(points=scene.points.replace(feature=scene.points.feature * 0.5))
    calls = [(scene, camera, BG), (moved, other, jnp.zeros(3))]
    for args in calls:
        render_image(cfg, params, args[0], args[1], args[2], cameras.NEAR, cameras.FAR)
    size = _render_chunk._cache_size()
    for args in calls:
        render_image(cfg, params, args[0], args[1], args[2], cameras.NEAR, cameras.FAR)
    assert _render_chunk._cache_size() == size


def test_stochastic_rule_needs_a_key_and_no_chunked_render(setup):
    cfg, params, scene, camera, _ = setup
    sto = cfg.replace(quadrature=cfg.quadrature.__class__(rule="stochastic", samples_per_level=(4, 6, 8)))
    rays = camera_rays(camera, cameras.NEAR, cameras.FAR).take(slice(0, 16))
    with pytest.raises(ValueError, match="PRNG key"):
        render_rays(sto, params, scene, rays, BG)
    out = render(sto, params, scene, rays, BG, key=jax.random.key(3))
    assert np.isfinite(np.asarray(out.rgb)).all()
    with pytest.raises(ValueError, match="stochastic"):
        render_chunked(sto, params, scene, rays, BG)


def test_config_errors_name_the_field():
    from ne_jax.render.quadrature import QuadratureConfig

    with pytest.raises(ValueError, match="samples_per_level"):
        RenderConfig(quadrature=QuadratureConfig(samples_per_level=(8, 11)))
    with pytest.raises(ValueError, match="Capacities.segments_per_ray"):
        Capacities(segments_per_ray=0.0)


def test_rays_that_miss_everything_are_background(setup):
    cfg, params, scene, _, _ = setup
    rays = Rays(origin=jnp.array([[10.0, 10.0, 10.0], [0.0, 0.0, 5.0]]),
                direction=jnp.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
                near=jnp.array([0.0, 0.0]), far=jnp.array([10.0, 10.0]))
    out = render(cfg, params, scene, rays, jnp.array([0.2, 0.4, 0.6]))
    np.testing.assert_array_equal(np.asarray(out.rgb), np.float32([[0.2, 0.4, 0.6]] * 2))
    np.testing.assert_array_equal(np.asarray(out.opacity), [0.0, 0.0])


def test_chunked_render_shades_only_the_rays_that_meet_the_cloud(setup, monkeypatch):
    """The first stage walks every ray; only rays with a segment reach the render, in full chunks:
    ceil(hits / chunk) render calls (one per chunk of all rays in a one-stage render), and the
    misses are the background."""
    import ne_jax.render.driver as R

    cfg, params, scene, camera, _ = setup
    rays = camera_rays(camera, cameras.NEAR, cameras.FAR)
    calls = []
    real = R._render_chunk_maybe_checked
    monkeypatch.setattr(R, "_render_chunk_maybe_checked", lambda *a: calls.append(a[3]) or real(*a))
    out = render_chunked(cfg.replace(chunk=64), params, scene, rays, BG)
    hits = int((np.asarray(out.num_segments) > 0).sum())
    assert 0 < hits < rays.num_rays - 64  # at least one chunk of rays with nothing to shade
    chunks = {id(r): r.num_rays for r in calls}  # a chunk that lost is rendered again with grown capacities
    assert sorted(chunks.values()) == [64] * -(-hits // 64)
    miss = np.asarray(out.num_segments) == 0
    np.testing.assert_array_equal(np.asarray(out.rgb)[miss], np.ones((int(miss.sum()), 3), np.float32))
    np.testing.assert_array_equal(np.asarray(out.opacity)[miss], 0.0)


def test_chunked_render_equals_one_call(setup):
    """render_chunked (chunks of rays, a two-pass walk whose retry share grows until it fits, a
    packing budget per chunk) must give what one render_rays call over every ray gives, without
    packing, for a per-ray background too."""
    cfg, params, scene, camera, _ = setup
    rays = camera_rays(camera, cameras.NEAR, cameras.FAR)
    bg = jax.random.uniform(jax.random.key(4), (rays.num_rays, 3))
    ref = render(cfg, params, scene.replace(capacities=scene.capacities.replace(segments_per_ray=None)), rays, bg)
    narrow = scene.replace(capacities=scene.capacities.replace(first_pass_frontier=2))  # most hit rays walk twice
    out = render_chunked(cfg.replace(chunk=64), params, narrow, rays, bg)
    assert int(out.lost.count.sum()) == 0 and int(ref.lost.count.sum()) == 0
    np.testing.assert_array_equal(np.asarray(out.num_segments), np.asarray(ref.num_segments))
    assert 0 < int((out.num_segments > 0).sum()) < rays.num_rays
    for a, b in zip(jax.tree_util.tree_leaves(out), jax.tree_util.tree_leaves(ref)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6, atol=1e-6)


def test_pixel_grid_image_is_the_mean_of_a_finer_image(setup):
    """``pixel_samples=2``: each pixel is the mean of the 2 x 2 pixels of the same camera at twice the
    resolution (the same rays); segments are summed and what was lost stays per ray."""
    cfg, params, scene, camera, _ = setup
    fine_camera = camera.replace(fx=2 * camera.fx, fy=2 * camera.fy, cx=2 * camera.cx, cy=2 * camera.cy,
                                 width=2 * RES, height=2 * RES)
    fine = render_image(cfg, params, scene, fine_camera, BG, cameras.NEAR, cameras.FAR)
    with count_compiles() as compiled:  # the same rays in the same chunks: the grid compiles no render
        out = render_image(cfg.replace(pixel_samples=2), params, scene, camera, BG, cameras.NEAR, cameras.FAR)
    assert "jit(_render_chunk)" not in compiled.names, compiled.names
    blocks = lambda a, reduce: reduce(np.asarray(a, np.float64).reshape(RES, 2, RES, 2, *a.shape[2:]), axis=(1, 3))  # noqa: E731
    for name in ("rgb", "opacity", "depth", "normal"):
        np.testing.assert_allclose(np.asarray(getattr(out, name)), blocks(getattr(fine, name), np.mean), atol=1e-5)
    np.testing.assert_array_equal(np.asarray(out.num_segments), blocks(fine.num_segments, np.sum))
    assert out.rgb.shape == (RES, RES, 3) and out.lost.emitted.shape == (RES, RES, 4)
    assert int(out.lost.emitted.sum()) == int(fine.lost.emitted.sum()) > 0
    with pytest.raises(ValueError, match="pixel_samples"):
        RenderConfig(pixel_samples=0)

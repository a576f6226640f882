"""Naive Plotting against a float64 per-pixel loop, the hand-computed pixel of one point, culling
(behind the camera, outside [near, far], dead points, outside the image), pure background, occlusion
order at huge density, finite gradients, one compilation, and a benchmark camera end to end."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ne_jax.benchmark import raycaster
from ne_jax.benchmark import scenes as S
from ne_jax.data import cameras
from ne_jax.data.rays import Camera
from ne_jax.geometry.points import PointState
from ne_jax.render import naive
from ne_jax.render.naive import DEFAULT_SPLAT_RADIUS, naive_plot_image, splat_offsets
from ne_jax.render.renderer import PointScene, RenderConfig
from ne_jax.render.shading import background_color, init_color_model, shade

from tests.mini_presets import tiny_render

W, H = 16, 12
C = 75  # one capacity for most tests, so they share compilations
NEAR, FAR = 1.0, 4.0
BG = np.array([0.2, 0.4, 0.9], np.float32)


def _cfg(**effects) -> RenderConfig:
    return tiny_render().with_effects(**effects)


def _camera(c2w=None) -> Camera:
    """A non-square image with fx != fy and an off-centre principal point."""
    c2w = cameras.look_at((0.3, -2.5, 0.8)) if c2w is None else c2w
    return Camera(c2w=jnp.asarray(c2w, jnp.float32), fx=jnp.float32(13.0), fy=jnp.float32(11.0),
                  cx=jnp.float32(7.6), cy=jnp.float32(6.3), width=W, height=H)


def _cloud(n=70, seed=0, ist=False) -> PointState:
    """Random points around the origin (some project outside the image), a few dead ones."""
    rng = np.random.default_rng(seed)
    xyz = rng.uniform(-0.9, 0.9, size=(n, 3))
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    pts = PointState.from_numpy(xyz, capacity=max(C, n + 5), feature_dim=32, normal=nrm, key=jax.random.key(seed))
    pts = pts.delete(np.array([3, 17]))
    if ist:
        c = pts.capacity
        q, _ = np.linalg.qr(rng.normal(size=(c, 3, 3)))
        pts = pts.replace(ist=jnp.asarray(q * rng.uniform(0.8, 1.2, size=(c, 1, 1)), jnp.float32))
    return pts


def _scene(points: PointState) -> PointScene:
    """Naive Plotting reads only ``scene.points``; the tree is built as a user would."""
    return PointScene.build(points, tiny_render())


def naive_loop(cfg, params, points: PointState, camera: Camera, background, near, far, radius):
    """Slow float64 reference: per point its projection and shading, per pixel a walk over the
    points covering it in (distance, index) order."""
    xyz = np.asarray(points.xyz, np.float64)
    c2w = np.asarray(camera.c2w, np.float64)
    fx, fy, cx, cy = (float(v) for v in (camera.fx, camera.fy, camera.cx, camera.cy))
    rel = xyz - c2w[:3, 3]
    cam = rel @ c2w[:3, :3]
    z = -cam[:, 2]
    t = np.linalg.norm(rel, axis=1)
    ok = np.asarray(points.alive) & (z > 0) & (t >= near) & (t <= far)
    zs = np.where(z > 0, z, 1.0)
    u, v = cx + fx * cam[:, 0] / zs, cy - fy * cam[:, 1] / zs
    fx_ = cfg.shading.effects
    out = shade(cfg.shading, params, points.feature,
                points.normal if fx_.uses_point_normals else None,
                jnp.asarray(rel / np.maximum(t, 1e-30)[:, None], jnp.float32),
                points.ist if fx_.uses_ist else None)
    sigma = np.asarray(out.sigma, np.float64)
    rgb = np.asarray(out.rgb, np.float64)
    nrm = None if out.shading_normal is None else np.asarray(out.shading_normal, np.float64)
    h, w = camera.height, camera.width
    res = {"rgb": np.zeros((h, w, 3)), "opacity": np.zeros((h, w)), "depth": np.zeros((h, w)),
           "normal": np.zeros((h, w, 3)), "num_segments": np.zeros((h, w), int), "front": -np.ones((h, w), int)}
    for j in range(h):
        for i in range(w):
            inside = (np.floor(u) == i) & (np.floor(v) == j)
            near_center = (i + 0.5 - u) ** 2 + (j + 0.5 - v) ** 2 <= radius**2
            idx = np.flatnonzero(ok & (inside | near_center))
            idx = idx[np.argsort(t[idx], kind="stable")]
            trans, acc_t = 1.0, 0.0
            for p in idx:
                tau = min(sigma[p], 1e3)
                wgt = trans * -np.expm1(-tau)
                res["rgb"][j, i] += wgt * rgb[p]
                if nrm is not None:
                    res["normal"][j, i] += wgt * nrm[p]
                acc_t += wgt * t[p]
                trans *= np.exp(-tau)
            res["rgb"][j, i] += trans * np.asarray(background[j, i], np.float64)
            res["opacity"][j, i] = 1.0 - trans
            res["depth"][j, i] = acc_t / (1.0 - trans) if trans < 1.0 else 0.0
            res["num_segments"][j, i] = idx.size
            res["front"][j, i] = idx[0] if idx.size else -1
    res["point_rgb"] = rgb
    return res


def _bg_image(cfg, params, camera):
    from ne_jax.data.rays import camera_rays

    rays = camera_rays(camera, NEAR, FAR)
    bg = background_color(cfg.shading, params, rays.origin, rays.direction, jnp.asarray(BG))
    return np.asarray(bg).reshape(camera.height, camera.width, 3)


@pytest.mark.parametrize("radius,effects", [
    (0.0, {}),
    (1.0, {"ist": True}),
    (1.6, {"specular": False, "background_model": "sphere"}),
])
def test_matches_float64_loop(radius, effects):
    cfg = _cfg(**effects)
    params = init_color_model(cfg.shading, jax.random.key(1))
    pts = _cloud(ist=effects.get("ist", False))
    cam = _camera()
    out = naive_plot_image(cfg, params, _scene(pts), cam, BG, NEAR, FAR, splat_radius=radius)
    ref = naive_loop(cfg, params, pts, cam, _bg_image(cfg, params, cam), NEAR, FAR, radius)
    assert out.rgb.shape == (H, W, 3) and out.opacity.shape == (H, W) and out.normal.shape == (H, W, 3)
    assert out.rgb.dtype == jnp.float32
    np.testing.assert_array_equal(np.asarray(out.num_segments), ref["num_segments"])
    assert ref["num_segments"].max() >= 3 and (ref["num_segments"] == 0).any()  # overlaps and empty pixels
    np.testing.assert_allclose(np.asarray(out.rgb), ref["rgb"], atol=2e-6, rtol=1e-5)
    np.testing.assert_allclose(np.asarray(out.opacity), ref["opacity"], atol=2e-6, rtol=1e-5)
    np.testing.assert_allclose(np.asarray(out.depth), ref["depth"], atol=1e-5, rtol=1e-5)
    np.testing.assert_allclose(np.asarray(out.normal), ref["normal"], atol=2e-6, rtol=1e-5)
    assert not np.any(np.asarray(out.lost.count))


def test_single_point_lands_on_hand_computed_pixel():
    """Camera at the origin looking down -z, fx = fy = 10, (cx, cy) = (8, 6): the point
    (0.25, -0.25, -2) projects to (u, v) = (8 + 10 * 0.125, 6 + 10 * 0.125) = (9.25, 7.25)."""
    cfg = _cfg()
    params = init_color_model(cfg.shading, jax.random.key(0))
    pts = PointState.from_numpy(np.array([[0.25, -0.25, -2.0]]), capacity=C, feature_dim=32, key=jax.random.key(3))
    cam = Camera(c2w=jnp.eye(4), fx=jnp.float32(10.0), fy=jnp.float32(10.0), cx=jnp.float32(8.0),
                 cy=jnp.float32(6.0), width=W, height=H)
    scene = PointScene(points=pts, tree=None)
    out = naive_plot_image(cfg, params, scene, cam, BG, NEAR, FAR, splat_radius=0.0)
    expected = np.zeros((H, W), int)
    expected[7, 9] = 1  # row j = 7, column i = 9
    np.testing.assert_array_equal(np.asarray(out.num_segments), expected)
    assert 0.0 < float(out.opacity[7, 9]) < 1.0
    np.testing.assert_allclose(float(out.depth[7, 9]), np.sqrt(2 * 0.25**2 + 4.0), rtol=1e-6)
    # a disc of radius 1 also reaches the pixel centres (8.5, 7.5) and (9.5, 6.5), at distance 0.79,
    # not (8.5, 6.5) at 1.06 nor (10.5, 7.5) / (9.5, 8.5) at 1.27
    out = naive_plot_image(cfg, params, scene, cam, BG, NEAR, FAR, splat_radius=1.0)
    expected[7, 8] = expected[6, 9] = 1
    np.testing.assert_array_equal(np.asarray(out.num_segments), expected)


def test_splat_offsets_are_the_reachable_pixels():
    assert splat_offsets(0.0).tolist() == [[0, 0]]
    assert len(splat_offsets(0.5)) == 5  # edge neighbours: at exactly 0.5 from a point on the edge
    assert len(splat_offsets(1.5)) == 13  # the 3x3 block and (+-2, 0), (0, +-2); (2, 1) needs > 1.5
    with pytest.raises(ValueError, match="splat_radius"):
        splat_offsets(-1.0)


def test_culled_points_change_nothing():
    """Points behind the camera (whose mirrored projection lands inside the image), before ``near``,
    beyond ``far`` and outside the image render exactly as if they were dead."""
    cfg = _cfg()
    params = init_color_model(cfg.shading, jax.random.key(0))
    base = _cloud(n=40, seed=2)
    cam = _camera()
    c2w = np.asarray(cam.c2w, np.float64)
    o, fwd = c2w[:3, 3], -c2w[:3, 2]
    extra = np.stack([
        o - 1.5 * fwd, o - 0.5 * fwd + 0.05 * c2w[:3, 0],  # behind the camera
        o + 0.5 * fwd,  # before near
        o + 5.0 * fwd,  # beyond far
        o + 2.0 * fwd + 3.0 * c2w[:3, 0],  # outside the image, left-right
    ])
    xyz = np.concatenate([np.asarray(base.xyz)[:40], extra])
    pts = PointState.from_numpy(xyz, capacity=C, feature_dim=32, key=jax.random.key(2))
    pts = pts.replace(alive=pts.alive.at[np.array([3, 17])].set(False))
    dead = pts.replace(alive=pts.alive.at[40:].set(False))
    with_extra = naive_plot_image(cfg, params, _scene(pts), cam, BG, NEAR, FAR, 1.0)
    with_dead = naive_plot_image(cfg, params, _scene(dead), cam, BG, NEAR, FAR, 1.0)
    for field in ("rgb", "opacity", "depth", "normal", "num_segments"):
        np.testing.assert_array_equal(np.asarray(getattr(with_extra, field)), np.asarray(getattr(with_dead, field)),
                                      field)
    assert int(np.sum(with_extra.num_segments)) > 0


def test_deleted_points_are_ignored():
    """Deleting points equals a cloud that never had them (other slots keep their values)."""
    cfg = _cfg()
    params = init_color_model(cfg.shading, jax.random.key(0))
    pts = _cloud(seed=4)
    cam = _camera()
    gone = np.arange(0, 70, 3)
    deleted = naive_plot_image(cfg, params, _scene(pts.delete(gone)), cam, BG, NEAR, FAR, 1.0)
    keep = np.setdiff1d(np.flatnonzero(np.asarray(pts.alive)), gone)
    compact = jax.tree_util.tree_map(lambda a: a[keep], pts)  # re-padded with dead slots to capacity C
    compact = jax.tree_util.tree_map(lambda a, b: b.at[: len(keep)].set(a), compact,
                                     pts.replace(alive=jnp.zeros_like(pts.alive)))
    ref = naive_plot_image(cfg, params, _scene(compact), cam, BG, NEAR, FAR, 1.0)
    np.testing.assert_array_equal(np.asarray(deleted.num_segments), np.asarray(ref.num_segments))
    np.testing.assert_allclose(np.asarray(deleted.rgb), np.asarray(ref.rgb), atol=1e-6)
    full = naive_plot_image(cfg, params, _scene(pts), cam, BG, NEAR, FAR, 1.0)
    assert int(np.sum(full.num_segments)) > int(np.sum(deleted.num_segments))


def test_empty_view_is_pure_background():
    cfg = _cfg()
    params = init_color_model(cfg.shading, jax.random.key(0))
    pts = _cloud()
    away = cameras.look_at((0.0, -2.5, 0.0), target=(0.0, -5.0, 0.0))  # the cloud is behind this camera
    all_dead = PointScene(points=pts.replace(alive=jnp.zeros_like(pts.alive)), tree=None)  # no tree to build
    for scene, cam in [(_scene(pts), _camera(away)), (all_dead, _camera())]:
        out = naive_plot_image(cfg, params, scene, cam, BG, NEAR, FAR, 1.0)
        np.testing.assert_array_equal(np.asarray(out.rgb), np.broadcast_to(BG, (H, W, 3)))
        assert not np.any(np.asarray(out.opacity)) and not np.any(np.asarray(out.depth))
        assert not np.any(np.asarray(out.num_segments))


def test_huge_density_shows_the_front_point_exactly():
    """``sigma`` ~ 1e4 (density bias shifted; clamped at TAU_MAX): alpha is exactly 1, so each
    covered pixel is the colour of its nearest point (up to the float32 shading of that point) —
    occlusion order — and no background leaks through."""
    cfg = _cfg()
    params = init_color_model(cfg.shading, jax.random.key(0))
    params = {"shader": {**params["shader"], "density": {**params["shader"]["density"],
                                                          "bias": params["shader"]["density"]["bias"] + 1.0e4}}}
    pts = _cloud(seed=5)
    cam = _camera()
    out = naive_plot_image(cfg, params, _scene(pts), cam, BG, NEAR, FAR, 1.0)
    ref = naive_loop(cfg, params, pts, cam, np.broadcast_to(BG, (H, W, 3)), NEAR, FAR, 1.0)
    covered = ref["front"] >= 0
    assert covered.sum() > 20 and (ref["num_segments"] >= 2).sum() > 10
    front_rgb = ref["point_rgb"][ref["front"][covered]]
    np.testing.assert_allclose(np.asarray(out.rgb)[covered], front_rgb, atol=1e-6, rtol=0)
    np.testing.assert_array_equal(np.asarray(out.opacity)[covered], 1.0)
    np.testing.assert_array_equal(np.asarray(out.rgb)[~covered], np.broadcast_to(BG, (H, W, 3))[~covered])
    assert np.all(np.isfinite(np.asarray(out.depth)))


def test_gradients_finite():
    """Image loss -> params, features, confidences (exactly 0: one point per segment), normals,
    ISTs and positions, with overlapping splats, at ordinary densities, at vanishing ones (density
    bias -60: opacities ~1e-26, where the depth's ``1 / opacity^2`` would overflow) and at huge ones
    (bias +2000: every ``tau`` clamped at TAU_MAX). One compilation: the bias shift is a parameter."""
    cfg = _cfg(ist=True)
    params = init_color_model(cfg.shading, jax.random.key(0))
    pts = _cloud(seed=6, ist=True)
    scene = _scene(pts)
    cam = _camera()
    target = jnp.full((H, W, 3), 0.3)
    names = ("xyz", "feature", "conf_logit", "normal", "ist")

    @jax.jit
    def grads(params, arrays):
        def loss(params, arrays):
            points = pts.replace(**arrays)
            out = naive_plot_image(cfg, params, scene.replace(points=points), cam, BG, NEAR, FAR, 1.0)
            return (jnp.mean((out.rgb - target) ** 2) + 0.01 * jnp.mean(out.depth) + 0.01 * jnp.mean(out.normal),
                    out.opacity)
        return jax.grad(loss, argnums=(0, 1), has_aux=True)(params, arrays)

    for shift in (0.0, -60.0, 2.0e3):
        shifted = {"shader": {**params["shader"], "density": {**params["shader"]["density"],
                                                               "bias": params["shader"]["density"]["bias"] + shift}}}
        (g_params, g_points), opacity = grads(shifted, {n: getattr(pts, n) for n in names})
        opacity = np.asarray(opacity)
        if shift < 0:
            assert 0 < opacity.max() < 1e-20
        if shift > 1e3:
            assert set(np.unique(opacity)) == {0.0, 1.0}
        for leaf in jax.tree_util.tree_leaves((g_params, g_points)):
            assert np.all(np.isfinite(np.asarray(leaf))), shift
        assert any(np.any(np.asarray(x) != 0) for x in jax.tree_util.tree_leaves(g_params))
        moving = ("xyz", "normal", "ist") + (("feature",) if shift < 1e3 else ())  # a clamped tau stops
        for name in moving:  # the gradient through sigma, not through the colour
            assert np.any(np.asarray(g_points[name]) != 0), (shift, name)
        assert not np.any(np.asarray(g_points["conf_logit"]))
    assert grads._cache_size() == 1


def _view_dirs(pts: PointState, cam: Camera) -> jax.Array:
    rel = pts.xyz - cam.c2w[:3, 3]
    return rel / jnp.linalg.norm(rel, axis=-1, keepdims=True)


def test_compiles_once():
    cfg = _cfg(specular=False)  # the cheapest model to compile
    params = init_color_model(cfg.shading, jax.random.key(0))
    sizes = [naive._naive_plot._cache_size()]
    for seed, eye in [(7, (0.3, -2.5, 0.8)), (8, (-1.0, -2.2, 0.3)), (9, (2.0, 1.0, 1.0))]:
        pts = _cloud(n=80, seed=seed)  # capacity 85: no other test uses it
        out = naive_plot_image(cfg, params, PointScene(points=pts, tree=None), _camera(cameras.look_at(eye)),
                               np.asarray(BG) * seed / 10, NEAR + seed / 100, FAR, splat_radius=1.0)
        out.rgb.block_until_ready()
        sizes.append(naive._naive_plot._cache_size())
    assert sizes[1] == sizes[0] + 1 and sizes[-1] == sizes[1]  # new data, camera, background, near: no retrace


def test_glossy_benchmark_camera_end_to_end():
    """The ``tiny`` benchmark density (20k surface samples, 64x64) with a random model at the default
    splat radius: finite, opaque on the object's silhouette (from the ray caster), background away
    from it."""
    res, scene = 64, S.get_scene("glossy", 0.75)
    samples = S.surface_samples(scene, 20_000, seed=0)
    cfg = tiny_render()
    pts = PointState.from_numpy(samples["xyz"], feature_dim=32, normal=samples["normal"], key=jax.random.key(0))
    params = init_color_model(cfg.shading, jax.random.key(1))
    c2w = cameras.orbit_cameras(8)[3]
    cam = Camera.from_fov(c2w, res, res, cameras.CAMERA_ANGLE_X)
    out = naive_plot_image(cfg, params, PointScene.build(pts, cfg), cam, np.zeros(3), cameras.NEAR, cameras.FAR)
    for field in ("rgb", "opacity", "depth", "normal"):
        assert np.all(np.isfinite(np.asarray(getattr(out, field)))), field
    mask = raycaster.RayCaster(S.apply_to_mesh(scene.mesh, None), scene.materials).render(
        c2w, res, res, cameras.CAMERA_ANGLE_X, 1)[..., 3] > 0.5
    opacity = np.asarray(out.opacity)
    assert 0.1 < mask.mean() < 0.9
    assert np.all(opacity[mask] > 0.5)
    grown = mask.copy()  # splats may spill one footprint radius past the silhouette
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            grown |= np.roll(np.roll(mask, di, 0), dj, 1)
    np.testing.assert_array_equal(opacity[~grown], 0.0)
    np.testing.assert_array_equal(np.asarray(out.rgb)[~grown], 0.0)
    assert DEFAULT_SPLAT_RADIUS <= 1.0

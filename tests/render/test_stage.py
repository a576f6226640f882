"""The sample -> KNN -> shade stage (:mod:`ne_jax.render.stage`): what each lookup reads, that the
three lookups agree where they must, the nearest-neighbour distance against numpy, finite gradients,
and the growth scan under the runtime checks."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ne_jax.checks import NonFiniteError
from ne_jax.geometry.points import PointState
from ne_jax.render.renderer import PointScene
from ne_jax.render.shading import Effects
from ne_jax.render.stage import shade_own, shade_samples, shade_segments, values_needed

from tests.mini_presets import tiny_render
from tests.render.scenes import glossy_model, glossy_points

# The lookups compiled whole (one program per config and shape, shared by the tests).
_segments = jax.jit(shade_segments, static_argnums=0, static_argnames="aux")
_samples = jax.jit(shade_samples, static_argnums=0, static_argnames="aux")
_own = jax.jit(shade_own, static_argnums=0)


@pytest.fixture(scope="module")
def setup():
    cfg = tiny_render()
    params, scene = glossy_model(cfg)
    xyz = np.asarray(scene.points.xyz)[np.asarray(scene.points.alive)]
    rng = np.random.default_rng(0)
    # segments inside leaf voxels: samples near points of the cloud, each segment in the bottom
    # rendering-level node of its first sample (found by walking down the tree)
    pos = xyz[rng.choice(len(xyz), 6)][:, None, :] + rng.normal(0, 0.3, (6, 4, 3)) * float(scene.tree.spacing)
    node = _bottom_nodes(scene, pos[:, 0])
    view = rng.normal(size=(6, 3))
    view /= np.linalg.norm(view, axis=-1, keepdims=True)
    return cfg, params, scene, jnp.asarray(pos, jnp.float32), node, jnp.asarray(view, jnp.float32)


def _bottom_nodes(scene: PointScene, x: np.ndarray) -> jnp.ndarray:
    """Heap index of the bottom rendering-level node whose box holds each point of ``x [B, 3]``."""
    tree = scene.tree
    lo, hi = np.asarray(tree.lo), np.asarray(tree.hi)
    level = tree.depth - 1  # the bottom rendering level
    first = 2**level - 1
    nodes = np.arange(first, 2 ** (level + 1) - 1)
    out = []
    for p in x:
        inside = np.all((lo[nodes] <= p) & (p <= hi[nodes]), axis=-1)
        out.append(nodes[np.argmax(inside)] if inside.any() else nodes[0])
    return jnp.asarray(out, jnp.int32)


def test_values_needed_reads_only_the_declared_effects():
    points = glossy_points()
    plain = values_needed(points, Effects(specular=False, point_normals=False, ist=False))
    assert set(plain) == {"feature"}
    full = values_needed(points, Effects(specular=True, point_normals=True, ist=True), aux=True)
    assert set(full) == {"feature", "normal", "ist", "confidence", "normal_moment"}
    c = np.asarray(points.confidence)
    n = np.asarray(points.normal)
    np.testing.assert_allclose(np.asarray(full["normal_moment"]).reshape(-1, 3, 3),
                               c[:, None, None] * n[:, :, None] * n[:, None, :], rtol=1e-6, atol=1e-7)


def test_one_sample_segments_shade_as_their_samples(setup):
    """A segment of one sample with weight 1 is that sample: ``integrate`` == ``interpolate``."""
    cfg, params, scene, pos, node, view = setup
    one = pos[:, :1]
    seg = _segments(cfg, params, scene, one, node, jnp.ones((6, 1)), view, aux=True)
    smp = _samples(cfg, params, scene, one, node, view, aux=True)
    for a, b in ((seg.sigma, smp.sigma[:, 0]), (seg.rgb, smp.rgb[:, 0]),
                 (seg.values["confidence"], smp.values["confidence"][:, 0])):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=2e-5, atol=2e-6)


def test_segment_means_are_the_weighted_sum_of_the_sample_values(setup):
    cfg, params, scene, pos, node, view = setup
    w = jnp.asarray(np.random.default_rng(1).uniform(0, 1, (6, 4)), jnp.float32)
    seg = _segments(cfg, params, scene, pos, node, w, view)
    smp = _samples(cfg, params, scene, pos, node, view)
    mean = np.einsum("bs,bsf->bf", np.asarray(w, np.float64), np.asarray(smp.values["feature"], np.float64))
    np.testing.assert_allclose(np.asarray(seg.values["feature"]), mean, rtol=1e-4, atol=1e-5)
    assert seg.sigma.shape == (6,) and smp.sigma.shape == (6, 4) and seg.nearest is None


def test_nearest_is_the_exact_nearest_alive_point_with_exact_knn(setup):
    cfg, params, scene, pos, node, view = setup
    sh = _samples(cfg.replace(exact_knn=True), params, scene, pos, node, view)
    alive = np.asarray(scene.points.xyz, np.float64)[np.asarray(scene.points.alive)]
    ref = np.min(np.linalg.norm(np.asarray(pos, np.float64)[..., None, :] - alive, axis=-1), axis=-1)
    np.testing.assert_allclose(np.asarray(sh.nearest), ref, rtol=1e-5, atol=1e-6)


def test_own_lookup_shades_each_point_from_its_own_values(setup):
    cfg, params, scene, _, _, _ = setup
    points = scene.points
    view = jnp.broadcast_to(jnp.asarray([0.0, 0.0, -1.0]), points.xyz.shape)
    own = _own(cfg, params, points, view)
    np.testing.assert_array_equal(np.asarray(own.values["feature"]), np.asarray(points.feature))
    # the same point shaded alone, as a one-point cloud, interpolates to itself
    single = PointState.from_numpy(np.asarray(points.xyz[:1]), feature_dim=points.feature_dim,
                                   feature=np.asarray(points.feature[:1]), normal=np.asarray(points.normal[:1]))
    alone = _own(cfg, params, single, view[:1])
    np.testing.assert_allclose(np.asarray(alone.rgb[0]), np.asarray(own.rgb[0]), rtol=1e-6)


def test_gradients_are_finite_at_samples_on_points_and_zero_weights(setup):
    """Hard cases: a sample exactly on a point (zero distance), segments whose weights are all zero."""
    cfg, params, scene, pos, node, view = setup
    on_point = pos.at[0, 0].set(scene.points.xyz[int(np.flatnonzero(np.asarray(scene.points.alive))[0])])
    w = jnp.zeros((6, 4)).at[1:, :].set(0.25)

    def loss(feature, xyz):
        sc = scene.replace(points=scene.points.replace(feature=feature, xyz=xyz))
        a = shade_segments(cfg, params, sc, on_point, node, w, view, aux=True)
        b = shade_samples(cfg, params, sc, on_point, node, view)
        return jnp.sum(a.rgb) + jnp.sum(a.sigma) + jnp.sum(b.rgb) + jnp.sum(jnp.where(jnp.isfinite(b.nearest),
                                                                                   b.nearest, 0.0))

    g = jax.jit(jax.grad(loss, argnums=(0, 1)))(scene.points.feature, scene.points.xyz)
    assert all(np.isfinite(np.asarray(x)).all() for x in g)


def test_the_lookups_check_their_values_under_checks(setup):
    from ne_jax.checks import checked

    cfg, params, scene, pos, node, view = setup
    bad = scene.replace(points=scene.points.replace(feature=scene.points.feature.at[:].set(jnp.nan)))
    run = checked(lambda sc: shade_samples(cfg.replace(checks=True), params, sc, pos, node, view).sigma)
    run(scene)
    with pytest.raises(NonFiniteError, match="interpolation"):
        run(bad)

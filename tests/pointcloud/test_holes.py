"""Growth into holes: photo-consistent candidates along rays that meet no point."""

from __future__ import annotations

import numpy as np
import pytest

from ne_jax.benchmark.generate import generate_scene
from ne_jax.data.ply import read_ply
from ne_jax.data.scene import load_split
from ne_jax.pointcloud.holes import HoleSearch, box_stretch, hole_candidates
from ne_jax.pointcloud.init import Views, bilinear, visibility
from ne_jax.pointcloud.normals import mean_spacing

from tests.mini_presets import mini_benchmark


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    """This module's blocks scene (12 training views): its own folder, not whichever ``bench*`` folder
    another test module of the same worker left in the base temp directory."""
    root = tmp_path_factory.mktemp("bench")
    generate_scene("blocks", mini_benchmark(resolution=64, train_views=12, surface_samples=20_000), root, edits=())
    return root / "blocks"


@pytest.fixture(scope="module")
def scene(scene_dir):
    cols = read_ply(scene_dir / "points.ply")
    return Views.from_split(load_split(scene_dir, "train")), np.stack([cols[c] for c in "xyz"], 1).astype(np.float64)


def _patch_rays(views, surface, centre, radius):
    """Rays from view 0 to the surface samples of a patch that view 0 sees, with their colours."""
    in_patch = np.linalg.norm(surface - centre, axis=1) < radius
    seen = visibility(views, surface, mean_spacing(surface))[0]
    pts = surface[in_patch & seen]
    u, v, _ = views.project(0, pts)
    h, w = views.alpha.shape[1:]
    ok = (u > 1) & (u < w - 1) & (v > 1) & (v < h - 1) & (bilinear(views.alpha[0], u, v) > 0.99)
    pts, u, v = pts[ok], u[ok], v[ok]
    origin = np.repeat(views.c2w[0, :3, 3][None], len(pts), axis=0)
    direction = pts - origin
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    return origin, direction, bilinear(views.rgb[0], u, v), pts, in_patch


def test_a_cut_patch_is_found_again_on_the_surface(scene):
    views, surface = scene
    rng = np.random.default_rng(0)
    u, v, _ = views.project(0, surface)
    seen = visibility(views, surface, mean_spacing(surface))[0]
    centre = surface[seen][rng.integers(seen.sum())]
    origin, direction, target, truth, in_patch = _patch_rays(views, surface, centre, 0.25)
    assert len(truth) > 30
    cloud = surface[~in_patch]
    spacing = mean_spacing(cloud)
    xyz, cost, found = hole_candidates(HoleSearch(), views, origin, direction, target, cloud, 2 * spacing)
    assert found.mean() > 0.4  # many rays into the hole propose a point ...
    footprint = 4.0 * 2 * np.tan(0.5 * 0.69) / views.alpha.shape[2]  # a pixel at the cameras' distance
    err = np.linalg.norm(xyz[found] - truth[found], axis=1)
    assert np.median(err) < 3 * footprint  # ... on the surface that was cut
    assert np.all(np.isfinite(cost[found]))


def test_rays_past_the_object_or_near_points_propose_nothing(scene):
    views, surface = scene
    origin = np.repeat(views.c2w[0, :3, 3][None], 3, axis=0)
    centre = surface.mean(0)
    away = np.cross(centre - origin[0], [0.0, 0.0, 1.0])
    ahead = (centre - origin[0]) / np.linalg.norm(centre - origin[0])
    sideways = ahead + 2.0 * away / np.linalg.norm(away)  # misses the region of interest
    direction = np.stack([sideways / np.linalg.norm(sideways), ahead, ahead])
    target = np.full((3, 3), 0.5)
    _, _, found = hole_candidates(HoleSearch(), views, origin, direction, target, surface, 0.05)
    assert not found[0]  # no stretch inside the box
    assert not found[1:].any()  # the cloud is whole there: any candidate is within min_distance of a point


def test_box_stretch_against_a_loop():
    rng = np.random.default_rng(1)
    o = rng.normal(size=(50, 3)) * 3
    d = rng.normal(size=(50, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    lo, hi = np.array([-1.0, -0.5, -1.0]), np.array([1.0, 0.5, 2.0])
    st = box_stretch(o, d, lo, hi)
    ts = np.linspace(0, 20, 20001)
    for i in range(50):
        inside = np.all((o[i] + ts[:, None] * d[i] >= lo) & (o[i] + ts[:, None] * d[i] <= hi), axis=1)
        if inside.any():
            assert st[i, 0] == pytest.approx(ts[inside][0], abs=2e-3)
            assert st[i, 1] == pytest.approx(ts[inside][-1], abs=2e-3)
        else:
            assert st[i, 0] >= st[i, 1] - 1e-9


def test_a_round_refills_a_patch_cut_from_a_trained_cloud(scene, scene_dir, tmp_path_factory):
    """A model trained a few steps, its cloud with a patch cut out: a round with ``fill_holes``
    grows points back inside the patch (the plain scan alone adds few there, near its edge)."""
    import jax

    from ne_jax.pointcloud.rounds import point_round
    from ne_jax.render.renderer import PointScene
    from ne_jax.train.loop import train
    from ne_jax.train.sampler import build_pool, sample_batch

    from tests.mini_presets import short_run

    views, surface = scene
    run = short_run(steps_per_epoch=20)
    model = train(run, scene_dir, tmp_path_factory.mktemp("run") / "m", progress=False, log=lambda s: None)
    points = model.scene.points
    xyz = np.asarray(points.xyz)
    seen = visibility(views, xyz, mean_spacing(xyz[np.asarray(points.alive)]))[0]
    centre = xyz[np.flatnonzero(seen & np.asarray(points.alive))[0]]
    patch = np.linalg.norm(xyz - centre, axis=1) < 0.3
    cut = points.replace(alive=points.alive & ~patch)
    scene_cut = PointScene.build(cut, run.render, model.scene.capacities)
    pool = build_pool(run.sampler, load_split(scene_dir, "train"), run.background)
    # the rays through the patch: a random batch leaves the round's hole share to whichever rays
    # render worst after a short training, which need not be the patch's
    rays = sample_batch(run.sampler.replace(batch_size=32768), pool, jax.random.key(0)).rays
    o, d = np.asarray(rays.origin), np.asarray(rays.direction)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    off = (centre - o) - np.sum((centre - o) * d, axis=1, keepdims=True) * d
    near_patch = np.flatnonzero(np.linalg.norm(off, axis=1) < 0.3)[:2048]
    rays = jax.tree.map(lambda a: a[near_patch], rays)
    added = {}
    for fill in (False, True):
        cfg = run.rounds.replace(fill_holes=fill, grow_max_fraction=0.2, prune=False, denoise=False)
        new, report = point_round(cfg, run.render, model.params, scene_cut, rays, pool.background, views)
        fresh = np.asarray(new.alive)[: points.capacity] & ~np.asarray(cut.alive)
        fresh = np.concatenate([fresh, np.asarray(new.alive)[points.capacity:]])
        # the patch's inner part: the scan's voxels reach a little way in from the cut's edge
        inside = np.linalg.norm(np.asarray(new.xyz)[fresh] - centre, axis=1) < 0.2
        added[fill] = int(inside.sum())
        if fill:
            assert report["grown"]["holes"]["candidates"] > 0 and report["grown"]["holes"]["added"] > 0
    assert added[True] >= 10 and added[True] > 3 * added[False]

"""Initial clouds: carving an analytic sphere, carving errors, frusta, PLY and ground-truth loaders."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from ne_jax.data.ply import PlyError, write_ply
from ne_jax.pointcloud.init import (
    GT_SOURCE,
    CarveConfig,
    CarvingError,
    Views,
    bilinear,
    carve_occupancy,
    carve_visual_hull,
    ground_truth_cloud,
    hull_test,
    load_ply_cloud,
    photo_consistency,
    shell_voxels,
)
from ne_jax.pointcloud.metrics import chamfer

from .conftest import RADIUS, fibonacci_sphere, sphere_alpha

CFG = CarveConfig(resolution=48, bounds=((-1.0,) * 3, (1.0,) * 3), num_points=8000)
VOXEL = 2.0 / 48


def _surface_error(xyz: np.ndarray) -> np.ndarray:
    """Distance of each point to the sphere, in voxel sizes."""
    return np.abs(np.linalg.norm(xyz, axis=1) - RADIUS) / VOXEL


def test_carved_sphere_within_one_and_a_half_voxels(sphere):
    # No snapping: points are jittered inside shell voxels, so they lie within about a voxel of the
    # hull (measured: mean 0.48, 99th percentile 1.26, max 1.59 voxels).
    cloud = carve_visual_hull(dataclasses.replace(CFG, snap_steps=0), sphere)
    assert cloud.source == "carving" and cloud.normals is None and not cloud.is_ground_truth
    assert cloud.xyz.shape == (8000, 3) and cloud.xyz.dtype == np.float32
    err = _surface_error(cloud.xyz)
    assert np.percentile(err, 99) < 1.5
    assert err.mean() < 0.7
    # Chamfer bound (both directions, mean) against dense surface samples: < 0.75 voxel sizes
    # (measured 0.47).
    ch = chamfer(cloud.xyz, fibonacci_sphere(20000, RADIUS))
    assert ch.mean < 0.75 * VOXEL
    assert ch.completeness_median < 0.75 * VOXEL


def test_snapping_moves_points_onto_the_hull(sphere):
    cloud = carve_visual_hull(CFG, sphere)
    assert cloud.info["snapped_fraction"] > 0.95
    err = _surface_error(cloud.xyz)
    # measured: mean 0.04, 99th percentile 0.09 voxels; the hull of 40 views is only slightly
    # larger than the sphere and the masks are anti-aliased 4x4.
    assert np.percentile(err, 99) < 0.3
    assert err.mean() < 0.15
    assert chamfer(cloud.xyz, fibonacci_sphere(20000, RADIUS)).mean < 0.4 * VOXEL


def test_deterministic_for_a_seed(sphere):
    a = carve_visual_hull(CFG, sphere)
    b = carve_visual_hull(CFG, sphere)
    c = carve_visual_hull(dataclasses.replace(CFG, seed=1), sphere)
    np.testing.assert_array_equal(a.xyz, b.xyz)
    assert not np.array_equal(a.xyz, c.xyz)


def test_fewer_shell_voxels_than_points_reuses_every_voxel(sphere):
    cfg = dataclasses.replace(CFG, resolution=12, num_points=5000, snap_steps=0)
    occupied, _, size = carve_occupancy(cfg, sphere)
    shell = shell_voxels(occupied)
    assert len(shell) < 5000
    cloud = carve_visual_hull(cfg, sphere)
    vox = np.floor((cloud.xyz.astype(np.float64) + 1.0) / size).astype(int)
    vox = np.clip(vox, 0, 11)
    hit = {tuple(v) for v in vox}
    assert hit == {tuple(v) for v in shell}


def test_shell_of_a_solid_cube_is_its_surface():
    occ = np.zeros((6, 6, 6), bool)
    occ[1:5, 1:5, 1:5] = True
    shell = shell_voxels(occ)
    assert len(shell) == 4**3 - 2**3
    full = shell_voxels(np.ones((3, 3, 3), bool))  # the grid boundary counts as empty
    assert len(full) == 26


def test_views_outside_the_frustum_give_no_information(sphere):
    # A camera so close that the sphere overflows its image: most of the sphere lies outside its
    # frustum, and must not be carved by it (a carver treating "outside" as "background" would
    # keep only the part of the sphere inside this one frustum).
    from ne_jax.data.cameras import look_at

    c2w = look_at(np.array([0.0, -0.95, 0.25]))
    size = sphere.alpha.shape[1]
    alpha = sphere_alpha(c2w, size, sphere.fx, RADIUS)
    assert alpha.min() == 1.0  # the object is cut by the frame on every side
    _, seen = hull_test(Views.create(alpha[None], c2w[None], sphere.fx, sphere.fy, sphere.cx, sphere.cy),
                        fibonacci_sphere(2000, RADIUS), 0.5)
    assert 0 < seen.sum() < 1000  # only part of the sphere is in the frustum
    both = Views.create(np.concatenate([sphere.alpha, alpha[None]]), np.concatenate([sphere.c2w, c2w[None]]),
                        sphere.fx, sphere.fy, sphere.cx, sphere.cy)
    cloud = carve_visual_hull(CFG, both)
    ch = chamfer(cloud.xyz, fibonacci_sphere(20000, RADIUS))
    assert ch.completeness_median < 0.5 * VOXEL
    assert ch.accuracy_median < 0.5 * VOXEL


def test_partial_frustum_with_own_intrinsics():
    # Voxels behind a camera or outside its image are not carved by it: a single camera looking
    # at the +x half of the box from close by carves only inside its frustum.
    from ne_jax.data.cameras import look_at

    c2w = look_at(np.array([2.0, 0.0, 0.0]))
    alpha = np.zeros((1, 32, 32), np.float32)
    alpha[0, 12:20, 12:20] = 1.0
    views = Views.create(alpha, c2w[None], 40.0, 40.0, 16.0, 16.0)
    pts = np.array([[0.0, 0.0, 0.0], [0.0, 0.3, 0.0], [3.0, 0.0, 0.0], [0.0, 5.0, 0.0]])
    carved, seen = hull_test(views, pts, 0.5)
    # centre: in the mask; (0, .3, 0): in the frustum, outside the mask; behind the camera and
    # far outside the image: no information.
    np.testing.assert_array_equal(carved, [False, True, False, False])
    np.testing.assert_array_equal(seen, [1, 1, 0, 0])


def test_empty_masks_raise(sphere):
    empty = Views.create(np.zeros_like(sphere.alpha), sphere.c2w, sphere.fx, sphere.fy, sphere.cx, sphere.cy)
    with pytest.raises(CarvingError, match=r"empty masks.*alpha > 0.5.*40 views"):
        carve_visual_hull(CFG, empty)


def test_opaque_images_raise(sphere):
    full = Views.create(np.ones_like(sphere.alpha), sphere.c2w, sphere.fx, sphere.fy, sphere.cx, sphere.cy)
    with pytest.raises(CarvingError, match="no background"):
        carve_visual_hull(CFG, full)


def test_bounds_missing_the_object_raise(sphere):
    cfg = dataclasses.replace(CFG, bounds=((2.0, 2.0, 2.0), (3.0, 3.0, 3.0)))
    with pytest.raises(CarvingError, match="carving left no voxel"):
        carve_visual_hull(cfg, sphere)


@pytest.mark.parametrize(
    "field, value, match",
    [
        ("resolution", 1, "cfg.resolution"),
        ("bounds", ((0, 0, 0), (1, -1, 1)), "cfg.bounds"),
        ("alpha_threshold", 1.0, "cfg.alpha_threshold"),
        ("num_points", 0, "cfg.num_points"),
        ("jitter", 2.0, "cfg.jitter"),
    ],
)
def test_bad_config_names_the_field(sphere, field, value, match):
    with pytest.raises(ValueError, match=match):
        carve_visual_hull(dataclasses.replace(CFG, **{field: value}), sphere)


def test_views_checks_shapes():
    with pytest.raises(ValueError, match=r"c2w: expected shape \[V=2, 4, 4\]"):
        Views.create(np.zeros((2, 4, 4)), np.zeros((3, 4, 4)), 1, 1, 2, 2)
    with pytest.raises(ValueError, match="fx: expected a positive focal length"):
        Views.create(np.zeros((1, 4, 4)), np.eye(4)[None], 0.0, 1, 2, 2)


def test_per_point_views_match_one_view_at_a_time(sphere):
    """``Views.project`` and ``bilinear`` with a view per point give what one view at a time gives."""
    views = sphere
    rng = np.random.default_rng(0)
    xyz = rng.uniform(-0.5, 0.5, (40, 3))
    view = rng.integers(0, views.num_views, 40)
    u, v, depth = views.project(view, xyz)
    stack = np.stack([views.alpha, 1 - views.alpha], -1)  # [V, H, W, 2]
    looked = bilinear(stack, u, v, view)
    for k in np.unique(view):
        sel = view == k
        uk, vk, dk = views.project(int(k), xyz[sel])
        np.testing.assert_allclose(np.stack([u[sel], v[sel], depth[sel]]), np.stack([uk, vk, dk]), rtol=1e-12)
        np.testing.assert_allclose(looked[sel], bilinear(stack[k], uk, vk), rtol=1e-6)
        np.testing.assert_allclose(bilinear(views.alpha, u[sel], v[sel], view[sel]), looked[sel, 0], rtol=1e-6)


def test_object_touching_the_bounds_warns(sphere):
    cfg = dataclasses.replace(CFG, bounds=((-0.5,) * 3, (0.5,) * 3), resolution=16)
    with pytest.warns(UserWarning, match="touches the boundary"):
        carve_visual_hull(cfg, sphere)


# ------------------------------------------------------------------------------------- PLY


def test_ply_cloud_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(50, 3)).astype(np.float32)
    nrm = rng.normal(size=(50, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    path = tmp_path / "mine.ply"
    write_ply(path, {**{c: xyz[:, i] for i, c in enumerate("xyz")},
                     **{f"n{c}": nrm[:, i].astype(np.float32) for i, c in enumerate("xyz")}})
    cloud = load_ply_cloud(path)
    np.testing.assert_array_equal(cloud.xyz, xyz)
    np.testing.assert_allclose(cloud.normals, nrm, atol=1e-6)
    assert cloud.source == f"ply:{path}" and not cloud.is_ground_truth
    write_ply(path, {c: xyz[:, i] for i, c in enumerate("xyz")})
    assert load_ply_cloud(path).normals is None


def test_ply_missing_file_names_it(tmp_path):
    path = tmp_path / "nope.ply"
    with pytest.raises(PlyError, match=r"not found: .*nope\.ply"):
        load_ply_cloud(path)


def test_ply_without_xyz_names_file_and_columns(tmp_path):
    path = tmp_path / "noxyz.ply"
    write_ply(path, {"x": np.zeros(3, np.float32), "a": np.zeros(3, np.float32)})
    with pytest.raises(PlyError, match=r"noxyz\.ply: expected vertex properties x, y, z; missing y, z \(found a, x\)"):
        load_ply_cloud(path)


def test_ply_with_nan_names_file_and_row(tmp_path):
    path = tmp_path / "nan.ply"
    x = np.zeros(4, np.float32)
    x[2] = np.nan
    write_ply(path, {"x": x, "y": np.zeros(4, np.float32), "z": np.zeros(4, np.float32)})
    with pytest.raises(PlyError, match=r"nan\.ply: expected finite x, y, z; found 1 vertex\(es\).*index 2"):
        load_ply_cloud(path)


def test_ply_not_a_ply(tmp_path):
    path = tmp_path / "junk.ply"
    path.write_bytes(b"hello")
    with pytest.raises(PlyError, match=r"junk\.ply: not a PLY file"):
        load_ply_cloud(path)


def test_ground_truth_cloud_is_labelled(tmp_path):
    pts = fibonacci_sphere(100, RADIUS).astype(np.float32)
    write_ply(tmp_path / "points.ply", {**{c: pts[:, i] for i, c in enumerate("xyz")},
                                        **{f"n{c}": pts[:, i] / RADIUS for i, c in enumerate("xyz")}})
    cloud = ground_truth_cloud(tmp_path)
    assert cloud.source == GT_SOURCE and cloud.is_ground_truth
    assert "benchmark only" in cloud.source
    np.testing.assert_allclose(np.linalg.norm(cloud.normals, axis=1), 1.0, atol=1e-6)
    with pytest.raises(PlyError, match=r"ground-truth surface samples not found: .*points\.ply"):
        ground_truth_cloud(tmp_path / "elsewhere")


# --------------------------------------------------------------------------- photo-consistency


@pytest.fixture(scope="module")
def textured_sphere():
    """24 views of a sphere textured by position (64 x 64), as Views with colours."""
    from ne_jax.data.cameras import look_at

    from .conftest import sphere_rgba

    size = 64
    focal = 0.5 * size / np.tan(0.5 * 0.6911112070083618)
    c2w = np.stack([look_at(e) for e in fibonacci_sphere(24, 4.0)])
    rgba = np.stack([sphere_rgba(c, size, focal, RADIUS) for c in c2w])
    return Views.create(rgba[..., 3], c2w, focal, focal, size / 2, size / 2, rgb=rgba[..., :3])


PHOTO = dataclasses.replace(CFG, resolution=32, num_points=2000, photo_iters=3)


def test_photo_consistent_surface_is_kept(textured_sphere):
    occupied, _, size = carve_occupancy(PHOTO, textured_sphere)
    shell = len(shell_voxels(occupied))
    kept, info = photo_consistency(PHOTO, textured_sphere, occupied, size)
    # a view-independent texture: (almost) every shell voxel agrees across its views
    assert info["photo_removed_per_sweep"][0] < 0.02 * shell  # measured: 2 of 904
    assert kept.sum() > 0.98 * occupied.sum()


def test_view_dependent_colors_are_carved(textured_sphere):
    # the same masks, but each view paints the object its own random colour: nothing is consistent
    rng = np.random.default_rng(0)
    rgb = np.broadcast_to(rng.random((textured_sphere.num_views, 1, 1, 3)), textured_sphere.rgb.shape)
    views = dataclasses.replace(textured_sphere, rgb=np.ascontiguousarray(rgb, np.float32))
    occupied, _, size = carve_occupancy(PHOTO, views)
    shell = len(shell_voxels(occupied))
    kept, info = photo_consistency(PHOTO, views, occupied, size)
    assert info["photo_removed_per_sweep"][0] > 0.5 * shell
    assert kept.sum() < occupied.sum()


def test_photo_consistency_needs_colors(sphere):
    with pytest.raises(ValueError, match="views.rgb: photo-consistency"):
        carve_visual_hull(dataclasses.replace(CFG, photo_iters=1), sphere)

"""The scene frame of a capture (normalisation), layout detection, and the SfM initial cloud."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from ne_jax.data.cameras import look_at
from ne_jax.data.capture import Capture, CaptureView, holdout_splits
from ne_jax.data.nerf_synthetic import load_split as load_nerf_synthetic_split
from ne_jax.data.nerf_synthetic import write_split
from ne_jax.data.png import DataError
from ne_jax.data.scene import LOOKED_FOR, Normalisation, detect_format, load_split, normalisation
from ne_jax.pointcloud.init import Views
from ne_jax.pointcloud.sfm_init import SfmCleaning, sfm_cloud


def _capture(rng, *, centre, up, radius, half, points=True, n=24) -> tuple[Capture, np.ndarray]:
    """Cameras on a ring ``radius`` around ``centre`` (elevations 10-50 degrees about ``up``) looking
    at it, and SfM points on the surface of a cube of half-size ``half`` about it."""
    z = np.asarray(up, float) / np.linalg.norm(up)
    x = np.cross(z, [1.0, 0, 0]) if abs(z[0]) < 0.9 else np.cross(z, [0, 1.0, 0])
    x /= np.linalg.norm(x)
    rot = np.stack([x, np.cross(z, x), z], 1)  # columns: the capture's axes of the local frame
    views = []
    for i in range(n):
        az, el = 2 * np.pi * i / n, np.deg2rad(10 + 40 * (i % 3) / 2)
        local = radius * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        c2w_local = look_at(local)
        c2w = np.eye(4)
        c2w[:3, :3] = rot @ c2w_local[:3, :3]
        c2w[:3, 3] = rot @ local + centre
        views.append(CaptureView(name=f"{i:03d}.png", image_path=Path(f"{i:03d}.png"), c2w=c2w, fx=50.0, fy=50.0,
                                 cx=32.0, cy=24.0, width=64, height=48))
    pts = rng.uniform(-half, half, (600, 3))
    face = rng.integers(0, 3, 600)
    pts[np.arange(600), face] = np.sign(rng.normal(size=600)) * half
    world = pts @ rot.T + centre
    cap = Capture(format="colmap", root=Path("."), views=tuple(views), splits=holdout_splits([v.name for v in views]),
                  split_rule="every 8th held out", points=world if points else None)
    return cap, world


def test_normalisation_brings_the_region_of_interest_into_the_unit_cube_with_z_up():
    rng = np.random.default_rng(0)
    centre = np.array([10.0, -3.0, 7.0])
    cap, world = _capture(rng, centre=centre, up=[1.0, 2.0, 0.5], radius=20.0, half=2.5)
    norm = normalisation(cap)
    pts = norm.to_scene(world)
    assert np.percentile(np.abs(pts).max(1), 90) == pytest.approx(1.0, rel=1e-6)
    np.testing.assert_allclose(norm.to_scene(centre), 0.0, atol=1e-9)  # the cameras look at the centre
    c2w = norm.c2w_to_scene(np.stack([v.c2w for v in cap.views]))
    np.testing.assert_allclose(c2w[:, :3, 1].mean(0) / np.linalg.norm(c2w[:, :3, 1].mean(0)), [0, 0, 1], atol=1e-9)
    for m in c2w:  # still rigid
        np.testing.assert_allclose(m[:3, :3].T @ m[:3, :3], np.eye(3), atol=1e-9)
    np.testing.assert_allclose(norm.to_capture(pts), world, atol=1e-9)
    back = Normalisation.from_dict(norm.as_dict())
    np.testing.assert_allclose(back.matrix(), norm.matrix(), atol=0)
    assert np.median(np.linalg.norm(c2w[:, :3, 3], axis=1)) == pytest.approx(20.0 * norm.scale, rel=1e-9)


def test_normalisation_without_points_puts_the_cameras_at_the_benchmark_distance():
    rng = np.random.default_rng(1)
    cap, _ = _capture(rng, centre=np.array([1.0, 2.0, 3.0]), up=[0, 0, 1.0], radius=0.3, half=0.05, points=False)
    norm = normalisation(cap)
    c2w = norm.c2w_to_scene(np.stack([v.c2w for v in cap.views]))
    np.testing.assert_allclose(np.median(np.linalg.norm(c2w[:, :3, 3], axis=1)), 4.0, rtol=1e-9)
    assert dict(norm.how)["centre"].startswith("the point nearest")


def test_normalisation_clamps_a_region_of_interest_the_cameras_stand_in():
    rng = np.random.default_rng(2)
    cap, _ = _capture(rng, centre=np.zeros(3), up=[0, 0, 1.0], radius=2.0, half=1.9)  # points out to the cameras
    norm = normalisation(cap)
    c2w = norm.c2w_to_scene(np.stack([v.c2w for v in cap.views]))
    assert np.median(np.linalg.norm(c2w[:, :3, 3], axis=1)) == pytest.approx(2.0, rel=1e-9)
    assert "clamp" in dict(norm.how)


def test_a_nerf_synthetic_folder_loads_as_before(tmp_path, random_c2w, random_rgba):
    rng = np.random.default_rng(3)
    write_split(tmp_path, "train", random_rgba(rng, 3, 8, 6), random_c2w(rng, 3), 0.7)
    assert detect_format(tmp_path) == "nerf_synthetic"
    a, b = load_split(tmp_path, "train"), load_nerf_synthetic_split(tmp_path, "train")
    np.testing.assert_array_equal(a.images, b.images)
    np.testing.assert_array_equal(a.c2w, b.c2w)


def test_an_unknown_folder_names_every_layout_looked_for(tmp_path):
    (tmp_path / "photos").mkdir()
    with pytest.raises(DataError) as e:
        detect_format(tmp_path)
    msg = str(e.value)
    assert str(tmp_path) in msg
    for what in LOOKED_FOR.values():
        assert what in msg
    with pytest.raises(DataError, match="does not exist"):
        detect_format(tmp_path / "missing")


def _sphere_views(n=12, size=48) -> Views:
    c2w = np.stack([look_at(4.0 * np.array([np.cos(a), np.sin(a), 0.4])) for a in np.linspace(0, 2 * np.pi, n, False)])
    return Views.create(np.ones((n, size, size), np.float32), c2w, 60.0, 60.0, size / 2, size / 2)


def test_sfm_cloud_drops_outliers_and_densifies_on_the_surface():
    rng = np.random.default_rng(4)
    surface = rng.normal(size=(800, 3))
    surface /= np.linalg.norm(surface, axis=1, keepdims=True)
    surface = 0.8 * surface + rng.normal(scale=0.003, size=surface.shape)
    outliers = rng.uniform(-1.2, 1.2, (60, 3))
    outliers = outliers[np.abs(np.linalg.norm(outliers, axis=1) - 0.8) > 0.3]
    behind = np.array([[0.0, 0.0, 30.0]])  # seen by no camera
    xyz = np.concatenate([surface, outliers, behind])
    error = np.concatenate([np.full(len(surface), 0.5), np.full(len(outliers), 0.5), [0.5]])
    error[:10] = 50.0  # badly reprojected surface points
    cloud = sfm_cloud(xyz, _sphere_views(), 5000, error=error)
    assert len(cloud) == 5000 and cloud.source == "sfm"
    dist = np.abs(np.linalg.norm(cloud.xyz, axis=1) - 0.8)
    assert np.percentile(dist, 99) < 0.05  # densified on the surface, outliers gone
    info = cloud.info
    assert info["after_error"] == len(xyz) - 10
    assert info["after_visibility"] == info["after_error"] - 1  # the point behind every camera
    assert info["after_outliers"] <= info["after_visibility"] - int(0.8 * len(outliers))


def test_sfm_cloud_averages_the_noise_across_a_surface_and_keeps_its_curvature():
    """SfM noise across a surface becomes thickness of the start: each kept point is moved onto the
    plane of its neighbours, so a noisy plane's spread across it falls and a sphere keeps its radius."""
    rng = np.random.default_rng(5)
    sigma = 0.02
    plane = np.concatenate([rng.uniform(-0.8, 0.8, (1500, 2)), rng.normal(scale=sigma, size=(1500, 1))], 1)
    cloud = sfm_cloud(plane, _sphere_views(), 6000)
    assert np.std(cloud.xyz[:, 2]) < sigma / 2
    sphere = rng.normal(size=(1500, 3))
    sphere /= np.linalg.norm(sphere, axis=1, keepdims=True)
    sphere *= 0.6
    cloud = sfm_cloud(sphere, _sphere_views(), 6000)
    radius = np.linalg.norm(cloud.xyz, axis=1)
    assert abs(np.median(radius) - 0.6) < 0.01  # the fit planes' bias stays within a few per cent
    unsmoothed = sfm_cloud(plane, _sphere_views(), 6000, cfg=SfmCleaning(smooth_neighbors=0))
    assert np.std(unsmoothed.xyz[:, 2]) > 0.8 * sigma


def test_sfm_cloud_needs_points_to_start_from():
    with pytest.raises(ValueError, match="survive cleaning"):
        sfm_cloud(np.array([[0.0, 0.0, 50.0]] * 3), _sphere_views(), 100)
    with pytest.raises(ValueError, match=r"expected SfM points \[P, 3\]"):
        sfm_cloud(np.zeros((4, 2)), _sphere_views(), 100)


@pytest.mark.parametrize("source", ["ply", "ground_truth"])
def test_a_start_from_a_ply_is_read_in_the_captures_coordinates(tmp_path, source):
    """A PLY the user gives (and the benchmark's ``points.ply`` of a capture) holds capture
    coordinates: the run's initial cloud is it brought into the scene frame, normals turned."""
    import formats_fixtures as fx

    from ne_jax.data.ply import write_ply
    from ne_jax.data.scene import scene_normalisation
    from ne_jax.train.loop import initial_cloud
    from ne_jax.train.run import InitConfig

    c2w = fx.circle_c2w(12, radius=8.0, height=3.0)
    c2w[:, :3, 3] += (5.0, -3.0, 2.0)  # the circle about (5, -3, 2), so the frames differ
    fx.write_colmap_text(tmp_path, c2w, [f"img_{i:02d}.png" for i in range(12)])
    norm = scene_normalisation(tmp_path)
    assert not norm.is_identity
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(50, 3)) + (5.0, -3.0, 2.0)
    normals = rng.normal(size=(50, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    ply = tmp_path / "points.ply"
    write_ply(ply, {**dict(zip("xyz", xyz.T.astype(np.float32))),
                    **dict(zip(("nx", "ny", "nz"), normals.T.astype(np.float32)))})
    views = Views.from_split(load_split(tmp_path, "train"))
    cloud = initial_cloud(InitConfig(source=source, ply_path=str(ply) if source == "ply" else None), tmp_path, views)
    np.testing.assert_allclose(cloud.xyz, norm.to_scene(xyz), atol=1e-5)
    np.testing.assert_allclose(norm.rotate_to_capture(cloud.normals), normals, atol=1e-5)
    assert np.abs(cloud.xyz).max() < 3  # in the scene frame, not 5 units off

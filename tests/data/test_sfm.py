"""Structure from motion (:mod:`ne_jax.data.sfm`): path-traced photos with known cameras -> a COLMAP
folder whose poses match the true ones, and the errors a bad folder of photos gives.

The end-to-end test renders the benchmark's ``blocks`` scene on a textured ground plate
(``ne_jax/benchmark/photos.py``: why the plate) from two rings of 12 cameras, runs
:func:`process_images` on one thread, aligns the recovered camera centres to the true ones by a
similarity and checks every camera's rotation and centre. "Scene size" for the centre tolerance is
the RMS distance of the true camera centres from their centroid (3.4 units; the object itself is
about 1.1 x 1.1 x 1.9 units).
"""

from __future__ import annotations

import json
import os
import time

import numpy as np
import pytest

from ne_jax.data.png import DataError, write_image

pycolmap = pytest.importorskip("pycolmap")
sfm = pytest.importorskip("ne_jax.data.sfm")

RESOLUTION = 320
SPP = 16
PER_RING = 12
MAX_ROTATION_ERROR_DEG = 1.0
MAX_CENTRE_ERROR = 0.01
"""Of the scene size: the RMS distance of the true camera centres from their centroid."""


def _opencv_c2w_rotation(c2w_opengl: np.ndarray) -> np.ndarray:
    """Camera-to-world rotation ``[..., 3, 3]`` with OpenCV axes (COLMAP's) of OpenGL cameras."""
    return c2w_opengl[..., :3, :3] @ np.diag([1.0, -1.0, -1.0])


@pytest.fixture(scope="module")
def reconstruction(tmp_path_factory):
    """``(root, names, c2w [n, 4, 4] true OpenGL cameras, report, progress lines, seconds)``."""
    pytest.importorskip("mitsuba")
    from ne_jax.benchmark.photos import render_photos

    root = tmp_path_factory.mktemp("sfm")
    t0 = time.perf_counter()
    names, c2ws = render_photos(root / "photos", RESOLUTION, SPP, PER_RING)
    t1 = time.perf_counter()
    lines: list[str] = []
    report = sfm.process_images(root / "photos", root / "scene", num_threads=1, progress=lines.append)
    seconds = {"render": t1 - t0, "sfm": time.perf_counter() - t1}
    return root, names, c2ws, report, lines, seconds


def _pose_errors(sparse, names, c2ws):
    """``(rotation error [n] degrees, centre error [n] world units, scene size)`` of the model in
    ``sparse`` against the true OpenGL cameras ``c2ws`` of ``names``, after a similarity alignment of
    the camera centres; every name must be registered."""
    rec = pycolmap.Reconstruction(sparse)
    by_name = {im.name: im for im in rec.images.values() if im.has_pose}
    assert sorted(by_name) == sorted(names)
    centres = np.stack([by_name[n].projection_center() for n in names])
    rotations = np.stack([by_name[n].cam_from_world().rotation.matrix().T for n in names])  # cam -> world
    true = c2ws[:, :3, 3]
    align = sfm.similarity_align(centres, true)
    centre_error = np.linalg.norm(align.apply(centres) - true, axis=1)
    rotation_error = sfm.rotation_angle_deg(align.R @ rotations, _opencv_c2w_rotation(c2ws))
    scene_size = float(np.sqrt(np.mean(np.sum((true - true.mean(0)) ** 2, axis=1))))
    return rotation_error, centre_error, scene_size


def test_every_photo_registers_at_its_true_pose(reconstruction):
    root, names, c2ws, report, _, seconds = reconstruction
    rec = pycolmap.Reconstruction(root / "scene" / "sparse" / "0")
    assert rec.num_reg_images() == len(names) == report["registered"] and report["unregistered"] == []
    rotation_error, centre_error, scene_size = _pose_errors(root / "scene" / "sparse" / "0", names, c2ws)
    print(f"\nsfm: {len(names)} views at {RESOLUTION} px, {SPP} spp; rotation error max "
          f"{rotation_error.max():.3f} mean {rotation_error.mean():.3f} deg; centre error max "
          f"{centre_error.max():.4f} mean {centre_error.mean():.4f} ({100 * centre_error.max() / scene_size:.2f}% of "
          f"{scene_size:.2f}); {report['points']} points, reprojection {report['mean_reprojection_error']:.2f} px; "
          f"render {seconds['render']:.1f} s, sfm {seconds['sfm']:.1f} s")
    assert rotation_error.max() < MAX_ROTATION_ERROR_DEG, rotation_error
    assert centre_error.max() < MAX_CENTRE_ERROR * scene_size, centre_error / scene_size
    # the intrinsics too: the true focal length is (W / 2) / tan(camera_angle_x / 2)
    from ne_jax.data.cameras import CAMERA_ANGLE_X

    (camera,) = rec.cameras.values()
    assert camera.width == camera.height == RESOLUTION
    assert camera.focal_length_x == pytest.approx(0.5 * RESOLUTION / np.tan(0.5 * CAMERA_ANGLE_X), rel=0.01)


def test_sequential_matcher_registers_every_photo(reconstruction, tmp_path):
    """Fewer pairs (each view with the next ones in name order: one ring, then the other) and still
    every view, within a degree (centres: 0.9% of the scene size here, so not asserted)."""
    root, names, c2ws, exhaustive, _, _ = reconstruction
    report = sfm.process_images(root / "photos", tmp_path / "scene", matcher="sequential", progress=None)
    assert report["registered"] == len(names) and report["settings"]["matcher"] == "sequential"
    assert report["pairs"]["candidates"] < exhaustive["pairs"]["candidates"]
    rotation_error, _, _ = _pose_errors(tmp_path / "scene" / "sparse" / "0", names, c2ws)
    assert rotation_error.max() < MAX_ROTATION_ERROR_DEG, rotation_error


def test_writes_the_colmap_layout_and_a_report(reconstruction):
    root, names, _, report, lines, _ = reconstruction
    scene = root / "scene"
    assert sorted(os.listdir(scene / "images")) == names
    for name in names:  # the photos themselves, hard-linked on one file system
        assert (scene / "images" / name).read_bytes() == (root / "photos" / name).read_bytes()
        assert os.path.samefile(scene / "images" / name, root / "photos" / name)
    for model_file in ("cameras.bin", "images.bin", "points3D.bin"):
        assert (scene / "sparse" / "0" / model_file).is_file()
    assert not any(p.name.startswith(".") for p in root.iterdir()) and not (scene / ".mapper").exists()
    assert json.loads((scene / "sfm.json").read_text()) == json.loads(json.dumps(report))
    assert report["images"] == len(names) and report["models"] >= 1 and report["points"] > 500
    assert report["features"]["min"] > 0 and report["pairs"]["verified"] >= len(names)
    assert 0 < report["mean_reprojection_error"] < 2.0 and report["warnings"] == []
    assert set(report["seconds"]) == {"copy", "extract", "match", "map", "total"}
    assert report["settings"]["num_threads"] == 1 and report["settings"]["matcher"] == "exhaustive"
    # one progress line per stage, with its counts and seconds
    text = "\n".join(lines)
    for needle in (f"{len(names)} photos", "features:", "matching (exhaustive", f"{len(names)} of {len(names)} images "
                   "registered", f"{report['points']:,} points", "wrote"):
        assert needle in text, (needle, text)
    assert sum(" s)" in line for line in lines) >= 4
    # the repository's COLMAP reader takes it
    from ne_jax.data.formats.colmap import read_colmap

    capture = read_colmap(scene)
    assert len(capture.views) == len(names)
    assert {v.width for v in capture.views} == {RESOLUTION}


# ------------------------------------------------------------------------------------- errors


def _photos(folder, count, size=32, value=0.5, suffix=".png"):
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(count):
        write_image(folder / f"p{i}{suffix}", np.full((size, size, 3), value, np.float32))
    return folder


def test_missing_or_file_photos_raise(tmp_path):
    with pytest.raises(DataError, match=r"nowhere: expected a folder of photos, found nothing"):
        sfm.process_images(tmp_path / "nowhere", tmp_path / "out", progress=None)
    (tmp_path / "a.png").write_bytes(b"")
    with pytest.raises(DataError, match=r"a\.png: expected a folder of photos, found a file"):
        sfm.process_images(tmp_path / "a.png", tmp_path / "out", progress=None)
    assert not (tmp_path / "out").exists()


def test_fewer_than_three_photos_raise(tmp_path):
    photos = _photos(tmp_path / "photos", 2)
    (photos / "notes.txt").write_text("not a photo")
    (photos / "sub").mkdir()
    _photos(photos / "sub", 3)  # not searched
    with pytest.raises(DataError, match=r"photos: expected at least 3 photos .* found 2 \(and 2 other entries\)"):
        sfm.process_images(photos, tmp_path / "out", progress=None)
    assert not (tmp_path / "out").exists()


def test_photo_suffixes_are_case_insensitive(tmp_path):
    photos = _photos(tmp_path / "photos", 1, suffix=".PNG")
    (photos / "b.JPeG").write_bytes(b"x")
    (photos / "c.jpg").write_bytes(b"x")
    (photos / ".hidden.png").write_bytes(b"x")
    assert sfm.list_photos(photos) == ["b.JPeG", "c.jpg", "p0.PNG"]


def test_blank_photos_register_too_few_and_write_nothing(tmp_path):
    photos = _photos(tmp_path / "photos", 4)
    lines = []
    with pytest.raises(DataError, match=r"photos: expected at least 3 photos registered in one model, found 0 of 4 "
                                        r".*overlap.*texture.*matcher='sequential'"):
        sfm.process_images(photos, tmp_path / "scene", progress=lines.append)
    assert sorted(os.listdir(tmp_path)) == ["photos"]  # no scene, no temporary folder
    assert any("features: 0 SIFT keypoints" in line for line in lines)
    with pytest.raises(DataError, match=r"or matcher='exhaustive' or a larger sequential_overlap"):
        sfm.process_images(photos, tmp_path / "scene", matcher="sequential", progress=None)


def test_unreadable_photos_raise_when_too_few_remain(tmp_path):
    photos = _photos(tmp_path / "photos", 2)
    (photos / "broken.jpg").write_bytes(b"not a jpeg")
    with pytest.raises(DataError, match=r"at least 3 readable photos, COLMAP read 2 of 3 \(unreadable: broken"):
        sfm.process_images(photos, tmp_path / "scene", progress=None)
    assert sorted(os.listdir(tmp_path)) == ["photos"]


def test_out_is_protected(tmp_path):
    photos = _photos(tmp_path / "photos", 3)
    (tmp_path / "file").write_text("x")
    with pytest.raises(DataError, match=r"file: expected a folder \(or nothing\)"):
        sfm.process_images(photos, tmp_path / "file", progress=None)
    with pytest.raises(DataError, match=r"photos: expected a new folder for the scene, found the photos folder"):
        sfm.process_images(photos, photos, progress=None)
    (tmp_path / "scene").mkdir()
    (tmp_path / "scene" / "keep.txt").write_text("mine")
    with pytest.raises(DataError, match=r"scene: expected a new or empty folder, found 1 entries"):
        sfm.process_images(photos, tmp_path / "scene", progress=None)
    with pytest.raises(DataError, match=r"found 0 of 3"):  # overwrite only replaces after success
        sfm.process_images(photos, tmp_path / "scene", overwrite=True, progress=None)
    assert (tmp_path / "scene" / "keep.txt").read_text() == "mine"


def test_bad_arguments_raise(tmp_path):
    photos = _photos(tmp_path / "photos", 3)
    for kwargs, match in (({"matcher": "vocab"}, "matcher"), ({"camera_model": "FISHEYE"}, "camera_model"),
                          ({"num_threads": 0}, "num_threads")):
        with pytest.raises(ValueError, match=match):
            sfm.process_images(photos, tmp_path / "scene", progress=None, **kwargs)


# --------------------------------------------------------------------------- similarity_align


@pytest.mark.parametrize("n", [3, 10, 100])
def test_similarity_align_recovers_a_similarity(n):
    rng = np.random.default_rng(n)
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    R = q * np.sign(np.diag(r))
    if np.linalg.det(R) < 0:
        R[:, 0] = -R[:, 0]
    src = rng.normal(size=(n, 3))
    dst = 2.5 * src @ R.T + np.array([1.0, -2.0, 0.5])
    scale, R_found, t = sfm.similarity_align(src, dst)
    np.testing.assert_allclose(scale, 2.5, rtol=1e-10)
    np.testing.assert_allclose(R_found, R, atol=1e-10)
    np.testing.assert_allclose(t, [1.0, -2.0, 0.5], atol=1e-10)
    np.testing.assert_allclose(sfm.similarity_align(src, dst).apply(src), dst, atol=1e-10)
    # a mirrored target gives the best proper rotation, never a reflection
    assert np.linalg.det(sfm.similarity_align(src, dst * np.array([1.0, 1.0, -1.0])).R) == pytest.approx(1.0)


def test_similarity_align_rejects_bad_input():
    with pytest.raises(ValueError, match="n >= 3"):
        sfm.similarity_align(np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="coincide"):
        sfm.similarity_align(np.ones((4, 3)), np.zeros((4, 3)))


def test_camera_warnings_flag_non_square_focal_lengths():
    rec = pycolmap.Reconstruction()
    cameras = ((1, "PINHOLE", [120.0, 90.0, 50.0, 40.0]), (2, "PINHOLE", [120.0, 119.0, 50.0, 40.0]),
               (3, "SIMPLE_RADIAL", [120.0, 50.0, 40.0, 0.0]))
    for camera_id, model, params in cameras:
        rec.add_camera(pycolmap.Camera(model=model, width=100, height=80, params=params, camera_id=camera_id))
    (warning,) = sfm.camera_warnings(rec)
    assert warning.startswith("camera 1 (PINHOLE): focal lengths fx 120.0 and fy 90.0 px differ by 25%")


def test_rotation_angle_deg():
    c, s = np.cos(np.radians(30.0)), np.sin(np.radians(30.0))
    rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(sfm.rotation_angle_deg(np.eye(3), rz), 30.0)
    np.testing.assert_allclose(sfm.rotation_angle_deg(rz, rz), 0.0, atol=1e-5)

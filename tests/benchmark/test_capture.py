"""The benchmark's capture variant (ne_jax.benchmark.capture) on a small setting (32 px, 11 views, 16
spp, one scene, two edits): the COLMAP text model reads back with pycolmap and its cameras are the
benchmark's, the nerfstudio copy holds the same cameras and points, the simulated SfM points lie
near the surfaces with the stated outlier share, images are opaque, every 8th image held out is a
test view, the edits' ground truth is where the edit evaluation looks for it, the same seed gives
the same bytes (through ``ne-jax make-benchmark``), and the presets check their view counts."""

import dataclasses
import hashlib
import json

import numpy as np
import pytest

from ne_jax.benchmark import capture as C
from ne_jax.benchmark import scenes as S
from ne_jax.benchmark.generate import PRESETS, BenchmarkPreset, _rng, generate_scene, get_preset, list_variants
from ne_jax.data import cameras
from ne_jax.data.nerf_synthetic import load_split
from ne_jax.data.ply import read_ply
from ne_jax.data.png import decode_png

pytest.importorskip("mitsuba")
pycolmap = pytest.importorskip("pycolmap")

MINI = dataclasses.replace(get_preset("tiny_capture"), name="mini_capture", resolution=32, train_views=9,
                           test_views=2, detail=0.4, surface_samples=300, spp=16, edit_train_views=3)
SCENE, EDITS = "blocks", ["cut", "turn_with_light"]


def digest_tree(root):
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file() and p.name != "scene.json"}  # scene.json: its seconds


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    root = tmp_path_factory.mktemp("bench_capture")
    generate_scene(SCENE, MINI, root, seed=0, edits=EDITS)
    return root


@pytest.fixture(scope="module")
def truth():
    """The benchmark's cameras of the scene in the capture's name order, and which view each image is."""
    cams = C.capture_cameras(MINI, SCENE, 0)
    order = C.view_order(MINI.train_views, MINI.test_views)
    return cams, order, np.stack([cams[s][i] for s, i in order])


def colmap_c2w(image) -> np.ndarray:
    """OpenGL camera-to-world of a pycolmap image (world-to-camera with OpenCV axes in the model)."""
    w2c = np.eye(4)
    w2c[:3] = np.asarray(image.cam_from_world().matrix())
    return np.linalg.inv(w2c) @ np.diag([1.0, -1.0, -1.0, 1.0])


def test_colmap_model_reads_back_with_the_benchmark_cameras(root, truth):
    _, order, c2ws = truth
    rec = pycolmap.Reconstruction(str(root / SCENE / "sparse" / "0"))
    assert rec.num_images() == len(order) == 11 and rec.num_cameras() == 1
    (camera,) = rec.cameras.values()
    pin = C.Pinhole.benchmark(32)
    assert camera.model.name == "PINHOLE" and (camera.width, camera.height) == (32, 32)
    np.testing.assert_allclose(camera.params, [pin.fx, pin.fy, 16.0, 16.0], rtol=1e-12)
    names = sorted(im.name for im in rec.images.values())
    assert names == [C.image_name(k) for k in range(len(order))]
    for im in rec.images.values():
        k = names.index(im.name)
        np.testing.assert_allclose(colmap_c2w(im), c2ws[k], atol=1e-6)
    # every 8th image of the sorted names (0, 8) is a test view, in orbit order: the LLFF rule gives the test split
    held_out = [names.index(n) for n in names[::8]]
    assert [order[k] for k in held_out] == [("test", 0), ("test", 1)]
    np.testing.assert_allclose(c2ws[held_out], cameras.orbit_cameras(2), atol=1e-12)
    # tracks and observations agree (pycolmap checks the references when it reads the model)
    assert rec.num_points3D() == C.SfMSimulation().points
    point = next(iter(rec.points3D.values()))
    assert point.track.length() >= 2
    for el in point.track.elements:
        assert rec.images[el.image_id].points2D[el.point2D_idx].point3D_id == next(iter(rec.points3D))


def test_nerfstudio_copy_has_the_same_cameras_points_and_images(root, truth):
    _, _, c2ws = truth
    ns = root / f"{SCENE}_ns"
    meta = json.loads((ns / "transforms.json").read_text())
    pin = C.Pinhole.benchmark(32)
    assert meta["camera_model"] == "PINHOLE" and meta["ply_file_path"] == "sparse_pc.ply"
    assert (meta["fl_x"], meta["fl_y"], meta["cx"], meta["cy"], meta["w"], meta["h"]) == (
        pin.fx, pin.fy, 16.0, 16.0, 32, 32)
    frames = sorted(meta["frames"], key=lambda f: f["file_path"])
    assert [f["file_path"] for f in frames] == [f"images/{C.image_name(k)}" for k in range(len(c2ws))]
    np.testing.assert_allclose(np.array([f["transform_matrix"] for f in frames]), c2ws, atol=1e-12)
    for f in frames:  # the same image files, hard-linked
        assert (ns / f["file_path"]).read_bytes() == (root / SCENE / f["file_path"]).read_bytes()
    ply = read_ply(ns / meta["ply_file_path"])
    rec = pycolmap.Reconstruction(str(root / SCENE / "sparse" / "0"))
    ids = sorted(rec.points3D)
    xyz = np.array([rec.points3D[i].xyz for i in ids])
    rgb = np.array([rec.points3D[i].color for i in ids])
    np.testing.assert_allclose(np.stack([ply[a] for a in "xyz"], 1), xyz, atol=1e-12)
    assert ply["red"].dtype == np.uint8 and (np.stack([ply[c] for c in ("red", "green", "blue")], 1) == rgb).all()
    assert json.loads((ns / "scene.json").read_text())["copy_of"] == f"../{SCENE}"


def test_images_are_opaque_rgb(root):
    for path in sorted((root / SCENE / "images").iterdir()):
        img = decode_png(path.read_bytes())
        assert img.shape == (32, 32, 3) and img.dtype == np.uint8
        assert img.mean() > 20  # lit: the sky and the ground fill the frame
    for directory in (root / SCENE / "edits" / EDITS[0], root / SCENE / "unedited"):
        for split in ("train", "test"):
            assert (np.asarray(load_split(directory, split).images)[..., 3] == 1.0).all()


def test_sfm_points_near_the_surfaces_with_the_outlier_share(root, truth):
    import open3d as o3d

    _, _, c2ws = truth
    scene = S.get_scene(SCENE, MINI.detail)
    ground = C.ground_for(scene)
    config = C.SfMSimulation()
    sfm = C.simulate_sfm(scene, ground, c2ws, C.Pinhole.benchmark(32), _rng(0, SCENE, "sfm"), config)
    rec = pycolmap.Reconstruction(str(root / SCENE / "sparse" / "0"))
    written = np.array([rec.points3D[i].xyz for i in sorted(rec.points3D)])
    np.testing.assert_allclose(written, sfm.xyz, atol=1e-12)  # the file holds this simulation
    assert sfm.outlier.sum() == round(config.outlier_share * config.points)
    assert sfm.sigma == pytest.approx(cameras.CAMERA_RADIUS / C.Pinhole.benchmark(32).fx)  # a pixel at the target

    gv, gf = ground.quad()
    mesh = o3d.t.geometry.RaycastingScene()
    faces = np.concatenate([scene.mesh.faces, gf + len(scene.mesh.vertices)])
    mesh.add_triangles(o3d.core.Tensor(np.concatenate([scene.mesh.vertices, gv]).astype(np.float32)),
                       o3d.core.Tensor(faces.astype(np.uint32)))
    dist = mesh.compute_distance(o3d.core.Tensor(sfm.xyz.astype(np.float32))).numpy()
    # inliers: |N(0, sigma)| off a locally flat surface (median 0.67 sigma), none far off
    inlier = dist[~sfm.outlier]
    assert 0.4 * sfm.sigma < np.median(inlier) < 0.9 * sfm.sigma
    assert np.quantile(inlier, 0.99) < 4 * sfm.sigma
    # the points more than 4 sigma off any surface are outliers, and they are most of the outliers
    far = dist > 4 * sfm.sigma
    assert sfm.outlier[far].all() and 0.4 * config.outlier_share < far.mean() <= config.outlier_share
    true_dist = mesh.compute_distance(o3d.core.Tensor(sfm.truth[~sfm.outlier].astype(np.float32))).numpy()
    assert true_dist.max() < 1e-4  # before the noise, on the surfaces
    # half the inliers on the objects, the rest on the ground; all seen by at least two images
    on_ground = np.abs(sfm.truth[~sfm.outlier][:, 2] - ground.z) < 1e-9
    assert on_ground.mean() == pytest.approx(1 - config.object_share, abs=0.01)
    assert min(len(t) for t in sfm.track_images) >= 2
    # errors are reprojection errors in pixels: about 1.5 px for the inliers
    assert 0.8 < np.median(sfm.error[~sfm.outlier]) < 2.5
    # colours: the surface albedo of the ground points
    np.testing.assert_array_equal(
        sfm.rgb[~sfm.outlier][on_ground],
        np.round(ground.albedo(sfm.truth[~sfm.outlier][on_ground]) * 255).astype(np.uint8))


def test_edits_ground_truth_in_the_layout_the_edit_evaluation_reads(root, truth):
    from ne_jax.benchmark.edits import benchmark_edit

    cams, _, _ = truth
    scene = S.get_scene(SCENE)
    ground = C.ground_for(S.get_scene(SCENE, MINI.detail))
    for folder in (root / SCENE, root / f"{SCENE}_ns"):
        for name in EDITS:
            edit, found = benchmark_edit(folder, name)
            assert found == folder / "edits" / name
            meta = json.loads((found / "scene.json").read_text())
            assert meta["edit_description"] == edit.description and meta["capture_frame"] == "../.."
            test = load_split(found, "test")
            np.testing.assert_allclose(np.asarray(test.c2w), cams["test"], atol=1e-6)  # the held-out cameras
            assert len(load_split(found, "train").c2w) == MINI.edit_train_views
    # an edit moves the objects as the benchmark's edit does and leaves the ground
    edit = C.objects_only(scene.edits["cut"], ground.objects_above)
    objects = scene.mesh.vertices[:50]
    ground_points = np.array([[0.3, -2.0, ground.z], [1.5, 0.2, ground.z + 0.005]])
    moved, deleted = edit(np.concatenate([objects, ground_points]))
    np.testing.assert_allclose(np.asarray(moved)[:50], np.asarray(scene.edits["cut"](objects)[0]), atol=1e-6)
    np.testing.assert_allclose(np.asarray(moved)[50:], ground_points, atol=1e-6)
    assert not np.asarray(deleted).any()
    delete_leg = C.objects_only(S.get_scene("stool").edits["delete_leg"], -0.91)
    under_the_leg = np.array([[0.42, 0.42, -0.92], [0.42, 0.42, -0.5]])
    assert np.asarray(delete_leg(under_the_leg)[1]).tolist() == [False, True]
    # the turn with the light turns the environment: its sky differs from the unedited views'
    turned = np.asarray(load_split(root / SCENE / "edits" / "turn_with_light", "test").images)
    unedited = np.asarray(load_split(root / SCENE / "unedited", "test").images)
    assert np.abs(turned[:, :4] - unedited[:, :4]).mean() > 0.01  # the top rows: sky


def test_listing_and_resume(root, tmp_path):
    listed = list_variants(root)
    assert [v[:2] for v in listed] == [(SCENE, None)] + [(SCENE, e) for e in EDITS]  # the copy is not listed
    assert listed[0][2] == root / SCENE / "unedited"
    meta = json.loads((root / SCENE / "scene.json").read_text())
    assert meta["layout"] == "colmap" and meta["split"]["test"] == [C.image_name(0), C.image_name(8)]
    assert meta["effects"]["background_model"] == "sphere" and meta["ground"]["z"] < -0.85
    assert meta["sfm"]["outliers"] == 120 and list(meta["edits"]) == EDITS
    # a finished scene is kept on resume; a missing nerfstudio copy is written again without rendering
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(root, copy)
    shutil.rmtree(copy / f"{SCENE}_ns")
    before = digest_tree(copy / SCENE)
    generate_scene(SCENE, MINI, copy, seed=0, edits=EDITS, resume=True)
    assert digest_tree(copy / SCENE) == before
    assert digest_tree(copy / f"{SCENE}_ns") == digest_tree(root / f"{SCENE}_ns")


def test_cli_make_benchmark_same_seed_same_bytes(root, tmp_path, monkeypatch, capsys):
    """``ne-jax make-benchmark --preset tiny_capture`` (the small preset standing in) writes the
    same bytes as the fixture and a contact sheet of the capture root."""
    import ne_jax.benchmark.generate as generate
    from ne_jax.cli import main

    real = generate.generate_benchmark
    monkeypatch.setattr(generate, "generate_benchmark",
                        lambda out, preset, scenes, seed: real(out, MINI, scenes, seed, edits=EDITS))
    assert main(["make-benchmark", "--preset", "tiny_capture", "--out", str(tmp_path), "--scenes", SCENE]) == 0
    assert (tmp_path / "contact_sheet.png").is_file()
    for name in (SCENE, f"{SCENE}_ns"):
        assert digest_tree(tmp_path / name) == digest_tree(root / name)


def test_presets():
    for name, pt in (("tiny_capture", "tiny_pt"), ("default_capture", "default_pt")):
        preset, base = PRESETS[name], PRESETS[pt]
        assert preset.capture and not preset.alpha and preset.val_views == 0
        assert (preset.resolution, preset.test_views, preset.spp, preset.detail) == (
            base.resolution, base.test_views, base.spp, base.detail)
        assert preset.edit_train_views == base.train_views
        order = C.view_order(preset.train_views, preset.test_views)
        assert [k for k, (s, _) in enumerate(order) if s == "test"] == list(range(0, len(order), 8))
        assert preset.record()["capture"] is True
    assert "capture" not in PRESETS["tiny_pt"].record()  # the other presets' records keep their bytes
    with pytest.raises(ValueError, match="every 8th"):
        BenchmarkPreset("bad", 32, 20, 0, 2, 1, 0.4, 100, renderer="pathtrace", spp=4, alpha=False, capture=True)
    with pytest.raises(ValueError, match="validation"):
        BenchmarkPreset("bad", 32, 9, 1, 2, 1, 0.4, 100, renderer="pathtrace", spp=4, alpha=False, capture=True)
    with pytest.raises(ValueError, match="edit_train_views"):
        BenchmarkPreset("bad", 32, 9, 1, 2, 1, 0.4, 100, edit_train_views=3)
    assert C.view_order(9, 2)[:9] == [("test", 0)] + [("train", i) for i in range(7)] + [("test", 1)]
    q = C.rotation_to_quaternion(np.diag([-1.0, -1.0, 1.0]))  # 180 degrees about z
    np.testing.assert_allclose(np.abs(q), [0, 0, 0, 1], atol=1e-12)

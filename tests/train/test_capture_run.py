"""A capture end to end: a COLMAP folder in its own coordinates (no masks, a sparse noisy SfM cloud)
is trained from its SfM points with a background sphere, evaluated on its held-out images, rendered,
exported and edited, with every coordinate a user sees in the capture's frame."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from ne_jax.benchmark.generate import generate_scene
from ne_jax.cli import main
from ne_jax.data.ply import read_ply
from ne_jax.data.scene import SCENE_RECORD_FILE, detect_format, load_split
from ne_jax.edit.model import edit_model
from ne_jax.eval import evaluate_model
from ne_jax.pointcloud.init import Views
from ne_jax.train.effects import with_declared
from ne_jax.train.loop import initial_cloud, train
from ne_jax.train.model import load_trained

from tests.data.formats_fixtures import write_colmap_text
from tests.mini_presets import TRAIN_SCENE, short_run

# the capture's frame: the benchmark scene scaled by 3, turned and moved (what a SfM run might give)
SCALE = 3.0
TURN = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
SHIFT = np.array([5.0, -2.0, 1.0])


def _to_capture(xyz):
    return SCALE * np.asarray(xyz, np.float64) @ TURN.T + SHIFT


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """The benchmark's blocks scene as a COLMAP capture: images composited on grey (no alpha), the
    test view named first (every 8th image held out), SfM points from its surface samples."""
    bench = tmp_path_factory.mktemp("bench")
    generate_scene("blocks", TRAIN_SCENE, bench, seed=0, edits=())
    src = bench / "blocks"
    train_split, test_split = load_split(src, "train"), load_split(src, "test")
    c2w = np.concatenate([test_split.c2w, train_split.c2w]).astype(np.float64)
    c2w[:, :3, :3] = TURN @ c2w[:, :3, :3]
    c2w[:, :3, 3] = _to_capture(c2w[:, :3, 3])
    images = np.concatenate([test_split.images, train_split.images])
    names = [f"{i:03d}.png" for i in range(len(images))]
    cols = read_ply(src / "points.ply")
    rng = np.random.default_rng(0)
    surface = np.stack([cols[c] for c in "xyz"], 1)[rng.choice(len(cols["x"]), 400, replace=False)]
    surface += rng.normal(scale=0.005, size=surface.shape)
    outliers = rng.uniform(-1.5, 1.5, (12, 3))
    xyz = _to_capture(np.concatenate([surface, outliers]))
    rgb = np.full((len(xyz), 3), 128, np.uint8)
    err = np.full(len(xyz), 0.7)
    root = tmp_path_factory.mktemp("capture") / "blocks"
    h, w = images.shape[1:3]
    s = train_split
    write_colmap_text(root, c2w, names, cameras=((1, "PINHOLE", w, h, (s.fx, s.fy, s.cx, s.cy)),),
                      points=(xyz, rgb, err), images=False)
    from ne_jax.data.png import write_image

    grey = images[..., :3] * images[..., 3:] + 0.5 * (1 - images[..., 3:])
    (root / "images").mkdir()
    for name, img in zip(names, grey):
        write_image(root / "images" / name, img)
    return root, src


@pytest.fixture(scope="module")
def trained(capture, tmp_path_factory):
    root, _ = capture
    run = short_run(epochs=2, steps_per_epoch=3, round_epochs=(1, 1))
    run = run.replace(render=with_declared(run.render, {"background_model": "sphere"}))
    out = tmp_path_factory.mktemp("run") / "capture"
    return train(run, root, out, progress=False, log=lambda s: None), out


def test_the_capture_is_read_in_the_scene_frame(capture, trained):
    root, src = capture
    model, out = trained
    assert detect_format(root) == "colmap"
    assert model.initial["source"] == "sfm" and "structure-from-motion" in model.initial["info"]["why"]
    record = json.loads((out / SCENE_RECORD_FILE).read_text())
    assert record["format"] == "colmap" and record["split_rule"] == "every 8th held out"
    assert record["splits"]["test"] == ["000.png"]
    # capture -> scene frame undoes the capture's similarity up to one of its own: the scene-frame
    # cameras are the benchmark's moved by one similarity (a turn about z, a scale, a shift)
    frame = model.frame
    ours = load_split(root, "train").c2w.astype(np.float64)
    truth = load_split(src, "train").c2w.astype(np.float64)
    composed = frame.matrix() @ np.block([[SCALE * TURN, SHIFT[:, None]], [np.zeros((1, 3)), np.ones((1, 1))]])
    np.testing.assert_allclose(composed[:3, :3] @ truth[:, :3, 3].T + composed[:3, 3:], ours[:, :3, 3].T, atol=1e-4)
    rot = composed[:3, :3] / np.cbrt(np.linalg.det(composed[:3, :3]))
    np.testing.assert_allclose(rot @ truth[:, :3, :3], ours[:, :3, :3], atol=1e-5)
    assert rot[2, 2] > 0.95  # the benchmark's up stays about up (the mean up vector of 6 cameras)
    # near/far from the SfM points, recorded in the run's config
    near, far = record["near_far"]["envelope"]
    assert model.run.sampler.near == pytest.approx(near, rel=1e-5) and model.run.sampler.far == pytest.approx(far, 1e-5)


def test_a_capture_run_evaluates_renders_and_exports_in_its_own_coordinates(capture, trained, tmp_path, capsys):
    root, _ = capture
    model, out = trained
    report, _ = evaluate_model(model, load_split(root, "test"), progress=False)
    assert np.isfinite(report["psnr"]) and report["num_views"] == 1
    assert main(["eval", str(out), "--out", str(tmp_path / "eval")]) == 0
    # a subset of a split: views evenly spaced, named by their index in the split, the split's time projected
    train_views = load_split(root, "train").num_views
    assert main(["eval", str(out), "--split", "train", "--views", "2", "--out", str(tmp_path / "part")]) == 0
    part = json.loads((tmp_path / "part" / "metrics.json").read_text())
    assert part["num_views"] == 2 and part["subset"]["of"] == train_views
    assert part["subset"]["projected_split_seconds"] >= part["seconds"]
    written = sorted(p.name for p in (tmp_path / "part" / "images").iterdir())
    assert [name[:3] for name in written] == ["000", f"{train_views - 1:03d}"]
    assert all(name.count(".png") == 1 for name in written)  # the image's own name, not name.png.png
    assert "the whole split would take at most" in capsys.readouterr().out
    assert main(["render", str(out), "--orbit", "2", "--out", str(tmp_path / "orbit.gif")]) == 0
    assert (tmp_path / "orbit.gif").is_file()
    assert main(["export", str(out), "--out", str(tmp_path / "cloud.ply")]) == 0
    assert "capture's coordinates" in capsys.readouterr().out
    cols = read_ply(tmp_path / "cloud.ply")
    exported = np.stack([cols[c] for c in "xyz"], 1)
    alive = np.flatnonzero(np.asarray(model.scene.points.alive))
    np.testing.assert_array_equal(cols["index"], alive)
    np.testing.assert_allclose(exported, model.frame.to_capture(np.asarray(model.scene.points.xyz)[alive]),
                               rtol=1e-5, atol=1e-5 * SCALE)


def test_an_edit_file_in_capture_coordinates_lands_where_the_user_meant(trained, tmp_path):
    model, out = trained
    loaded = load_trained(out)
    assert np.allclose(loaded.frame.matrix(), model.frame.matrix())
    alive = np.flatnonzero(np.asarray(model.scene.points.alive))
    before = np.asarray(model.scene.points.xyz, np.float64)[alive]
    in_capture = model.frame.to_capture(before)
    step = np.array([0.3, 0.0, 0.0])  # capture units, along the capture's x
    rows = in_capture + step
    rows[:5] = np.nan  # deleted
    np.save(tmp_path / "edit.npy", rows)
    edited, report = edit_model(loaded, tmp_path / "edit.npy", tmp_path / "edited")
    assert report["deleted"] == 5
    after = np.asarray(edited.scene.points.xyz, np.float64)[alive[5:]]
    expected = model.frame.to_scene(in_capture[5:] + step)
    np.testing.assert_allclose(after, expected, atol=1e-4)
    assert np.allclose(load_trained(tmp_path / "edited").frame.matrix(), model.frame.matrix())


def test_an_sfm_start_is_densified_to_init_sfm_points_not_the_carving_count(capture):
    root, _ = capture
    init = short_run().init
    views = Views.from_split(load_split(root, "train"))
    cloud = initial_cloud(dataclasses.replace(init, source="sfm", sfm_points=900), root, views)
    assert len(cloud.xyz) == 900 != init.carve.num_points
    assert cloud.info["why"]

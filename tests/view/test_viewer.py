"""The viewer's server without a browser: it starts on a free port, serves its page, renders frames
of a browser camera in every mode, refuses a port in use, and its edit steps (select, move, delete,
undo, benchmark edits, save) give the edited model that ``ne-jax edit`` makes from the saved PLY."""

from __future__ import annotations

import dataclasses
import socket
import urllib.request

import numpy as np
import pytest

pytest.importorskip("viser")

from ne_jax.cli import main  # noqa: E402
from ne_jax.compiles import count_compiles  # noqa: E402
from ne_jax.data.nerf_synthetic import load_split  # noqa: E402
from ne_jax.train.model import load_trained  # noqa: E402
from ne_jax.view import edits as E  # noqa: E402
from ne_jax.view.frames import MODES, camera_from_viewer, look_at, render_frame  # noqa: E402
from ne_jax.view.viewer import Viewer, ViewerError  # noqa: E402


@pytest.fixture(scope="module")
def viewer(tiny_run):
    v = Viewer(tiny_run, port=0, max_side=32)
    yield v
    v.stop()


def test_serves_and_renders_a_camera(viewer, tiny_run):
    assert viewer.port > 0 and viewer.url.endswith(f":{viewer.port}")
    with urllib.request.urlopen(viewer.url, timeout=30) as r:
        assert r.status == 200 and b"<html" in r.read().lower()
    model = load_trained(tiny_run)
    c2w = np.asarray(load_split(model.scene_dir, "train").c2w[0], np.float64)
    pos = c2w[:3, 3]
    wxyz = look_at(pos, (0, 0, 0))
    frames = {}
    for mode in MODES:
        img, secs = viewer.render(wxyz, pos, np.deg2rad(40), 24, 16, mode)
        assert img.shape == (16, 24, 3) and img.dtype == np.uint8 and secs > 0
        frames[mode] = img
    assert frames["rgb"].std() > 0 and not np.array_equal(frames["rgb"], frames["depth"])
    # the frame is the model's render of the same camera (OpenCV -> OpenGL conversion included)
    want, _ = render_frame(model, camera_from_viewer(wxyz, pos, np.deg2rad(40), 24, 16))
    np.testing.assert_array_equal(frames["rgb"], want)
    # a camera moved elsewhere renders something else
    other, _ = viewer.render(look_at(-pos, (0, 0, 0)), -pos, np.deg2rad(40), 24, 16)
    assert not np.array_equal(other, frames["rgb"])


def test_preview_frames_shoot_one_ray_per_pixel(tiny_run):
    """A model trained with a pixel grid renders its full frames on that grid and its previews (the
    frames of a moving camera) with one ray per pixel."""
    base = load_trained(tiny_run)
    run = base.run.replace(render=base.run.render.replace(pixel_samples=2))
    model = dataclasses.replace(base, run=run)
    v = Viewer(model, port=0, max_side=32, warm_up=False)
    try:
        pos = np.asarray(load_split(base.scene_dir, "train").c2w[0], np.float64)[:3, 3]
        wxyz = look_at(pos, (0, 0, 0))
        cam = camera_from_viewer(wxyz, pos, np.deg2rad(40), 24, 16)
        full, _ = v.render(wxyz, pos, np.deg2rad(40), 24, 16)
        preview, _ = v.render(wxyz, pos, np.deg2rad(40), 24, 16, preview=True)
    finally:
        v.stop()
    np.testing.assert_array_equal(full, render_frame(model, cam)[0])
    np.testing.assert_array_equal(preview, render_frame(base, cam)[0])
    assert not np.array_equal(full, preview)


def test_port_in_use_and_missing_run_are_refused(viewer, tmp_path):
    with pytest.raises(ViewerError, match=f"port {viewer.port} on 127.0.0.1: expected a free port"):
        Viewer(viewer.model, port=viewer.port)
    with pytest.raises(ViewerError, match="expected a run directory"):
        Viewer(tmp_path / "nope", port=0)


def test_edit_steps_and_save_match_ne_jax_edit(viewer, tmp_path):
    xyz = np.asarray(viewer.model.scene.points.xyz)[np.asarray(viewer.model.scene.points.alive)]
    center = 0.5 * (xyz.min(0) + xyz.max(0))
    # the warm-up compiled the edit path: the first edit and its render compile neither the IST nor
    # the render of a carried tree (small eager ops for new shapes aside)
    assert viewer.warmed.wait(300) and "failed" not in viewer.status
    sel = viewer.select_region(E.Region.make("box", center, np.ptp(xyz, 0) * 0.3))
    wxyz, pos = look_at(center + (0, -3, 0), center), center + (0, -3, 0)
    with count_compiles() as compiled:
        viewer.move(E.Transform(translation=(0.05, 0, 0)))
        viewer.render(wxyz, pos, np.deg2rad(40), 24, 16)
    assert not {"jit(ist_from_plan)", "jit(_survey_chunk)", "jit(_render_chunk)"} & set(compiled.names), compiled.names
    assert viewer.undo() and viewer.edited_model is viewer.model
    with pytest.raises(E.SelectionError, match="found none"):
        viewer.select_region(E.Region.make("sphere", center + 100, 0.01))
        viewer.move(E.Transform(translation=(0.1, 0, 0)))
    sel = viewer.select_region(E.Region.make("box", center + (0, 0, 0.25 * np.ptp(xyz[:, 2])),
                                             np.ptp(xyz, 0) * (1.2, 1.2, 0.5)))
    assert 0 < sel.size < xyz.shape[0]
    viewer.move(E.Transform.from_euler(E.selection_center(viewer.edit, sel), (0.05, 0, 0), (0, 0, 30)))
    assert viewer.edited_model is not viewer.model and viewer.edit.changed(viewer._points)
    viewer.select(sel[:5])
    viewer.delete()
    assert int(viewer.edit.deleted.sum()) == 5
    out = tmp_path / "edited"
    report = viewer.save(out)
    assert report["deleted"] == 5 and (out / E.EDIT_PLY).is_file()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # nothing half written left
    saved = load_trained(out)
    np.testing.assert_array_equal(np.asarray(saved.scene.points.xyz), np.asarray(viewer.edited_model.scene.points.xyz))
    # `ne-jax edit RUN --edit out/edit.ply` makes the same edited model
    again = tmp_path / "again"
    assert main(["edit", str(viewer.model.run_dir), "--edit", str(out / E.EDIT_PLY), "--out", str(again),
                 "--no-eval"]) == 0
    cli = load_trained(again)
    np.testing.assert_array_equal(np.asarray(cli.scene.points.xyz), np.asarray(saved.scene.points.xyz))
    np.testing.assert_array_equal(np.asarray(cli.scene.points.alive), np.asarray(saved.scene.points.alive))
    np.testing.assert_array_equal(np.asarray(cli.scene.points.ist), np.asarray(saved.scene.points.ist))
    # undo twice: back to the unedited model; a benchmark edit loads by name
    assert viewer.undo() and viewer.undo() and not viewer.undo()
    assert viewer.edited_model is viewer.model
    viewer.load_edit("twist")
    assert viewer.edit.changed(viewer._points)
    assert viewer.undo()


def test_cli_view_reports_bad_input(tiny_run, tmp_path, capsys):
    assert main(["view", str(tmp_path / "missing")]) == 2
    assert "expected a run directory" in capsys.readouterr().err
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        assert main(["view", str(tiny_run), "--port", str(port)]) == 2
        assert f"port {port} on 127.0.0.1: expected a free port" in capsys.readouterr().err

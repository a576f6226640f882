"""apply_edit: edits from functions, .npy and .ply files and sequences; bad edits get named errors;
model parameters untouched; normals oriented; ISTs compose; a held edit context edits as one made on
the spot, and another cloud's is refused."""

import jax
import numpy as np
import pytest

from ne_jax.data.ply import write_ply
from ne_jax.edit.apply import EditConfig, apply_edit, apply_edit_with_report, edit_context
from ne_jax.edit.deformations import Edit, cut_points, delete_part, halfspace, rotation_matrix
from ne_jax.edit.ist import ISTConfig
from ne_jax.edit.targets import EditError
from ne_jax.geometry.points import PointState
from ne_jax.pointcloud.normals import NormalConfig, estimate_normals
from ne_jax.render.renderer import PointScene

from tests.mini_presets import tiny_render

N, CAP = 600, 640
R1 = np.asarray(rotation_matrix([1.0, 2.0, 3.0], 0.7), np.float64)
R2 = np.asarray(rotation_matrix([0.0, -1.0, 0.5], -1.1), np.float64)


@pytest.fixture(scope="module")
def points():
    x = np.random.default_rng(0).normal(size=(N, 3))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    n = estimate_normals(NormalConfig(orient="none"), x)
    n *= np.sign(np.sum(n * x, axis=1, keepdims=True))  # outward, like a trained model's
    return PointState.from_numpy(x, CAP, 8, normal=n, key=jax.random.key(0))


def rotation_edit(rot, name="rot"):
    return Edit(name, "rigid", lambda p: p @ np.asarray(rot, np.float32).T)


def test_function_edit_moves_points_and_keeps_parameters(points):
    edited, report = apply_edit_with_report(points, rotation_edit(R1))
    alive = np.asarray(points.alive)
    np.testing.assert_allclose(np.asarray(edited.xyz)[alive], np.asarray(points.xyz)[alive] @ R1.T, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(edited.feature), np.asarray(points.feature))
    np.testing.assert_array_equal(np.asarray(edited.conf_logit), np.asarray(points.conf_logit))
    assert edited.capacity == CAP
    ist = np.asarray(edited.ist)
    np.testing.assert_allclose(ist[alive], np.broadcast_to(R1.T, (N, 3, 3)), atol=1e-5)
    np.testing.assert_allclose(ist[~alive], np.broadcast_to(np.eye(3), (CAP - N, 3, 3)))
    # normals re-estimated and oriented like the originals (outward), not Open3D's arbitrary signs
    np.testing.assert_allclose(np.asarray(edited.normal)[alive], np.asarray(points.normal)[alive] @ R1.T, atol=1e-4)
    assert report["moved"] == N and report["deleted"] == 0 and report["good"] == N


def test_kept_normals_switch_leaves_every_normal_as_it_was(points):
    """The analysis switch ``reestimate_normals=False``: positions and IST as usual, normals untouched."""
    edited = apply_edit(points, rotation_edit(R1), EditConfig(reestimate_normals=False))
    alive = np.asarray(points.alive)
    np.testing.assert_array_equal(np.asarray(edited.normal)[alive], np.asarray(points.normal)[alive])
    np.testing.assert_allclose(np.asarray(edited.ist)[alive], np.broadcast_to(R1.T, (N, 3, 3)), atol=1e-5)


def test_deletion_flips_alive_only(points):
    edited, report = apply_edit_with_report(points, delete_part("cap", halfspace([0, 0, 1], 0.5)))
    z = np.asarray(points.xyz)[:, 2]
    expect = np.asarray(points.alive) & ~(z > 0.5)
    np.testing.assert_array_equal(np.asarray(edited.alive), expect)
    np.testing.assert_array_equal(np.asarray(edited.xyz), np.asarray(points.xyz))
    assert report["deleted"] == int((z[:N] > 0.5).sum()) and report["moved"] == 0
    np.testing.assert_allclose(np.asarray(edited.ist)[expect], np.broadcast_to(np.eye(3), (expect.sum(), 3, 3)),
                               atol=1e-5)


def test_npy_rows_with_nan_deletions(points, tmp_path):
    rows = np.asarray(points.xyz)[:N] @ R1.T
    rows[:10] = np.nan
    path = tmp_path / "edit.npy"
    np.save(path, rows)
    edited = apply_edit(points, path)
    assert not np.asarray(edited.alive)[:10].any() and np.asarray(edited.alive)[10:N].all()
    np.testing.assert_allclose(np.asarray(edited.xyz)[10:N], rows[10:], atol=1e-6)
    full = np.vstack([rows, np.zeros((CAP - N, 3))])  # one row per slot works too
    np.testing.assert_array_equal(np.asarray(apply_edit(points, full).alive), np.asarray(edited.alive))


@pytest.mark.parametrize("rows, message", [
    (np.zeros((N - 1, 3)), rf"expected new positions of shape \[{N}, 3\].*found shape \({N - 1}, 3\)"),
    (np.zeros((N, 2)), r"found shape \(600, 2\)"),
])
def test_npy_wrong_shape_is_named(points, tmp_path, rows, message):
    path = tmp_path / "bad.npy"
    np.save(path, rows)
    with pytest.raises(EditError, match=message) as e:
        apply_edit(points, path)
    assert str(path) in str(e.value)


def test_partial_nan_row_is_refused(points):
    rows = np.asarray(points.xyz)[:N].copy()
    rows[7, 1] = np.nan
    with pytest.raises(EditError, match=r"all-NaN rows for deleted points.*first row 7"):
        apply_edit(points, rows)
    rows[7] = [np.inf, 0, 0]
    with pytest.raises(EditError, match="first row 7"):
        apply_edit(points, rows)


def test_deleting_everything_is_refused(points):
    with pytest.raises(EditError, match=f"all {N} alive points deleted"):
        apply_edit(points, np.full((N, 3), np.nan))


def test_missing_file_and_unknown_suffix(points, tmp_path):
    with pytest.raises(EditError, match="found nothing"):
        apply_edit(points, tmp_path / "none.npy")
    (tmp_path / "e.txt").write_text("1 2 3")
    with pytest.raises(EditError, match=r"expected a \.npy or \.ply edit file, found suffix '\.txt'"):
        apply_edit(points, tmp_path / "e.txt")
    with pytest.raises(EditError, match="found int"):
        apply_edit(points, 3)


def _ply(path, xyz, index):
    write_ply(path, {"x": xyz[:, 0].astype(np.float32), "y": xyz[:, 1].astype(np.float32),
                     "z": xyz[:, 2].astype(np.float32), "index": np.asarray(index, np.int32)})


def test_ply_with_index_moves_listed_points_and_deletes_the_rest(points, tmp_path):
    keep = np.arange(50, N)[::-1]  # any order
    xyz = np.asarray(points.xyz)[keep] @ R1.T
    _ply(tmp_path / "e.ply", xyz, keep)
    edited, report = apply_edit_with_report(points, tmp_path / "e.ply")
    assert report["deleted"] == 50 and not np.asarray(edited.alive)[:50].any()
    np.testing.assert_allclose(np.asarray(edited.xyz)[keep], xyz, atol=1e-6)


@pytest.mark.parametrize("index, message", [
    (lambda i: np.r_[i[:-1], i[0]], "expected each index once, found index 0 2 times"),
    (lambda i: np.r_[i[:-1], N + 5], f"expected indices of alive points, found 1 of dead slots \\(first: {N + 5}\\)"),
    (lambda i: np.r_[i[:-1], CAP], rf"expected indices in \[0, {CAP}\), found {CAP}"),
])
def test_bad_ply_indices_are_named(points, tmp_path, index, message):
    idx = index(np.arange(N))
    _ply(tmp_path / "bad.ply", np.zeros((len(idx), 3)), idx)
    with pytest.raises(EditError, match=message):
        apply_edit(points, tmp_path / "bad.ply")


def test_ply_without_index_is_named(points, tmp_path):
    write_ply(tmp_path / "noidx.ply", {"x": np.zeros(3, np.float32), "y": np.zeros(3, np.float32),
                                       "z": np.zeros(3, np.float32)})
    with pytest.raises(EditError, match=r"missing \['index'\]"):
        apply_edit(points, tmp_path / "noidx.ply")


def test_sequences_and_repeated_edits_compose_the_ist(points):
    both = R2 @ R1
    once = apply_edit(points, [rotation_edit(R1), rotation_edit(R2, "rot2")])
    twice = apply_edit(apply_edit(points, rotation_edit(R1)), rotation_edit(R2, "rot2"))
    alive = np.asarray(points.alive)
    for edited in (once, twice):
        np.testing.assert_allclose(np.asarray(edited.xyz)[alive], np.asarray(points.xyz)[alive] @ both.T, atol=1e-5)
    # a sequence is one edit from the original: its IST is (R2 R1)^T; two edits compose theirs
    np.testing.assert_allclose(np.asarray(once.ist)[alive], np.broadcast_to(both.T, (N, 3, 3)), atol=1e-5)
    np.testing.assert_allclose(np.asarray(twice.ist)[alive], np.broadcast_to(both.T, (N, 3, 3)), atol=2e-5)


def _same(a, b):
    jax.tree_util.tree_map(np.testing.assert_array_equal, a, b)


def _without_seconds(report):
    return {k: v for k, v in report.items() if k != "seconds"}


def test_a_held_context_edits_as_one_made_on_the_spot(points):
    render = tiny_render()
    scene = PointScene.build(points, render)
    cfg = EditConfig()
    context = edit_context(cfg, points, scene, render)
    assert context.carry is not None and context.neighbors.alive.sum() == N
    cut = Edit("cut", "cut", lambda p: cut_points(p, (0.05, 0.0, 0.0), (1.0, 0.0, 0.0), 0.5))
    for edit in (cut, delete_part("cap", halfspace([0, 0, 1], 0.5))):  # the second deletes: its own table
        spot, spot_report = apply_edit_with_report(points, edit)
        held, held_report = apply_edit_with_report(points, edit, cfg, context)
        _same(held, spot)
        assert _without_seconds(held_report) == _without_seconds(spot_report)
        _same(cfg.scene(scene, held, render, context), cfg.scene(scene, spot, render))
    # an edited scene (its tree carried from the rest cloud) edited again with its own context
    once = cfg.scene(scene, apply_edit(points, cut), render)
    again = edit_context(cfg, once.points, once, render)
    twice = apply_edit(once.points, rotation_edit(R1), cfg, again)
    _same(cfg.scene(once, twice, render, again), cfg.scene(once, twice, render))


def test_a_context_of_another_cloud_is_refused(points):
    other = points.replace(xyz=1.01 * points.xyz)
    with pytest.raises(ValueError, match="another cloud"):
        apply_edit(points, rotation_edit(R1), context=edit_context(EditConfig(), other))
    with pytest.raises(ValueError, match="8 candidates.*found one of 4"):
        apply_edit(points, rotation_edit(R1), context=edit_context(EditConfig(ist=ISTConfig(candidates=4)), points))
    render = tiny_render()
    scene = PointScene.build(points, render)
    edited = apply_edit(points, rotation_edit(R1))
    wrong = edit_context(EditConfig(), other, PointScene.build(other, render), render)
    with pytest.raises(ValueError, match="another cloud"):
        EditConfig().scene(scene, edited, render, wrong)

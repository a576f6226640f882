"""The viewer's edit logic without a browser: selection by region and by screen rectangle, gizmo
transforms, deletion, zero-point selections refused, and the PLY that ``ne-jax edit`` reads."""

from __future__ import annotations

import numpy as np
import pytest

from ne_jax.data.ply import read_ply
from ne_jax.edit.deformations import ball, delete_part
from ne_jax.edit.targets import edit_target
from ne_jax.geometry.points import PointState
from ne_jax.view import edits as E


@pytest.fixture
def points():
    rng = np.random.default_rng(0)
    xyz = rng.uniform(-1, 1, (400, 3)).astype(np.float32)
    pts = PointState.from_numpy(xyz, capacity=420, feature_dim=4)  # 20 dead slots
    alive = np.asarray(pts.alive).copy()
    alive[[3, 50]] = False  # dead slots among the first N too
    return pts.replace(alive=alive)


def _quat(axis, deg):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    a = np.deg2rad(deg) / 2
    return np.concatenate([[np.cos(a)], np.sin(a) * axis])


def test_rotations_round_trip():
    for axis, deg in [((0, 0, 1), 30), ((1, 1, 2), 170), ((2, -1, 0.5), -75), ((1, 0, 0), 0)]:
        r = E.quat_to_matrix(_quat(axis, deg))
        np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(E.quat_to_matrix(E.matrix_to_quat(r)), r, atol=1e-12)
        np.testing.assert_allclose(E.euler_deg_to_matrix(E.matrix_to_euler_deg(r)), r, atol=1e-12)
    np.testing.assert_allclose(E.euler_deg_to_matrix((0, 0, 90)) @ [1, 0, 0], [0, 1, 0], atol=1e-12)


def test_region_selection_against_a_loop(points):
    edit = E.ViewEdit.identity(points)
    xyz, alive = np.asarray(points.xyz, np.float64), np.asarray(points.alive)
    box = E.Region.make("box", (0.1, -0.2, 0.3), (0.8, 0.6, 1.0), _quat((0, 0, 1), 30))
    r = E.quat_to_matrix(_quat((0, 0, 1), 30))
    want = [i for i in range(points.capacity)
            if alive[i] and all(abs(float(r[:, k] @ (xyz[i] - (0.1, -0.2, 0.3)))) <= (0.4, 0.3, 0.5)[k]
                                for k in range(3))]
    np.testing.assert_array_equal(E.select_region(edit, box), want)
    sphere = E.Region.make("sphere", (0, 0, 0), 0.5)
    want = [i for i in range(points.capacity) if alive[i] and np.linalg.norm(xyz[i]) <= 0.5]
    got = E.select_region(edit, sphere)
    np.testing.assert_array_equal(got, want)
    assert got.dtype == np.int64 and 3 not in got and 50 not in got
    # deleted points are not selectable any more
    gone = E.delete_points(edit, got[:5])
    assert set(E.select_region(gone, sphere)) == set(got[5:])


def test_screen_rect_selection_matches_projection(points):
    edit = E.ViewEdit.identity(points)
    # a camera at (0, 0, 4) looking down -z (OpenCV: +z forward, so rotate 180 degrees about x)
    c2w = np.eye(4)
    c2w[:3, :3] = E.quat_to_matrix(_quat((1, 0, 0), 180))
    c2w[:3, 3] = (0, 0, 4)
    fov, aspect = np.deg2rad(40.0), 1.5
    got = E.select_screen_rect(edit, c2w, fov, aspect, (0.5, 0.5), (1.0, 1.0))
    xyz = np.asarray(points.xyz, np.float64)
    alive = np.asarray(points.alive)
    # seen from above with +y down in the image: the bottom-right quarter is x > 0, y < 0 in the world
    want = np.flatnonzero(alive & (xyz[:, 0] >= 0) & (xyz[:, 1] <= 0))
    np.testing.assert_array_equal(got, want)
    everything = E.select_screen_rect(edit, c2w, fov, aspect, (0, 0), (1, 1))
    np.testing.assert_array_equal(everything, np.flatnonzero(alive))
    behind = c2w.copy()
    behind[:3, 3] = (0, 0, -4)  # looking away from the cloud
    assert E.select_screen_rect(edit, behind, fov, aspect, (0, 0), (1, 1)).size == 0


def test_gizmo_transform_moves_the_selection_only(points):
    edit = E.ViewEdit.identity(points)
    sel = E.select_region(edit, E.Region.make("sphere", (0.3, 0.3, 0.3), 0.5))
    pivot = E.selection_center(edit, sel)
    t = E.Transform.from_gizmo(pivot, (1, 0, 0, 0), pivot + (0.1, 0.0, -0.2), _quat((0, 0, 1), 90), scale=1.5)
    moved = E.move_points(edit, sel, t)
    xyz = np.asarray(points.xyz, np.float64)
    rz = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1.0]])
    want = pivot + (0.1, 0.0, -0.2) + 1.5 * (xyz[sel] - pivot) @ rz.T
    np.testing.assert_allclose(moved.xyz[sel], want, atol=1e-5)
    others = np.setdiff1d(np.arange(points.capacity), sel)
    np.testing.assert_array_equal(moved.xyz[others], edit.xyz[others])
    assert moved.xyz.dtype == np.float32 and not moved.deleted.any()
    # the same motion from the numeric fields (Euler angles)
    t2 = E.Transform.from_euler(pivot, (0.1, 0.0, -0.2), (0, 0, 90), 1.5)
    np.testing.assert_allclose(E.move_points(edit, sel, t2).xyz, moved.xyz, atol=1e-6)
    with pytest.raises(ValueError, match="scale"):
        E.Transform(scale=0.0)


def test_zero_point_selection_is_refused(points):
    edit = E.ViewEdit.identity(points)
    empty = E.select_region(edit, E.Region.make("sphere", (5, 5, 5), 0.1))
    assert empty.size == 0
    with pytest.raises(E.SelectionError, match="at least one point, found none"):
        E.move_points(edit, empty, E.Transform(translation=(1, 0, 0)))
    with pytest.raises(E.SelectionError, match="at least one point, found none"):
        E.delete_points(edit, empty)
    with pytest.raises(E.SelectionError, match="alive and not deleted"):
        E.delete_points(edit, [3])  # a dead slot
    with pytest.raises(E.SelectionError, match="at least one point to remain"):
        E.delete_points(edit, np.flatnonzero(edit.remaining))


def test_ply_is_what_ne_jax_edit_reads(points, tmp_path):
    edit = E.ViewEdit.identity(points)
    sel = E.select_region(edit, E.Region.make("box", (0.5, 0.5, 0), 1.0))
    edit = E.move_points(edit, sel, E.Transform.from_euler((0, 0, 0), (0.2, -0.1, 0.05), (10, 20, 30), 0.9))
    edit = E.delete_points(edit, E.select_region(edit, E.Region.make("sphere", (-0.5, -0.5, -0.5), 0.4)))
    path = tmp_path / "edit.ply"
    n = E.write_edit_ply(path, edit)
    props = read_ply(path)
    assert sorted(props) == ["index", "x", "y", "z"] and n == int(edit.remaining.sum())
    # `ne-jax edit RUN --edit edit.ply` reads a PLY with edit_target: the same target as the viewer's rows
    from_ply = edit_target(points, path)
    from_rows = edit_target(points, edit.rows())
    alive = np.asarray(points.alive)
    np.testing.assert_array_equal(from_ply.deleted, edit.deleted)
    np.testing.assert_array_equal(from_rows.deleted, edit.deleted)
    keep = alive & ~edit.deleted
    np.testing.assert_array_equal(from_ply.xyz[keep], edit.xyz[keep])
    np.testing.assert_array_equal(from_rows.xyz[keep], edit.xyz[keep])
    # an edit loaded back from its own PLY (or from a benchmark-style Edit) is the same edit
    back = E.ViewEdit.from_source(points, path)
    np.testing.assert_array_equal(back.xyz[keep], edit.xyz[keep])
    np.testing.assert_array_equal(back.deleted, edit.deleted)
    fn = delete_part("cut_ball", ball((0.0, 0.0, 0.0), 0.3))
    by_fn = E.ViewEdit.from_source(points, fn)
    by_region = E.delete_points(E.ViewEdit.identity(points),
                                E.select_region(E.ViewEdit.identity(points), E.Region.make("sphere", (0, 0, 0), 0.3)))
    # the region's boundary is inclusive, the benchmark ball's is strict: compare away from it
    d = np.linalg.norm(np.asarray(points.xyz, np.float64), axis=1)
    away = np.abs(d - 0.3) > 1e-6
    np.testing.assert_array_equal(by_fn.deleted[away], by_region.deleted[away])


def test_move_fields_in_capture_coordinates():
    """A move typed in a capture's coordinates (``offsets_to_model``) moves the model-frame points as the
    same move moves the capture's points: frame(move_capture(x)) == move_model(frame(x)); and
    ``offsets_to_capture`` inverts it (the gizmo's motion shown in the fields)."""
    from ne_jax.data.scene import Normalisation

    rn = E.euler_deg_to_matrix((10.0, -30.0, 75.0))
    frame = Normalisation(scale=0.37, rotation=tuple(map(tuple, rn)), translation=(0.2, -1.0, 0.5))
    rng = np.random.default_rng(0)
    x_cap, pivot_cap = rng.normal(size=(20, 3)), rng.normal(size=3)
    t_cap, angles = np.array([0.3, -0.1, 2.0]), np.array([20.0, 5.0, -40.0])
    moved_cap = E.Transform.from_euler(pivot_cap, t_cap, angles, 1.5).apply(x_cap)
    t, rot = E.offsets_to_model(frame, t_cap, angles)
    in_model = E.Transform(tuple(map(tuple, rot)), tuple(t), 1.5, tuple(frame.to_scene(pivot_cap[None])[0]))
    np.testing.assert_allclose(in_model.apply(frame.to_scene(x_cap)), frame.to_scene(moved_cap), atol=1e-12)
    back_t, back_angles = E.offsets_to_capture(frame, t, rot)
    np.testing.assert_allclose(back_t, t_cap, atol=1e-12)
    np.testing.assert_allclose(back_angles, angles, atol=1e-9)

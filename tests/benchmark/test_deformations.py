"""Edits as functions of points: their geometry, identities, and gradients."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ne_jax.edit import deformations as D


@pytest.fixture
def points():
    return np.random.default_rng(0).uniform(-1, 1, (500, 3)).astype(np.float32)


def test_bend_zero_angle_is_identity(points):
    out = D.bend_points(jnp.asarray(points), (0, 0, 0), (0, 0, 1), (1, 0, 0), 0.0, 1.0)
    np.testing.assert_array_equal(np.asarray(out), points)


def test_bend_maps_center_line_to_arc():
    u = jnp.linspace(-1, 1, 201)
    line = jnp.stack([jnp.zeros_like(u), jnp.zeros_like(u), u], 1)
    angle, length = np.deg2rad(90.0), 2.0
    arc = np.asarray(D.bend_points(line, (0, 0, 0), (0, 0, 1), (1, 0, 0), angle, length), np.float64)
    radius = length / angle
    # On the circle of that radius centred at (R, 0, 0), and arc length preserved.
    np.testing.assert_allclose(np.linalg.norm(arc - [radius, 0, 0], axis=1), radius, atol=2e-6)
    seg = np.linalg.norm(np.diff(arc, axis=0), axis=1).sum()
    assert seg == pytest.approx(2.0, rel=1e-4)


def test_bend_reference_formula(points):
    """Against the textbook form with explicit radius (float64)."""
    angle, length = 0.7, 1.5
    k = angle / length
    out = np.asarray(D.bend_points(jnp.asarray(points), (0, 0, 0), (0, 1, 0), (0, 0, 1), angle, length))
    p = points.astype(np.float64)
    u, w = p[:, 1], p[:, 2]
    theta, rho = k * u, 1 / k - w
    ref = np.stack([p[:, 0], rho * np.sin(theta), 1 / k - rho * np.cos(theta)], 1)
    np.testing.assert_allclose(out, ref, atol=3e-6)


def test_twist_keeps_distance_to_axis_and_height(points):
    out = np.asarray(D.twist_points(jnp.asarray(points), (0, 0, 0), (0, 0, 1), 1.3))
    np.testing.assert_allclose(np.hypot(out[:, 0], out[:, 1]), np.hypot(points[:, 0], points[:, 1]), atol=2e-6)
    np.testing.assert_allclose(out[:, 2], points[:, 2], atol=1e-7)
    angle = np.arctan2(out[:, 1], out[:, 0]) - np.arctan2(points[:, 1], points[:, 0])
    wrapped = (angle - 1.3 * points[:, 2] + np.pi) % (2 * np.pi) - np.pi
    far = np.hypot(points[:, 0], points[:, 1]) > 0.05
    np.testing.assert_allclose(wrapped[far], 0.0, atol=1e-4)


def test_rigid_part_moves_only_region_rigidly(points):
    edit = D.rigid_part("r", D.halfspace((0, 0, 1), 0.2), (1, 1, 0), 40.0, (0.1, 0, 0.2), (0, 0.3, 0))
    moved, deleted = map(np.asarray, edit(points))
    inside = points[:, 2] > 0.2
    assert not deleted.any()
    np.testing.assert_array_equal(moved[~inside], points[~inside])
    d_before = np.linalg.norm(points[inside][:, None] - points[inside][None], axis=-1)
    d_after = np.linalg.norm(moved[inside][:, None] - moved[inside][None], axis=-1)
    np.testing.assert_allclose(d_after, d_before, atol=1e-5)


def test_cut_pulls_sides_apart(points):
    moved = np.asarray(D.cut_points(jnp.asarray(points), (0, 0, 0.1), (0, 0, 2), 0.4))
    above = points[:, 2] > 0.1
    np.testing.assert_allclose(moved[above] - points[above], np.broadcast_to([0, 0, 0.2], (above.sum(), 3)),
                               atol=1e-6)
    np.testing.assert_allclose(moved[~above] - points[~above], np.broadcast_to([0, 0, -0.2], ((~above).sum(), 3)),
                               atol=1e-6)


def test_delete_and_compose(points):
    delete = D.delete_part("d", D.ball((0, 0, 0), 0.5))
    shift = D.cut("c", (0, 0, 0), (1, 0, 0), 2.0)  # moves x>0 by +1, others by -1
    both = D.compose("both", shift, delete)
    moved, deleted = map(np.asarray, both(points))
    # deleted where the *shifted* point is inside the ball
    ref_moved = np.asarray(shift(points)[0])
    np.testing.assert_array_equal(moved, ref_moved)
    np.testing.assert_array_equal(deleted, np.linalg.norm(ref_moved, axis=1) < 0.5)


def test_apply_matches_call(points):
    edit = D.twist("t", (0, 0, 0), (0, 1, 0), 45.0)
    a, b = edit(points), edit.apply(points)
    np.testing.assert_allclose(np.asarray(a[0]), np.asarray(b[0]), atol=1e-6)
    np.testing.assert_array_equal(np.asarray(a[1]), np.asarray(b[1]))


def test_transform_normals_rotation_and_scaling():
    rot = D.rigid_part("r", lambda p: jnp.ones(p.shape[0], bool), (0, 0, 1), 90.0, (0, 0, 0))
    n = D.transform_normals(rot, np.zeros((1, 3)), np.array([[1.0, 0, 0]]))
    np.testing.assert_allclose(np.asarray(n), [[0, 1, 0]], atol=1e-6)
    # Non-rigid: squash z by 1/2 -> a 45-degree normal tilts towards z (inverse transpose).
    squash = D.Edit("s", "test", lambda p: p * jnp.array([1.0, 1.0, 0.5]))
    n = np.asarray(D.transform_normals(squash, np.zeros((1, 3)), np.array([[1.0, 0, 1.0]]) / np.sqrt(2)))
    np.testing.assert_allclose(n, [[1 / np.sqrt(5), 0, 2 / np.sqrt(5)]], atol=1e-6)


def test_gradient_through_bend_angle_is_finite():
    p = jnp.asarray(np.random.default_rng(1).uniform(-1, 1, (100, 3)), jnp.float32)

    def loss(angle):
        return jnp.sum(D.bend_points(p, (0, 0, 0), (0, 0, 1), (1, 0, 0), angle, 1.0) ** 2)

    for angle in (0.0, 1e-8, 0.5, np.pi):
        g = jax.grad(loss)(jnp.float32(angle))
        assert np.isfinite(g)
    # finite difference check at a generic angle
    eps = 1e-3
    fd = (loss(0.5 + eps) - loss(0.5 - eps)) / (2 * eps)
    assert float(jax.grad(loss)(jnp.float32(0.5))) == pytest.approx(float(fd), rel=2e-2)


def test_rotation_matrix_is_orthonormal():
    r = np.asarray(D.rotation_matrix((1, 2, 3), 0.7))
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-6)
    assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-6)


def test_rigid_scene_moves_every_point_by_its_matrix(points):
    edit = D.rigid_scene("turn", (1, 1, 2), 40.0, pivot=(0.2, -0.1, 0.3), translation=(0.0, 0.5, 0.0))
    motion = edit.matrix
    rot, shift = motion[:3, :3], motion[:3, 3]
    np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(rot) == pytest.approx(1.0, abs=1e-12)
    axis = np.array([1.0, 1, 2]) / np.sqrt(6)
    np.testing.assert_allclose(rot @ axis, axis, atol=1e-12)
    np.testing.assert_allclose(motion[:3, :3] @ [0.2, -0.1, 0.3] + shift, [0.2, 0.4, 0.3], atol=1e-12)  # pivot, shifted
    # the same rotation as rotate_points (then the translation), in float32
    ref = np.asarray(D.rotate_points(jnp.asarray(points), (1, 1, 2), np.deg2rad(40.0), (0.2, -0.1, 0.3))) + [0, 0.5, 0]
    moved, deleted = map(np.asarray, edit(points))
    assert not deleted.any()
    np.testing.assert_allclose(moved, points.astype(np.float64) @ rot.T + shift, atol=2e-6)
    np.testing.assert_allclose(moved, ref, atol=2e-6)
    normals = np.asarray(D.transform_normals(edit, points, np.tile([[0.0, 0.6, 0.8]], (len(points), 1))))
    np.testing.assert_allclose(normals, np.tile(rot @ [0.0, 0.6, 0.8], (len(points), 1)), atol=2e-6)


def test_rigid_scene_flags_and_other_edits():
    fixed = D.rigid_scene("a", (0, 0, 1), 30.0)
    moving = D.rigid_scene("b", (0, 0, 1), 30.0, moves_environment=True)
    assert not fixed.moves_environment and moving.moves_environment and fixed.kind == moving.kind == "rigid_scene"
    np.testing.assert_array_equal(fixed.matrix, moving.matrix)
    assert hash(fixed) != hash(moving) or fixed != moving  # hashable: a static jit argument
    # edits that are not one whole-scene motion carry none
    part = D.rigid_part("r", D.halfspace((0, 0, 1), 0.0), (1, 0, 0), 20.0, (0, 0, 0))
    assert part.rigid is None and part.matrix is None and not part.moves_environment
    # cameras move with the scene as T @ c2w: a point fixed in the camera frame follows T
    c2w = np.eye(4)
    c2w[:3, 3] = (0.0, 0.0, 4.0)
    p_cam = np.array([0.1, -0.2, -3.0, 1.0])
    np.testing.assert_allclose((moving.matrix @ c2w) @ p_cam, moving.matrix @ (c2w @ p_cam), atol=1e-12)
    moved = np.asarray(moving(np.asarray([(c2w @ p_cam)[:3]], np.float32))[0])[0]
    np.testing.assert_allclose(moved, ((moving.matrix @ c2w) @ p_cam)[:3], atol=2e-6)

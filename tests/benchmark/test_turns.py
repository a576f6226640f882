"""The whole-scene turns every benchmark scene ends with: ``turn_with_light`` (lights and sky turn
with the scene; ground truth is the original scene seen from the cameras ``T^-1 @ c2w``) and
``turn_scene`` (lights and sky stay; the turned mesh is rendered)."""

import hashlib
import json

import numpy as np
import pytest

from ne_jax.benchmark import raycaster
from ne_jax.benchmark import scenes as S
from ne_jax.benchmark.generate import generate_scene
from ne_jax.data import cameras
from ne_jax.data.nerf_synthetic import load_split, write_split
from ne_jax.data.ply import read_ply
from ne_jax.edit import deformations as D

from tests.mini_presets import GEN_SCENES

TURNS = ("turn_with_light", "turn_scene")


@pytest.fixture(scope="module")
def glossy_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("turns")
    generate_scene("glossy", GEN_SCENES, root, seed=0)
    return root


def _digests(directory):
    return {str(p.relative_to(directory)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(directory.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("name", sorted(S.SCENES))
def test_every_scene_ends_with_the_same_two_turns(name):
    scene = S.get_scene(name, 0.3)
    assert list(scene.edits)[-2:] == list(TURNS) and len(scene.edits) == 6
    with_light, fixed = (scene.edits[t] for t in TURNS)
    assert with_light.moves_environment and not fixed.moves_environment
    assert all(not e.moves_environment and e.rigid is None for e in list(scene.edits.values())[:4])
    expected = D.rigid_motion(S.TURN_AXIS, S.TURN_DEGREES, S.TURN_PIVOT)
    np.testing.assert_array_equal(with_light.matrix, expected)
    np.testing.assert_array_equal(fixed.matrix, expected)


def test_co_moving_truth_is_the_original_from_inversely_moved_cameras(glossy_root, tmp_path):
    """Bit for bit: the PNGs of ``turn_with_light`` are the original scene rendered from ``T^-1 @ c2w``,
    while its transforms hold the original cameras."""
    scene = S.get_scene("glossy", GEN_SCENES.detail)
    edit = scene.edits["turn_with_light"]
    target = glossy_root / "glossy" / "edits" / "turn_with_light"
    cams = cameras.orbit_cameras(GEN_SCENES.test_views)
    written = json.loads((target / "transforms_test.json").read_text())
    np.testing.assert_array_equal([f["transform_matrix"] for f in written["frames"]], cams)
    caster = raycaster.RayCaster(S.apply_to_mesh(scene.mesh, None), scene.materials)
    moved = np.linalg.inv(edit.matrix) @ cams
    res = GEN_SCENES.resolution
    images = np.stack([caster.render(c, res, res, cameras.CAMERA_ANGLE_X, GEN_SCENES.supersample)
                       for c in moved]).astype(np.float32)
    write_split(tmp_path, "test", images, cams, cameras.CAMERA_ANGLE_X)
    assert {k: v for k, v in _digests(tmp_path).items() if k.endswith(".png")} == \
        {k: v for k, v in _digests(target).items() if k.startswith("test/")}


def test_turning_mesh_lights_and_sky_together_is_moving_the_camera():
    """The principle behind the co-moving ground truth: the mesh turned by ``T`` with lights and sky
    turned by ``T`` (``RayCaster(environment=R)``), seen from ``T @ c2w``, is the original seen from
    ``c2w`` (up to float32 ray casting on different vertex coordinates: ~1e-5 here)."""
    scene = S.get_scene("glossy", 0.5)
    edit = scene.edits["turn_scene"]
    motion = edit.matrix
    c2w = cameras.orbit_cameras(8)[1]
    original = raycaster.RayCaster(S.apply_to_mesh(scene.mesh, None), scene.materials).render(
        c2w, 32, 32, cameras.CAMERA_ANGLE_X, 2)
    turned = raycaster.RayCaster(S.apply_to_mesh(scene.mesh, edit), scene.materials, environment=motion[:3, :3])
    image = turned.render(motion @ c2w, 32, 32, cameras.CAMERA_ANGLE_X, 2)
    diff = np.abs(image - original).max(-1)
    assert 0.2 < original[..., 3].mean() < 0.9
    assert np.mean(diff > 1e-4) <= 0.005 and diff.mean() < 1e-4
    # the same turn with the lights and sky fixed looks different on this glossy scene: highlights
    # and reflections slide over the surface
    fixed = raycaster.RayCaster(S.apply_to_mesh(scene.mesh, edit), scene.materials).render(motion @ c2w, 32, 32,
                                                                                   cameras.CAMERA_ANGLE_X, 2)
    np.testing.assert_array_equal(fixed[..., 3], image[..., 3])
    assert np.abs(fixed - image)[..., :3].max() > 0.2


def test_fixed_environment_turn_by_zero_degrees_is_the_original():
    scene = S.get_scene("glossy", 0.5)
    zero = D.rigid_scene("zero", S.TURN_AXIS, 0.0, S.TURN_PIVOT)
    np.testing.assert_array_equal(zero.matrix, np.eye(4))
    c2w = cameras.orbit_cameras(8)[3]
    a = raycaster.RayCaster(S.apply_to_mesh(scene.mesh, None), scene.materials).render(
        c2w, 24, 24, cameras.CAMERA_ANGLE_X, 2)
    b = raycaster.RayCaster(S.truth_mesh(scene.mesh, zero), scene.materials).render(S.truth_cameras(zero, c2w), 24, 24,
                                                                            cameras.CAMERA_ANGLE_X, 2)
    np.testing.assert_allclose(b, a, atol=1e-5)  # vertices rounded to float32 by the edit: normals move by ~1e-7


def test_co_moving_and_fixed_turns_differ_in_color_not_in_silhouette(glossy_root):
    base = glossy_root / "glossy" / "edits"
    co, fixed = (load_split(base / t, "train").images for t in TURNS)
    assert np.abs(co[..., 3] - fixed[..., 3]).max() <= 1 / 255  # same geometry from the same cameras
    assert np.abs(co[..., :3] - fixed[..., :3]).max() > 0.2


@pytest.mark.parametrize("turn", TURNS)
def test_turned_points_are_the_rotated_samples(glossy_root, turn):
    original = read_ply(glossy_root / "glossy" / "points.ply")
    edited = read_ply(glossy_root / "glossy" / "edits" / turn / "points.ply")
    motion = S.get_scene("glossy", GEN_SCENES.detail).edits[turn].matrix
    rot, shift = motion[:3, :3], motion[:3, 3]
    np.testing.assert_array_equal(edited["index"], np.arange(GEN_SCENES.surface_samples))
    xyz = np.stack([original[a] for a in "xyz"], 1).astype(np.float64)
    normal = np.stack([original[f"n{a}"] for a in "xyz"], 1).astype(np.float64)
    np.testing.assert_allclose(np.stack([edited[a] for a in "xyz"], 1), xyz @ rot.T + shift, atol=2e-6)
    np.testing.assert_allclose(np.stack([edited[f"n{a}"] for a in "xyz"], 1), normal @ rot.T, atol=2e-6)
    for key in ("red", "green", "blue", "material"):
        np.testing.assert_array_equal(edited[key], original[key])
    meta = json.loads((glossy_root / "glossy" / "edits" / turn / "scene.json").read_text())
    np.testing.assert_array_equal(meta["rigid"], motion)
    assert meta["moves_environment"] == (turn == "turn_with_light")


def test_turns_are_deterministic_and_leave_the_other_edits_alone(glossy_root, tmp_path, monkeypatch):
    """Same seed, same bytes for the turns; and a scene made without them has the same bytes in
    every other edit (appending them shifts no random stream)."""
    generate_scene("glossy", GEN_SCENES, tmp_path / "again", seed=0)
    for turn in TURNS:
        a = _digests(glossy_root / "glossy" / "edits" / turn)
        assert len(a) == 4 + GEN_SCENES.train_views + GEN_SCENES.test_views  # two transforms, points.ply, scene.json
        assert a == _digests(tmp_path / "again" / "glossy" / "edits" / turn)
    monkeypatch.setattr(S, "scene_turns", lambda: ())
    generate_scene("glossy", GEN_SCENES, tmp_path / "without", seed=0)
    without = _digests(tmp_path / "without" / "glossy")
    with_turns = _digests(glossy_root / "glossy")
    assert not any(k.startswith("edits/turn") for k in without)
    differ = [k for k in without if without[k] != with_turns[k]]
    assert differ == ["scene.json"]  # it lists the edits

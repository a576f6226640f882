"""Which ground-truth surface samples the training cameras see, against a brute-force float64
ray-triangle reference (numpy)."""

import json
import shutil

import numpy as np
import pytest

from ne_jax.benchmark import scenes as S
from ne_jax.benchmark.generate import generate_scene, seen_surface_samples
from ne_jax.data.nerf_synthetic import load_split
from ne_jax.data.ply import read_ply

from tests.mini_presets import mini_benchmark

MINI = mini_benchmark(resolution=16, train_views=4, detail=0.3, surface_samples=300)


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    root = tmp_path_factory.mktemp("seen")
    generate_scene("glossy", MINI, root, seed=0)
    return root


def _first_hits(origin, dirs, tri):
    """Möller-Trumbore, float64: distance ``[n]`` to the nearest of the triangles ``[F, 3, 3]``."""
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    p = np.cross(dirs[:, None], e2[None])  # [n, F, 3]
    det = np.einsum("fk,nfk->nf", e1, p)
    ok = np.abs(det) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = origin - tri[:, 0]  # [F, 3]
    u = np.einsum("fk,nfk->nf", s, p) * inv
    q = np.cross(s, e1)  # [F, 3]
    v = np.einsum("nk,fk->nf", dirs, q) * inv
    t = np.einsum("fk,fk->f", e2, q)[None] * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
    return np.where(hit, t, np.inf).min(axis=1)


def _reference(scene_dir, tolerance=1e-3):
    meta = json.loads((scene_dir / "scene.json").read_text())
    scene = S.get_scene(meta["scene"], meta["preset"]["detail"])
    edit = None if meta.get("edit") is None else scene.edits[meta["edit"]]
    mesh = S.apply_to_mesh(scene.mesh, edit)
    tri = mesh.vertices[mesh.faces]
    ply = read_ply(scene_dir / "points.ply")
    xyz = np.stack([ply[a].astype(np.float64) for a in "xyz"], 1)
    split = load_split(scene_dir, "train")
    seen = np.zeros(len(xyz), bool)
    for c2w in split.c2w.astype(np.float64):
        eye = c2w[:3, 3]
        local = (xyz - eye) @ c2w[:3, :3]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = split.fx * local[:, 0] / -local[:, 2] + split.cx  # pixel coordinates
            v = split.fy * local[:, 1] / -local[:, 2] + split.cy
        inside = (local[:, 2] < 0) & (u >= 0) & (u <= split.width) & (v >= 0) & (v <= split.height)
        dist = np.linalg.norm(xyz - eye, axis=1)
        t = _first_hits(eye, (xyz - eye) / dist[:, None], tri)
        seen |= inside & (t >= dist - tolerance)
    return seen


@pytest.mark.parametrize("edit", [None, "cut"])
def test_seen_samples_match_a_brute_force_reference(root, edit):
    scene_dir = root / "glossy" if edit is None else root / "glossy" / "edits" / edit
    seen, ref = seen_surface_samples(scene_dir), _reference(scene_dir)
    assert seen.dtype == bool and seen.shape == ref.shape
    assert 0.3 < ref.mean() < 0.99  # the scene hides some samples (inside the sphere) and shows most
    assert np.mean(seen != ref) <= 0.01  # float32 ray casting vs float64: only samples at the tolerance may differ


def test_no_cameras_in_front_see_nothing(root, tmp_path):
    """Cameras turned away from the scene see no sample."""
    scene_dir = tmp_path / "glossy"
    shutil.copytree(root / "glossy", scene_dir)
    path = scene_dir / "transforms_train.json"
    meta = json.loads(path.read_text())
    for f in meta["frames"]:
        m = np.asarray(f["transform_matrix"])
        m[:3, :3] = m[:3, :3] @ np.diag([-1.0, 1.0, -1.0])  # turn around the camera's y axis
        f["transform_matrix"] = m.tolist()
    path.write_text(json.dumps(meta))
    assert not seen_surface_samples(scene_dir).any()


def test_a_folder_without_scene_json_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"scene\.json"):
        seen_surface_samples(tmp_path)

"""The path-traced benchmark (Mitsuba 3): a scene folder the loader reads, value ranges, determinism for a
seed, edits' ground truth, the environment turning with the scene, the environment map's directions,
flat subdivision, and the renderer's name checked."""

import dataclasses
import hashlib
import json

import numpy as np
import pytest

from ne_jax.benchmark import raycaster
from ne_jax.benchmark import scenes as S
from ne_jax.benchmark.generate import RENDERERS, BenchmarkPreset, generate_scene
from ne_jax.data import cameras
from ne_jax.data.nerf_synthetic import load_split

from tests.mini_presets import mini_benchmark

mi = pytest.importorskip("mitsuba")
P = pytest.importorskip("ne_jax.benchmark.pathtracer")

PT = dataclasses.replace(mini_benchmark(resolution=20, train_views=2, test_views=1, detail=0.4, surface_samples=300),
                         name="mini_pt", renderer="pathtrace", spp=16)
ANGLE = cameras.CAMERA_ANGLE_X


def digest_tree(root):
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def over_white(rgba):
    return rgba[..., :3] * rgba[..., 3:4] + (1.0 - rgba[..., 3:4])


def psnr(a, b):
    return float(-10 * np.log10(np.mean((over_white(a) - over_white(b)) ** 2)))


def tracer(edit=None, environment=None, spp=16, res=PT.resolution, mesh=None):
    scene = S.get_scene("glossy", PT.detail)
    mesh = S.truth_mesh(scene.mesh, edit) if mesh is None else mesh
    return P.PathTracer(mesh, scene.materials, P.scene_surfaces("glossy", scene.materials), environment,
                        max_edge=P.pixel_footprint(res, ANGLE), spp=spp)


@pytest.fixture(scope="module")
def glossy_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("bench_pt")
    generate_scene("glossy", PT, root, seed=0)
    return root


def test_folder_loads_with_valid_ranges(glossy_root):
    meta = json.loads((glossy_root / "glossy" / "scene.json").read_text())
    assert meta["preset"]["renderer"] == "pathtrace" and meta["preset"]["spp"] == 16
    assert "mitsuba" in meta["renderer"] and meta["generation"]["images"] == 4 and meta["generation"]["seconds"] > 0
    for split, count in (("train", 2), ("val", 1), ("test", 1)):
        data = load_split(glossy_root / "glossy", split)
        images = np.asarray(data.images)
        assert images.shape == (count, 20, 20, 4) and np.isfinite(images).all()
        assert images.min() >= 0.0 and images.max() <= 1.0
        alpha = images[..., 3]
        assert (alpha == 0).any() and (alpha == 1).any()  # background and object
        assert images[..., :3][alpha > 0].mean() > 0.1  # lit, not black


def test_silhouette_matches_the_ray_caster(glossy_root):
    """The camera convention (Mitsuba looks along +z, x to the left) is right: same silhouette."""
    scene = S.get_scene("glossy", PT.detail)
    c2w = np.asarray(load_split(glossy_root / "glossy", "train").c2w[0], np.float64)
    ours = load_split(glossy_root / "glossy", "train").images[0, ..., 3] > 0.5
    ref = raycaster.RayCaster(S.truth_mesh(scene.mesh, None), scene.materials).render(c2w, 20, 20, ANGLE, 4)
    ref = ref[..., 3] > 0.5
    assert (np.asarray(ours) & ref).sum() / (np.asarray(ours) | ref).sum() > 0.8  # 20 px: edges are a third


def test_same_seed_same_bytes_other_seed_other_noise(glossy_root, tmp_path):
    generate_scene("glossy", PT, tmp_path / "a", seed=0)
    a, b = digest_tree(glossy_root / "glossy"), digest_tree(tmp_path / "a" / "glossy")
    timed = [k for k in a if k.endswith("scene.json")]
    assert len(a) > 20 and {k: a[k] for k in a if k not in timed} == {k: b[k] for k in b if k not in timed}
    for k in timed:  # scene.json: the same but for the generation time
        ma, mb = (json.loads((root / k).read_text()) for root in (glossy_root / "glossy", tmp_path / "a" / "glossy"))
        ma.pop("generation"), mb.pop("generation")
        assert ma == mb
    t = tracer()
    c2w = cameras.orbit_cameras(4)[1]
    one, two = t.render(c2w, 20, 20, ANGLE, seed=1), t.render(c2w, 20, 20, ANGLE, seed=2)
    assert not np.array_equal(one, two) and psnr(one, two) > 20


def test_edit_changes_the_ground_truth_where_it_should(glossy_root):
    """delete_cube: alpha drops where the ray caster says the cube was, and nowhere else."""
    scene = S.get_scene("glossy", PT.detail)
    original = np.asarray(load_split(glossy_root / "glossy", "train").images)
    deleted = np.asarray(load_split(glossy_root / "glossy" / "edits" / "delete_cube", "train").images)
    cams = np.asarray(load_split(glossy_root / "glossy", "train").c2w, np.float64)
    rc_before = raycaster.RayCaster(S.truth_mesh(scene.mesh, None), scene.materials)
    rc_after = raycaster.RayCaster(S.truth_mesh(scene.mesh, scene.edits["delete_cube"]), scene.materials)
    for i, c2w in enumerate(cams):
        gone = (rc_before.render(c2w, 20, 20, ANGLE, 4)[..., 3] - rc_after.render(c2w, 20, 20, ANGLE, 4)[..., 3])
        drop = original[i, ..., 3] - deleted[i, ..., 3]
        assert (gone > 0.9).any()
        assert (drop[gone > 0.9] > 0.5).all()  # the cube's pixels are empty now
        assert np.abs(drop[gone < 0.05]).max() < 0.35  # elsewhere only sub-pixel edge noise


def test_turn_with_light_is_the_original_from_moved_cameras(glossy_root):
    """The turned mesh under the turned environment, seen from c2w, is the original seen from T^-1 c2w
    (what the folder holds), up to noise; keeping the environment (turn_scene) is clearly different."""
    scene = S.get_scene("glossy", PT.detail)
    edit = scene.edits["turn_with_light"]
    c2w = np.asarray(load_split(glossy_root / "glossy", "test").c2w[0], np.float64)
    res, spp = 24, 64
    reference = tracer(spp=spp, res=res).render(S.truth_cameras(edit, c2w), res, res, ANGLE, seed=3)
    again = tracer(spp=spp, res=res).render(S.truth_cameras(edit, c2w), res, res, ANGLE, seed=4)
    turned = S.apply_to_mesh(scene.mesh, edit)
    moved = tracer(mesh=turned, environment=edit.matrix[:3, :3], spp=spp, res=res).render(c2w, res, res, ANGLE, seed=5)
    fixed = tracer(mesh=turned, spp=spp, res=res).render(c2w, res, res, ANGLE, seed=5)
    noise = psnr(reference, again)
    assert psnr(moved, reference) > noise - 1.5
    assert psnr(fixed, reference) < noise - 5
    # the folder's turn_with_light test view is that reference at another seed
    stored = np.asarray(load_split(glossy_root / "glossy" / "edits" / "turn_with_light", "test").images[0])
    small = tracer().render(S.truth_cameras(edit, c2w), 20, 20, ANGLE, seed=6)
    stored_noise = psnr(small, tracer().render(S.truth_cameras(edit, c2w), 20, 20, ANGLE, seed=7))
    assert psnr(stored, small) > stored_noise - 1.5


def test_environment_map_directions_and_rotation():
    """Mitsuba's envmap emitter returns environment_radiance(R^T d) for a world direction d."""
    import drjit as dr

    mi = P.import_mitsuba()
    rot = S.get_scene("glossy", 0.25).edits["turn_with_light"].matrix
    to_world = np.eye(4)
    to_world[:3, :3] = rot[:3, :3]
    emitter = mi.load_dict({"type": "envmap", "bitmap": mi.Bitmap(P.environment_map()),
                            "to_world": mi.ScalarTransform4f(to_world.tolist())})
    dirs = np.random.default_rng(0).normal(size=(40, 3))
    dirs = np.concatenate([[[0, 0, 1.0], [0, 0, -1.0]], dirs / np.linalg.norm(dirs, axis=1, keepdims=True)])
    got = []
    for d in dirs:
        si = dr.zeros(mi.SurfaceInteraction3f)
        si.wi = mi.Vector3f(*(-d))  # looking along d
        got.append(np.array(emitter.eval(si), np.float64).reshape(-1)[:3])
    want = P.environment_radiance(dirs @ rot[:3, :3])  # R^T d, row-wise
    np.testing.assert_allclose(np.array(got), want, rtol=0.05, atol=0.01)


def test_subdivide_keeps_the_surface():
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0.5]], float)
    faces = np.array([[0, 1, 2], [1, 3, 2]])
    values, new_faces = P.subdivide(vertices, faces)
    assert new_faces.shape == (8, 3) and len(values) == 4 + 5  # one midpoint per edge, shared
    assert len(np.unique(values, axis=0)) == len(values)

    def area(v, f):
        return 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1).sum()

    np.testing.assert_allclose(area(values, new_faces), area(vertices, faces))


def test_unknown_renderer_is_named():
    with pytest.raises(ValueError, match=r"BenchmarkPreset\.renderer.*'blender'.*\['pathtrace', 'raycast'\]"):
        dataclasses.replace(PT, renderer="blender")
    with pytest.raises(ValueError, match=r"BenchmarkPreset\.spp"):
        dataclasses.replace(PT, spp=0)
    assert sorted(RENDERERS) == ["pathtrace", "raycast"]
    assert BenchmarkPreset("x", 8, 1, 1, 1, 1, 0.25, 10).record() == {
        "name": "x", "resolution": 8, "train_views": 1, "val_views": 1, "test_views": 1, "supersample": 1,
        "detail": 0.25, "surface_samples": 10}  # a ray-cast preset records what it always did

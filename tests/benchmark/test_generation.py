"""Writing the benchmark: layout, determinism, cameras shared by edits, points, contact sheet, CLI."""

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from ne_jax.benchmark import scenes as S
from ne_jax.benchmark.generate import generate_benchmark, generate_scene, list_variants
from ne_jax.cli import main
from ne_jax.data.nerf_synthetic import load_split
from ne_jax.data.ply import read_ply
from ne_jax.train import load_trained
from ne_jax.viz import contact_sheet

from tests.mini_presets import GEN_SCENES


def digest_tree(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def glossy_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("bench_a")
    generate_scene("glossy", GEN_SCENES, root, seed=0)
    return root


def test_same_seed_same_bytes(glossy_root, tmp_path):
    generate_scene("glossy", GEN_SCENES, tmp_path, seed=0)
    a, b = digest_tree(glossy_root / "glossy"), digest_tree(tmp_path / "glossy")
    assert len(a) > 20 and a == b


def test_other_seed_other_cameras(glossy_root, tmp_path):
    generate_scene("glossy", GEN_SCENES, tmp_path, seed=1, edits=())  # the cameras of the original suffice
    a = load_split(glossy_root / "glossy", "train").c2w
    b = load_split(tmp_path / "glossy", "train").c2w
    assert not np.allclose(a, b)


def test_layout_and_shared_cameras(glossy_root):
    variants = list_variants(glossy_root)
    assert [v[1] for v in variants] == [None, *S.get_scene("glossy", 0.5).edits]
    original = {s: load_split(glossy_root / "glossy", s) for s in ("train", "val", "test")}
    assert [len(original[s]) for s in ("train", "val", "test")] == [3, 1, 2]
    assert original["train"].images.shape[1:] == (16, 16, 4)
    for _, edit, directory in variants[1:]:
        for split in ("train", "test"):
            edited = load_split(directory, split)
            np.testing.assert_array_equal(edited.c2w, original[split].c2w)
            assert not np.array_equal(edited.images, original[split].images), edit
    # the cut shows caps: more opaque pixels than the original in at least one view
    assert any(load_split(glossy_root / "glossy" / "edits" / "cut", "train").images[..., 3].sum((1, 2))
               > original["train"].images[..., 3].sum((1, 2)))


def test_points_ply(glossy_root):
    pts = read_ply(glossy_root / "glossy" / "points.ply")
    assert len(pts["x"]) == 400 and "index" not in pts
    normals = np.stack([pts["nx"], pts["ny"], pts["nz"]], 1)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-5)
    deleted = read_ply(glossy_root / "glossy" / "edits" / "delete_cube" / "points.ply")
    assert len(deleted["index"]) < 400
    np.testing.assert_array_equal(deleted["x"], pts["x"][deleted["index"]])


def test_contact_sheet(glossy_root, tmp_path):
    out = contact_sheet(glossy_root, tmp_path / "sheet.png")
    import imageio.v3 as iio

    img = iio.imread(out)
    assert img.ndim == 3 and img.shape[0] > 100 and img.shape[1] > 5 * 100


def test_generate_benchmark_rejects_unknown_scene_before_writing(tmp_path):
    with pytest.raises(KeyError, match="unknown scene 'lego'"):
        generate_benchmark(tmp_path, GEN_SCENES, ["glossy", "lego"])
    assert not (tmp_path / "glossy").exists()


def test_failed_scene_leaves_nothing(tmp_path, monkeypatch):
    def boom(*args, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr("ne_jax.benchmark.generate.write_split", boom)
    with pytest.raises(RuntimeError, match="disk full"):
        generate_scene("cup", GEN_SCENES, tmp_path)
    assert list(tmp_path.iterdir()) == []


def test_cli_make_benchmark_and_errors(tmp_path, capsys):
    assert main(["make-benchmark", "--out", str(tmp_path / "b"), "--scenes", "lego"]) == 2
    assert "unknown scene 'lego'" in capsys.readouterr().err
    assert not (tmp_path / "b" / "lego").exists()
    with pytest.raises(SystemExit):
        main(["make-benchmark", "--preset", "huge", "--out", str(tmp_path)])


def test_cli_demo_runs_every_stage_on_small_stand_ins(tmp_path, capsys, monkeypatch):
    """``ne-jax demo`` through its four stages (benchmark, training, test views, orbit) with 16-px
    scenes and a 4-step run in place of the ``tiny`` ones; the README's exact command is the slow
    test below."""
    import ne_jax.benchmark.generate as generate
    import ne_jax.train.run as run

    from tests.mini_presets import short_run

    real = generate.generate_benchmark
    monkeypatch.setattr(generate, "generate_benchmark", lambda root, preset, scenes, seed: real(root, GEN_SCENES,
                                                                                                 scenes, seed))
    monkeypatch.setattr(run, "get_run_preset", lambda name: short_run())
    assert main(["demo", "--out", str(tmp_path), "--orbit-frames", "3"]) == 0
    out = capsys.readouterr().out
    assert "[4/4] rendering an orbit" in out and "contact sheet" in out
    assert (tmp_path / "contact_sheet.png").is_file() and (tmp_path / "run" / "orbit.gif").is_file()
    assert (tmp_path / "run" / "eval_test").is_dir()
    assert len(list_variants(tmp_path / "benchmark")) == 4 * 7  # original + six edits per scene
    # the effects blocks' scene.json declares (specular off), as `ne-jax train` of the folder takes them
    declared = json.loads((tmp_path / "benchmark" / "blocks" / "scene.json").read_text())["effects"]
    notes = json.loads((tmp_path / "run" / "metrics.json").read_text())["notes"]["effects"]
    assert notes["source"] == "scene.json" and notes["effects"]["specular"] == "off" and declared["specular"] is False
    assert "effects: specular=off, background_model=constant (scene.json)" in out
    assert not load_trained(tmp_path / "run").run.render.shading.effects.specular


@pytest.mark.slow
def test_cli_demo_runs_end_to_end(tmp_path, capsys):
    """The README's main command (tiny preset, all scenes; about 6 minutes on 2 cores)."""
    assert main(["demo", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "contact sheet" in out
    assert (tmp_path / "contact_sheet.png").is_file()
    assert len(list_variants(tmp_path / "benchmark")) == 4 * 7  # original + six edits per scene


def _original_files(scene_dir: Path) -> dict[str, str]:
    """Digests of a scene's original (its images, cameras and points; not its edits or scene.json)."""
    return {k: v for k, v in digest_tree(scene_dir).items() if not k.startswith("edits") and k != "scene.json"}


def test_originals_only_makes_the_same_original_and_no_edits(glossy_root, tmp_path):
    generate_scene("glossy", GEN_SCENES, tmp_path, seed=0, edits=())
    assert not (tmp_path / "glossy" / "edits").exists()
    assert [v[1] for v in list_variants(tmp_path)] == [None]
    assert _original_files(tmp_path / "glossy") == _original_files(glossy_root / "glossy")
    with pytest.raises(KeyError, match="no edit 'melt'"):
        generate_scene("cup", GEN_SCENES, tmp_path, edits=["melt"])
    assert not (tmp_path / "cup").exists()


def _counting_renderer(monkeypatch, fail_after=None):
    """Count the images rendered (``calls[0]``); with ``fail_after``, stop the run as a kill would after
    that many."""
    import ne_jax.benchmark.generate as generate

    real, calls = generate._renderer, [0]

    def renderer(*args):
        render, description = real(*args)

        def counted(c2w, seed):
            if fail_after is not None and calls[0] == fail_after:
                raise KeyboardInterrupt
            calls[0] += 1
            return render(c2w, seed)

        return counted, description

    monkeypatch.setattr(generate, "_renderer", renderer)
    return calls


def test_resume_continues_from_the_last_image_with_the_same_bytes(glossy_root, tmp_path):
    total = 6 + 6 * 5  # the original's 3 + 1 + 2 views, each edit's 3 + 2
    with pytest.MonkeyPatch.context() as mp:
        calls = _counting_renderer(mp, fail_after=8)
        with pytest.raises(KeyboardInterrupt):
            generate_scene("glossy", GEN_SCENES, tmp_path, seed=0, resume=True)
        assert calls[0] == 8 and not (tmp_path / "glossy").exists()
        assert len(list((tmp_path / ".glossy.partial").rglob("r_*.npz"))) == 8
    with pytest.MonkeyPatch.context() as mp:
        calls = _counting_renderer(mp)
        generate_scene("glossy", GEN_SCENES, tmp_path, seed=0, resume=True)
        assert calls[0] == total - 8  # only the images the first sitting did not finish
    assert digest_tree(tmp_path / "glossy") == digest_tree(glossy_root / "glossy")
    assert not (tmp_path / ".glossy.partial").exists()
    with pytest.MonkeyPatch.context() as mp:  # a finished scene is kept as it is
        calls = _counting_renderer(mp)
        stamp = (tmp_path / "glossy" / "scene.json").stat().st_mtime_ns
        generate_scene("glossy", GEN_SCENES, tmp_path, seed=0, resume=True)
        assert calls[0] == 0 and (tmp_path / "glossy" / "scene.json").stat().st_mtime_ns == stamp
        generate_scene("glossy", GEN_SCENES, tmp_path, seed=1, resume=True)  # another seed: made anew
        assert calls[0] == total


def test_make_benchmark_originals_only_and_resume(tmp_path, monkeypatch, capsys):
    import json

    import experiments.make_benchmark as mb

    monkeypatch.setattr(mb, "RESULTS", tmp_path / "repo" / "results")
    monkeypatch.setattr(mb, "get_preset", lambda name: GEN_SCENES)
    out = tmp_path / "bench"
    mb.main(["--preset", "tiny", "--out", str(out), "--scenes", "cup", "--originals-only"])
    assert [v[:2] for v in list_variants(out / "tiny")] == [("cup", None)]
    row = json.loads((tmp_path / "repo" / "results" / "make_benchmark.json").read_text())["presets"]["tiny"]
    assert row["images"] == 3 + 1 + 2 and row["variants_per_scene"] == 1
    assert row["command"].endswith("--scenes cup --originals-only")
    stamp = (out / "tiny" / "cup" / "scene.json").stat().st_mtime_ns
    calls = _counting_renderer(monkeypatch)
    mb.main(["--preset", "tiny", "--out", str(out), "--scenes", "cup", "glossy", "--originals-only", "--resume"])
    assert (out / "tiny" / "cup" / "scene.json").stat().st_mtime_ns == stamp  # kept, not rendered again
    assert calls[0] == 6 and [v[:2] for v in list_variants(out / "tiny")] == [("cup", None), ("glossy", None)]
    mb.main(["--preset", "tiny", "--out", str(out), "--scenes", "glossy", "--originals-only"])  # no --resume
    assert calls[0] == 12  # glossy rendered again ...
    assert (out / "tiny" / "cup" / "scene.json").stat().st_mtime_ns == stamp  # ... and cup, not asked for, kept

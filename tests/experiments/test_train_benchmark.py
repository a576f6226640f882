"""The training benchmark's command line refuses to restart runs it would overwrite."""

from __future__ import annotations

import pytest

from experiments import train_benchmark

from tests.mini_presets import TRAIN_SCENE


def _load():
    return train_benchmark


def test_runs_holding_a_run_need_resume(tmp_path, capsys):
    (tmp_path / "glossy" / "checkpoints").mkdir(parents=True)
    with pytest.raises(SystemExit):
        _load().main(["--runs", str(tmp_path), "--scenes", "glossy", "cup"])
    err = capsys.readouterr().err
    assert "already holds runs of ['glossy']" in err and "--resume" in err


def test_resume_needs_runs(capsys):
    with pytest.raises(SystemExit):
        _load().main(["--resume"])
    assert "pass --runs DIR" in capsys.readouterr().err


def test_scenes_take_set_names_and_do_not_mix_the_sets(capsys):
    with pytest.raises(SystemExit):
        _load().main(["--scenes", "heldout", "stool"])
    assert "expected tuning scenes or held-out ones, found both (vase bowl lamp pattern stool)" in \
        capsys.readouterr().err
    with pytest.raises(SystemExit):
        _load().main(["--scenes", "nope"])
    assert "--scenes: unknown scene 'nope'" in capsys.readouterr().err


def test_a_short_run_writes_the_table(tmp_path):
    """Two steps on a small scene (a small carving, set with ``--set``): the JSON and the table hold both
    Chamfer measures and the worst test view's share of hole pixels."""
    import json

    from ne_jax.benchmark.generate import generate_scene

    generate_scene("glossy", TRAIN_SCENE, tmp_path / "bench", seed=0, edits=())
    sets = ["init.carve.resolution=48", "init.carve.num_points=1500"]
    _load().main(["--preset", "tiny", "--root", str(tmp_path / "bench"), "--scenes", "glossy", "--epochs", "1",
                  "--steps-per-epoch", "2", *(a for change in sets for a in ("--set", change)),
                  "--runs", str(tmp_path / "runs"), "--results", str(tmp_path / "out")])
    res = json.loads((tmp_path / "out" / "train_benchmark_tiny.json").read_text())
    s = res["scenes"]["glossy"]
    assert s["steps"] == 2 and 0.3 < s["seen_share"] < 1.0 and res["set"] == sets
    assert s["initial_points"] <= 1500
    # the seen-surface measure: the accuracy over all samples, the completeness over the seen ones
    for when in ("initial", "final"):
        expected = 0.5 * (s[f"accuracy_{when}"] + s[f"completeness_seen_{when}"])
        assert s[f"chamfer_seen_{when}"] == pytest.approx(expected, abs=2e-5)
    table = (tmp_path / "out" / "train_benchmark_tiny.md").read_text()
    assert "| glossy |" in table and "% seen)" in table
    assert 0.0 <= s["hole_pixels_worst_view"] <= 1.0 and f"{100 * s['hole_pixels_worst_view']:.2f}% |" in table


def test_scenes_accumulate_only_within_one_config(tmp_path):
    from ne_jax.train.run import get_run_preset

    tb = _load()
    run = get_run_preset("tiny")
    row = {"test_psnr": 20.0, "test_ssim": 0.8, "train_seconds": 1.0, "initial_points": 1, "final_points": 1,
           "chamfer_initial": 0.1, "chamfer_final": 0.1, "chamfer_ratio": 1.0}
    tb.write_results("tiny", run, {"cup": {**row, "commit": "abc1234"}}, tmp_path)
    assert set(tb._earlier_scenes("tiny", run, tmp_path)) == {"cup"}
    assert "commit abc1234, config key " in (tmp_path / "train_benchmark_tiny.md").read_text()
    other = run.replace(seed=run.seed + 1)
    assert tb._earlier_scenes("tiny", other, tmp_path) == {}  # another config starts a new table
    tb.write_results("tiny", other, {"stool": row}, tmp_path)
    assert "| cup |" not in (tmp_path / "train_benchmark_tiny.md").read_text()


def test_a_path_traced_root_names_its_own_results(tmp_path):
    """Results on the path-traced benchmark go to ``train_benchmark_<preset>_pt``, apart from the
    ray-cast ones of the same preset; a ray-cast root (its preset records no renderer) keeps the name."""
    import json

    from experiments.common import benchmark_suffix
    from ne_jax.train.run import get_run_preset

    for name, preset in (("tiny_pt", {"name": "tiny_pt", "renderer": "pathtrace", "spp": 256}),
                         ("tiny", {"name": "tiny"})):
        (tmp_path / name / "cup").mkdir(parents=True)
        (tmp_path / name / "cup" / "scene.json").write_text(json.dumps({"scene": "cup", "preset": preset}))
    assert benchmark_suffix(tmp_path / "tiny_pt", ["stool", "cup"]) == "_pt"  # the first scene present
    assert benchmark_suffix(tmp_path / "tiny", ["cup"]) == ""
    assert benchmark_suffix(tmp_path / "none", ["cup"]) == ""

    tb = _load()
    run = get_run_preset("tiny")
    row = {"test_psnr": 20.0, "test_ssim": 0.8, "train_seconds": 1.0, "initial_points": 1, "final_points": 1,
           "chamfer_initial": 0.1, "chamfer_final": 0.1, "chamfer_ratio": 1.0}
    out = tmp_path / "out"
    tb.write_results("tiny", run, {"cup": {**row, "commit": "abc1234"}}, out)
    tb.write_results("tiny", run, {"stool": {**row, "commit": "abc1234"}}, out, name="tiny_pt")
    assert set(json.loads((out / "train_benchmark_tiny.json").read_text())["scenes"]) == {"cup"}
    pt = json.loads((out / "train_benchmark_tiny_pt.json").read_text())
    assert set(pt["scenes"]) == {"stool"} and pt["benchmark"] == "tiny_pt" and pt["preset"] == "tiny"
    assert "--root BENCH/tiny_pt" in (out / "train_benchmark_tiny_pt.md").read_text()
    assert set(tb._earlier_scenes("tiny_pt", run, out)) == {"stool"}
    # a preset changed with --set says so in the re-run command and the JSON
    tb.write_results("tiny", run, {"cup": row}, tmp_path / "set", sets=["render.kdtree.margin_factor=1.5"])
    md = (tmp_path / "set" / "train_benchmark_tiny.md").read_text()
    assert "--preset tiny --set render.kdtree.margin_factor=1.5`" in md
    assert json.loads((tmp_path / "set" / "train_benchmark_tiny.json").read_text())["set"] == [
        "render.kdtree.margin_factor=1.5"]


def test_set_names_an_unknown_field(capsys):
    with pytest.raises(SystemExit):
        _load().main(["--set", "render.kdtree.falloff=1.0"])
    assert "--set: config assignment 'render.kdtree.falloff=1.0'" in capsys.readouterr().err

"""The density gate study trains both configs on each benchmark root and tables them.

The default tests check its configs, its reading back of finished trainings and its tables with the
trainings stood in for; the study with two-step trainings runs with ``-m slow``."""

from __future__ import annotations

import json

import pytest

from experiments import density_gate_study

from tests.mini_presets import TRAIN_SCENE


@pytest.mark.slow  # a study run end to end: -m slow
def test_two_step_study_tables_both_configs(tmp_path):
    from ne_jax.benchmark.generate import generate_scene

    generate_scene("glossy", TRAIN_SCENE, tmp_path / "bench", seed=0, edits=())
    argv = ["--root", f"tiny={tmp_path / 'bench'}", "--scenes", "glossy", "--runs", str(tmp_path / "runs"),
            "--config", "gate=render.kdtree.density_falloff=2.0",
            "--epochs", "1", "--steps-per-epoch", "2", "--results", str(tmp_path / "out")]
    density_gate_study.main(argv)
    res = json.loads((tmp_path / "out" / "density_gate_tiny.json").read_text())
    base, gated = (res["benchmarks"]["tiny"][c] for c in ("baseline", "gate"))
    assert base["config_key"] != gated["config_key"]
    for cfg in (base, gated):
        s = cfg["scenes"]["glossy"]
        assert s["steps"] == 2 and set(s["confidence"]) == {"below_0.1", "above_0.9", "median"}
    md = (tmp_path / "out" / "density_gate_tiny.md").read_text()
    assert "| tiny | glossy | baseline |" in md and "| tiny | glossy | gate |" in md
    # a second invocation reads the finished configs back instead of training again
    metrics = [tmp_path / "runs" / "tiny" / c / "runs" / "glossy" / "metrics.json" for c in ("baseline", "gate")]
    stamps = [m.stat().st_mtime_ns for m in metrics]
    density_gate_study.main(argv[:-2] + ["--results", str(tmp_path / "again")])
    assert [m.stat().st_mtime_ns for m in metrics] == stamps
    assert (tmp_path / "again" / "density_gate_tiny.md").read_text().count("| glossy |") == 2


def test_configs_are_named_and_checked():
    assert density_gate_study.parse_configs(["g=render.kdtree.density_falloff=1.0,train.confidence_lr=10"]) == {
        "baseline": [], "g": ["render.kdtree.density_falloff=1.0", "train.confidence_lr=10"]}
    for bad in (["render.kdtree.density_falloff=1.0"], ["g=x"], ["baseline=train.confidence_lr=2"]):
        with pytest.raises(ValueError, match="--config"):
            density_gate_study.parse_configs(bad)


def test_a_config_that_is_the_preset_is_refused():
    density_gate_study.same_as_preset("default", {"baseline": [], "gate": ["render.kdtree.density_falloff=1.0"]})
    with pytest.raises(ValueError, match="--config gate: .* is the tiny preset as it is"):
        density_gate_study.same_as_preset("tiny", {"baseline": [], "gate": ["render.kdtree.density_falloff=1.0"]})
    with pytest.raises(SystemExit):  # the command line says so before training anything
        density_gate_study.main(["--root", "tiny=.", "--runs", "RUNS"])


def _scene_json(root, scene="glossy", renderer=None):
    (root / scene).mkdir(parents=True)
    preset = {"name": "tiny"} if renderer is None else {"name": "tiny_pt", "renderer": renderer}
    (root / scene / "scene.json").write_text(json.dumps({"scene": scene, "preset": preset}))
    return root


def _scene_row(psnr, seconds):
    return {"test_psnr": psnr, "test_ssim": 0.8, "train_seconds": seconds, "final_points": 100, "grown": 5,
            "pruned": 2, "chamfer_seen_ratio": 1.5, "steps": 2}


def test_a_finished_config_is_read_back_and_an_unfinished_one_trained(tmp_path, monkeypatch):
    """``_train`` reads a config's ``train_benchmark`` results back when they hold every scene asked for;
    otherwise it runs ``train_benchmark`` on the missing ones, resuming the runs folder once it exists."""
    root = _scene_json(tmp_path / "bench")
    out = tmp_path / "gate"
    results = out / "results" / "train_benchmark_tiny.json"
    calls = []

    def fake_main(argv):
        calls.append(argv)
        results.write_text(json.dumps({"scenes": {"glossy": {}, "cup": {}}, "config_key": "k"}))

    monkeypatch.setattr(density_gate_study.train_benchmark, "main", fake_main)
    results.parent.mkdir(parents=True)
    results.write_text(json.dumps({"scenes": {"glossy": {}}, "config_key": "k"}))
    assert density_gate_study._train("tiny", root, ["glossy"], out, ["--epochs", "1"])["scenes"] == {"glossy": {}}
    pt = _scene_json(tmp_path / "bench_pt", renderer="pathtrace")  # its results: train_benchmark_tiny_pt
    (out / "results" / "train_benchmark_tiny_pt.json").write_text(json.dumps({"scenes": {"glossy": {"pt": 1}}}))
    assert density_gate_study._train("tiny", pt, ["glossy"], out, [])["scenes"] == {"glossy": {"pt": 1}}
    assert calls == []  # finished: read back
    assert set(density_gate_study._train("tiny", root, ["glossy", "cup"], out, ["--epochs", "1"])["scenes"]) == \
        {"glossy", "cup"}
    assert calls == [["--preset", "tiny", "--root", str(root), "--runs", str(out / "runs"), "--results",
                      str(out / "results"), "--scenes", "glossy", "cup", "--epochs", "1"]]
    (out / "runs").mkdir()
    results.write_text(json.dumps({"scenes": {"glossy": {}}, "config_key": "k"}))
    density_gate_study._train("tiny", root, ["cup"], out, [])
    assert calls[-1][-1] == "--resume"  # a stopped study continues its runs


def test_tables_every_config_on_every_root(tmp_path, monkeypatch):
    """The command line with the trainings stood in for: each config trained on each ``--root`` with the
    schedule and its ``--set`` changes, in its own runs folder; the JSON and both tables."""
    roots = {"tiny": _scene_json(tmp_path / "tiny"), "tiny_pt": _scene_json(tmp_path / "tiny_pt", renderer="pathtrace")}
    trained = []

    def fake_train(preset, root, scenes, folder, extra):
        trained.append((preset, root, scenes, folder, extra))
        psnr = 20.0 + 2.0 * ("density_falloff=2.0" in " ".join(extra)) + (root == roots["tiny_pt"])
        return {"config_key": f"key{len(trained)}", "commit": "abc1234", "scenes": {"glossy": _scene_row(psnr, 30.0)}}

    monkeypatch.setattr(density_gate_study, "_train", fake_train)
    monkeypatch.setattr(density_gate_study, "confidence_summary",
                        lambda run_dir: {"below_0.1": 0.125, "above_0.9": 0.5, "median": 0.75})
    runs, out = tmp_path / "runs", tmp_path / "out"
    density_gate_study.main(["--root", f"tiny={roots['tiny']}", "--root", f"tiny_pt={roots['tiny_pt']}",
                             "--scenes", "glossy", "--runs", str(runs),
                             "--config", "gate=render.kdtree.density_falloff=2.0",
                             "--epochs", "1", "--steps-per-epoch", "2", "--results", str(out)])
    schedule = ["--epochs", "1", "--steps-per-epoch", "2"]
    assert [(t[1], t[3], t[4]) for t in trained] == [
        (roots[b], runs / b / c, schedule + ([] if c == "baseline" else ["--set", "render.kdtree.density_falloff=2.0"]))
        for b in ("tiny", "tiny_pt") for c in ("baseline", "gate")]
    res = json.loads((out / "density_gate_tiny.json").read_text())
    assert res["configs"] == {"baseline": [], "gate": ["render.kdtree.density_falloff=2.0"]}
    assert res["benchmarks"]["tiny_pt"]["gate"]["config_key"] == "key4"
    s = res["benchmarks"]["tiny"]["gate"]["scenes"]["glossy"]
    assert s["test_psnr"] == 22.0 and s["confidence"] == {"below_0.1": 0.125, "above_0.9": 0.5, "median": 0.75}
    md = (out / "density_gate_tiny.md").read_text()
    assert "| tiny | gate | 22.00 | +2.00 | 22.00 | 30 |" in md and "| tiny_pt | baseline | 21.00 | +0.00 |" in md
    assert "| tiny | glossy | gate | 22.00 | 0.800 | 30 | 100 | 5 | 2 | 1.50 | 12.5% | 50.0% | 0.75 |" in md
    assert "`gate`: `render.kdtree.density_falloff=2.0`" in md and res["command"] in md

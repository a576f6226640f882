"""The density gate study trains both configs on each benchmark root and tables them."""

from __future__ import annotations

import json

import pytest

from experiments import density_gate_study

from tests.mini_presets import TRAIN_SCENE


@pytest.mark.slow  # a study run end to end: -m slow
def test_two_step_study_tables_both_configs(tmp_path):
    from ne_jax.benchmark.generate import generate_scene

    generate_scene("glossy", TRAIN_SCENE, tmp_path / "bench", seed=0)
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

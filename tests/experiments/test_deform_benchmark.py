"""The deformation benchmark's command line: ``--set`` changes the preset, is recorded in the
results, and keys the cached records, so another config measures anew."""

from __future__ import annotations

import json
import shlex

import pytest

from experiments import deform_benchmark as db
from ne_jax.benchmark.generate import generate_scene
from ne_jax.config_json import config_key, config_set
from ne_jax.train.run import get_run_preset

from tests.mini_presets import TRAIN_SCENE

SHORT = ["--set", "epochs=1", "--set", "steps_per_epoch=2", "--set", "round_epochs=[1, 0]",
         "--set", "init.carve.num_points=1500"]


def test_set_is_recorded_and_keys_the_records(tmp_path, monkeypatch):
    monkeypatch.setattr(db, "RESULTS", tmp_path / "out")
    generate_scene("blocks", TRAIN_SCENE, tmp_path / "bench", seed=0, edits=("cut",))
    args = ["--preset", "tiny", "--root", str(tmp_path / "bench"), "--scenes", "blocks", "--edits", "cut",
            "--variants", "full", "--no-finetune", "--runs", str(tmp_path / "runs"), *SHORT]
    db.main(args)
    report = json.loads((tmp_path / "out" / "deform_benchmark_tiny_partial.json").read_text())
    want = config_key(config_set(get_run_preset("tiny"), *SHORT[1::2]))
    assert report["config_key"] == want and report["set"] == SHORT[1::2]
    assert report["command"].endswith(" " + shlex.join(SHORT) + " --runs DIR"), report["command"]
    (rec,) = report["records"]
    assert rec["edit"] == "cut" and rec["zero_shot"]["psnr"] > 5
    assert (tmp_path / "runs" / "blocks" / "records" / want / "cut" / "full-zero.json").is_file()
    assert f"config key {want}" in (tmp_path / "out" / "deform_benchmark_tiny_partial.md").read_text()


def test_bad_set_is_refused(capsys):
    with pytest.raises(SystemExit):
        db.main(["--runs", "x", "--set", "render.no_such_field=1"])
    assert "--set" in capsys.readouterr().err

"""The deformation benchmark's command line: ``--set`` changes the preset, is recorded in the
results, and keys the cached records, so another config measures anew; ``--by-kind`` tables a results
file by kind of edit.

The default tests run the command line with the models, their scores and the edits' measurements
stood in for (no training, no rendering); the benchmark with a two-step model runs with ``-m slow``."""

from __future__ import annotations

import json
import shlex
from types import SimpleNamespace

import numpy as np
import pytest

from experiments import deform_benchmark as db
from ne_jax.benchmark.generate import generate_scene
from ne_jax.config_json import config_key, config_set
from ne_jax.train.run import get_run_preset

from tests.mini_presets import TRAIN_SCENE

SHORT = ["--set", "epochs=1", "--set", "steps_per_epoch=2", "--set", "round_epochs=[1, 0]",
         "--set", "init.carve.num_points=1500"]


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    """The blocks scene (24 px) with its ``cut`` edit."""
    root = tmp_path_factory.mktemp("deform") / "bench"
    generate_scene("blocks", TRAIN_SCENE, root, seed=0, edits=("cut",))
    return root


def _args(bench, runs, *extra):
    return ["--preset", "tiny", "--root", str(bench), "--scenes", "blocks", "--edits", "cut", "--variants", "full",
            "--no-finetune", "--runs", str(runs), *extra]


def _check_report(out, runs, sets):
    """The partial results of ``sets``: the config key of the preset so changed, the ``--set`` changes
    in the JSON and the re-run command, one record, cached under the key."""
    report = json.loads((out / "deform_benchmark_tiny_partial.json").read_text())
    want = config_key(config_set(get_run_preset("tiny"), *sets[1::2]))
    assert report["config_key"] == want and report["set"] == sets[1::2]
    assert report["command"].endswith(" " + shlex.join(sets) + " --runs DIR"), report["command"]
    (rec,) = report["records"]
    assert (runs / "blocks" / "records" / want / "cut" / "full-zero.json").is_file()
    assert f"config key {want}" in (out / "deform_benchmark_tiny_partial.md").read_text()
    return report, rec


@pytest.mark.slow  # a study run end to end: -m slow
def test_set_is_recorded_and_keys_the_records(bench, tmp_path, monkeypatch):
    monkeypatch.setattr(db, "RESULTS", tmp_path / "out")
    db.main(_args(bench, tmp_path / "runs", *SHORT))
    _, rec = _check_report(tmp_path / "out", tmp_path / "runs", SHORT)
    assert rec["edit"] == "cut" and rec["zero_shot"]["psnr"] > 5


def test_set_keys_the_records_with_the_measurements_stood_in_for(bench, tmp_path, monkeypatch):
    """The same checks with the models, their scores and the edits' measurements stood in for; a second
    invocation reads its record back, another ``--set`` measures anew."""
    monkeypatch.setattr(db, "RESULTS", tmp_path / "out")
    image = np.full((TRAIN_SCENE.resolution, TRAIN_SCENE.resolution, 3), 0.5, np.float32)
    models, measured = [], []

    def trained_model(run, scene_dir, run_dir, log):
        models.append((run.name, run_dir))
        return SimpleNamespace(run=run, scene_dir=scene_dir)

    def score(model, variant, scene_dir):
        assert scene_dir == bench / "blocks" and variant.name == "full"  # the unedited model, own test views
        return {"psnr": 24.0, "ssim": 0.9, "lpips": None, "lost_segments": 0}, image

    def measure(args, runs, scene, edit, truth, v, model, finetuned, zero_cache):
        measured.append((scene, edit, v.name, model.run.steps_per_epoch))
        assert truth == bench / "blocks" / "edits" / "cut" and zero_cache.name == "full-zero"
        return {"scene": scene, "edit": edit, "variant": v.name, "zero_shot": {"psnr": 21.0, "ssim": 0.8,
                                                                               "lpips": None}}, image

    for name, fn in (("trained_model", trained_model), ("score", score), ("measure", measure)):
        monkeypatch.setattr(db, name, fn)
    runs = tmp_path / "runs"
    db.main(_args(bench, runs, *SHORT))
    report, rec = _check_report(tmp_path / "out", runs, SHORT)
    assert rec["edit"] == "cut" and rec["zero_shot"]["psnr"] == 21.0
    assert measured == [("blocks", "cut", "full", 2)] and models == [("tiny", runs / "blocks" / "models" / "tiny")]
    assert report["unedited"]["blocks"]["psnr"] == 24.0 and report["training"]["steps_per_epoch"] == 2
    md = (tmp_path / "out" / "deform_benchmark_tiny_partial.md").read_text()
    assert "| Ours (full) | 21.00 | 21.00 | 0.800 |  |" in md and "| unedited model, own test views | 24.00 |" in md
    assert (tmp_path / "out" / "deform_benchmark_tiny_partial.png").is_file()

    db.main(_args(bench, runs, *SHORT))  # the same config: the record and the unedited score are read back
    assert len(measured) == 1 and len(models) == 1
    other = SHORT[:-1] + ["init.carve.num_points=1200"]
    db.main(_args(bench, runs, *other))  # another config: measured anew, under its own key
    assert len(measured) == 2 and len(models) == 2
    _check_report(tmp_path / "out", runs, other)


def test_bad_set_is_refused(capsys):
    with pytest.raises(SystemExit):
        db.main(["--runs", "x", "--set", "render.no_such_field=1"])
    assert "--set" in capsys.readouterr().err


def _by_kind_rec(scene, edit, variant, psnr, ft=None):
    r = {"scene": scene, "edit": edit, "variant": variant,
         "zero_shot": {"psnr": psnr, "ssim": 0.5, "lpips": 0.1}}
    if ft is not None:
        r["finetune"] = {"psnr": ft, "ssim": 0.6, "lpips": None}
    return r


def test_means_by_kind_and_every_edit_has_a_kind(tmp_path):
    rec = _by_kind_rec
    records = [rec("stool", "twist", "full", 20.0, 21.0), rec("cup", "bend", "full", 22.0, 23.0),
               rec("cup", "delete_handle", "full", 18.0, 19.0), rec("cup", "bend", "no_ist", 10.0, 11.0)]
    table = db.by_kind(records).splitlines()
    assert table[0] == "| variant | smooth deformation | deletion | mean | SSIM | LPIPS |"
    assert table[2] == "| full | 21.00 | 18.00 | 20.00 | 0.500 | 0.100 |"
    assert table[3] == "| no_ist | 10.00 |  | 10.00 | 0.500 | 0.100 |"
    assert "| full | 22.00 | 19.00 | 21.00 | 0.600 |  |" in db.by_kind(records, "finetune")
    with pytest.raises(KeyError, match="has no kind"):
        db.kind_of("squash")
    path = tmp_path / "deform_benchmark_x.json"
    path.write_text(json.dumps({"preset": "x", "commit": "abc", "records": records,
                                "unedited": {"cup": {"psnr": 24.0}, "stool": {"psnr": 22.0}}}))
    db.main(["--by-kind", str(path)])
    assert "re-run: `python -m experiments.deform_benchmark --by-kind deform_benchmark_x.json`" in \
        (tmp_path / "deform_benchmark_x_by_kind.md").read_text()
    text = (tmp_path / "deform_benchmark_x_by_kind.md").read_text()
    assert "**Fine-tuned**" in text and "23.00 dB on their own test views" in text


def test_runs_are_required_without_by_kind(capsys):
    with pytest.raises(SystemExit):
        db.main(["--scenes", "cup"])
    assert "required: --runs" in capsys.readouterr().err

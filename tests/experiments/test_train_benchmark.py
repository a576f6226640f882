"""The training benchmark's command line refuses to restart runs it would overwrite."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[2] / "experiments" / "train_benchmark.py"


def _load():
    spec = importlib.util.spec_from_file_location("train_benchmark", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


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

"""Every experiment module imports, and a few answer ``python -m experiments.<name> --help``."""

from __future__ import annotations

import importlib
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
MODULES = sorted(p.stem for p in (ROOT / "experiments").glob("*.py") if p.stem != "__init__")


@pytest.mark.parametrize("name", MODULES)
def test_imports(name):
    importlib.import_module(f"experiments.{name}")


@pytest.mark.parametrize("name", ["compare_runs", "bench_presets"])
def test_help_runs_as_module(name):
    out = subprocess.run([sys.executable, "-m", f"experiments.{name}", "--help"], cwd=ROOT,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "usage" in out.stdout.lower()


def test_command_is_the_module_form():
    from experiments.common import command

    assert command("experiments.deform_benchmark", ["--scenes", "a b"]) == \
        "python -m experiments.deform_benchmark --scenes 'a b'"

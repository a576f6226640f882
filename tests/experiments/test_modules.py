"""Every experiment module imports without starting JAX, sets its process up in its entry point, and a
few answer ``python -m experiments.<name> --help``."""

from __future__ import annotations

import importlib
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
MODULES = sorted(p.stem for p in (ROOT / "experiments").glob("*.py") if p.stem != "__init__")


@pytest.mark.parametrize("name", MODULES)
def test_imports(name):
    importlib.import_module(f"experiments.{name}")


def test_imports_leave_jax_unstarted_for_the_entry_points_setup():
    """``ne_jax.setup()`` runs in an entry point after its module's imports: none may start JAX."""
    env = {k: v for k, v in os.environ.items() if k not in ("NE_JAX_HOST_DEVICES", "XLA_FLAGS", "JAX_NUM_CPU_DEVICES")}
    code = ("import importlib, jax, ne_jax\n"
            f"for name in {MODULES!r}:\n    importlib.import_module('experiments.' + name)\n"
            "ne_jax.setup(host_devices=3)\nprint(len(jax.devices()))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300,
                         env={**env, "JAX_PLATFORMS": "cpu"})
    assert out.returncode == 0, out.stderr
    assert out.stdout.split()[-1] == "3"


def test_every_entry_point_sets_its_process_up():
    """Each ``if __name__ == "__main__"`` block sets the process up before ``main()``, as ``ne-jax`` does:
    with :func:`experiments.common.entry`, or with ``ne_jax.setup`` itself (a module that runs against
    older code)."""
    for name in MODULES:
        text = (ROOT / "experiments" / f"{name}.py").read_text()
        if 'if __name__ == "__main__":' in text:
            block = text[text.index('if __name__ == "__main__":'):]
            assert "entry(main" in block or ("ne_jax.setup(" in block
                                             and block.index("ne_jax.setup(") < block.index("main()")), name


def test_entry_sets_up_then_exits_with_mains_status(monkeypatch):
    import ne_jax
    from experiments.common import entry

    calls = []
    monkeypatch.setattr(ne_jax, "setup", lambda **kw: calls.append(("setup", kw)))
    with pytest.raises(SystemExit) as exit_:
        entry(lambda: calls.append("main") or 3)
    assert calls == [("setup", {"huge_pages": True}), "main"] and exit_.value.code == 3


@pytest.mark.parametrize("name", ["compare_runs", "accuracy_vs_time"])
def test_help_runs_as_module(name):
    out = subprocess.run([sys.executable, "-m", f"experiments.{name}", "--help"], cwd=ROOT,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "usage" in out.stdout.lower()


def test_command_is_the_module_form():
    from experiments.common import command

    assert command("experiments.deform_benchmark", ["--scenes", "a b"]) == \
        "python -m experiments.deform_benchmark --scenes 'a b'"

"""One host device per usable core by default (``import ne_jax``), the opt-outs, JAX's own settings
winning, the warning when JAX started first, and the ``ne-jax --host-devices`` flag.

The device count is fixed once JAX's backends start, so the end-to-end checks run fresh Python
processes (``JAX_PLATFORMS=cpu``); the rule itself (:func:`requested_host_devices`) is checked on
environment dicts.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

import jax
import pytest

from ne_jax._platform import ENV, XLA_FLAG, requested_host_devices, usable_cores
from ne_jax.cli import build_parser
from ne_jax.devices import even_mesh, ray_mesh


def test_the_suite_runs_on_one_device_unless_told_otherwise():
    """tests/conftest.py sets NE_JAX_HOST_DEVICES=1 unless the environment chose a count."""
    assert ENV in os.environ
    if os.environ[ENV] == "1" and XLA_FLAG not in os.environ.get("XLA_FLAGS", ""):
        assert len(jax.devices()) == 1


@pytest.mark.parametrize("env, expected", [
    ({}, "cores"),
    ({"JAX_PLATFORMS": "cpu"}, "cores"),
    ({ENV: "3"}, 3),
    ({ENV: " 1 "}, 1),
    ({ENV: "3", "XLA_FLAGS": f"--xla_dump_to=/tmp {XLA_FLAG}=4"}, None),  # JAX's own count wins
    ({"JAX_NUM_CPU_DEVICES": "2"}, None),
    ({"JAX_PLATFORMS": "cuda"}, None),  # an accelerator: its devices, not the host's
    ({"JAX_PLATFORMS": "cuda,cpu", ENV: "3"}, None),
])
def test_requested_host_devices(env, expected):
    assert requested_host_devices(env) == (usable_cores() if expected == "cores" else expected)


@pytest.mark.parametrize("bad", ["0", "-2", "two", "1.5"])
def test_a_bad_count_is_a_named_error(bad):
    with pytest.raises(ValueError, match=rf"{ENV}: expected an integer >= 1 .* found '{bad}'"):
        requested_host_devices({ENV: bad})


def test_even_mesh_on_one_device():
    mesh = ray_mesh(1)
    assert even_mesh(7, mesh) is mesh


def _python(code: str, **env) -> subprocess.CompletedProcess:
    base = {k: v for k, v in os.environ.items() if k not in (ENV, "XLA_FLAGS", "JAX_NUM_CPU_DEVICES")}
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                          env={**base, "JAX_PLATFORMS": "cpu", **env})


def test_import_gives_one_device_per_core_and_the_opt_outs_work():
    """Default: one per usable core; NE_JAX_HOST_DEVICES=3; the CLI flag (after ``import ne_jax``,
    before JAX starts); JAX imported, but not started, before ne_jax; XLA_FLAGS winning over
    NE_JAX_HOST_DEVICES. One process per case (the count is fixed per process)."""
    count = "import json, jax; print(json.dumps(len(jax.devices())))"
    cases = [
        ({}, f"import ne_jax; {count}", usable_cores()),
        ({ENV: "3"}, f"import ne_jax; {count}", 3),
        ({ENV: "1"}, f"import jax; import ne_jax; {count}", 1),
        ({}, "import ne_jax.cli as c; c.main(['--host-devices', '3', 'export', '/nonexistent', '--out', 'x.ply']); "
             + count, 3),
        ({ENV: "3", "XLA_FLAGS": f"{XLA_FLAG}=2"}, f"import ne_jax; {count}", 2),
    ]
    for env, code, expected in cases:
        proc = _python(code, **env)
        assert proc.returncode == 0, proc.stderr
        assert json.loads(proc.stdout.strip().splitlines()[-1]) == expected, (env, code, proc.stdout)


def test_jax_started_before_ne_jax_warns_once_with_what_to_do():
    proc = _python("import warnings, jax; warnings.simplefilter('always'); jax.numpy.zeros(1); "
                   "import ne_jax, ne_jax._platform as p; p.configure_host_devices(); print(len(jax.devices()))",
                   **{ENV: "2"})
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "1"
    assert proc.stderr.count("RuntimeWarning") == 1, proc.stderr
    assert "JAX started before ne_jax could give it 2 host devices" in proc.stderr
    assert "Import ne_jax before running any JAX code" in proc.stderr and f"{ENV}=1 silences this" in proc.stderr


def test_host_devices_flag_is_parsed_and_checked(capsys):
    args = build_parser().parse_args(["--host-devices", "2", "export", "run", "--out", "x.ply"])
    assert args.host_devices == 2
    from ne_jax.cli import main

    assert main(["--host-devices", "0", "export", "run", "--out", "x.ply"]) == 2
    assert "--host-devices: expected an integer >= 1 (1 opts out), found 0" in capsys.readouterr().err

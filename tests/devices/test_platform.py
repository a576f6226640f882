"""Importing ``ne_jax`` changes nothing; ``ne_jax.setup()`` gives one host device per usable core,
the opt-outs and JAX's own settings win, it refuses once JAX has started with another count, and
the ``ne-jax --host-devices`` flag.

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
    """tests/conftest.py sets NE_JAX_HOST_DEVICES=1 (for ne_jax.setup() in the CLI and entry points
    tests run) unless the environment chose a count; the suite's own process keeps JAX's default."""
    assert ENV in os.environ
    if os.environ[ENV] == "1" and XLA_FLAG not in os.environ.get("XLA_FLAGS", ""):
        assert len(jax.devices()) == 1


@pytest.mark.parametrize("env, host_devices, expected", [
    ({}, None, "cores"),
    ({"JAX_PLATFORMS": "cpu"}, None, "cores"),
    ({ENV: "3"}, None, 3),
    ({ENV: " 1 "}, None, 1),
    ({ENV: "3"}, 2, 2),  # the argument (the CLI flag) over the variable
    ({}, 5, 5),
    ({ENV: "3", "XLA_FLAGS": f"--xla_dump_to=/tmp {XLA_FLAG}=4"}, None, None),  # JAX's own count wins
    ({"XLA_FLAGS": f"{XLA_FLAG}=4"}, 2, None),
    ({"JAX_NUM_CPU_DEVICES": "2"}, None, None),
    ({"JAX_PLATFORMS": "cuda"}, None, None),  # an accelerator: its devices, not the host's
    ({"JAX_PLATFORMS": "cuda,cpu", ENV: "3"}, 2, None),
])
def test_requested_host_devices(env, host_devices, expected):
    assert requested_host_devices(env, host_devices) == (usable_cores() if expected == "cores" else expected)


@pytest.mark.parametrize("bad", ["0", "-2", "two", "1.5"])
def test_a_bad_count_is_a_named_error(bad):
    with pytest.raises(ValueError, match=rf"{ENV}: expected an integer >= 1 .* found '{bad}'"):
        requested_host_devices({ENV: bad})
    with pytest.raises(ValueError, match=r"host_devices: expected an integer >= 1 .* found 0"):
        requested_host_devices({}, 0)


def test_even_mesh_on_one_device():
    mesh = ray_mesh(1)
    assert even_mesh(7, mesh) is mesh


def _python(code: str, **env) -> subprocess.CompletedProcess:
    drop = (ENV, "XLA_FLAGS", "JAX_NUM_CPU_DEVICES", "GLIBC_TUNABLES")
    base = {k: v for k, v in os.environ.items() if k not in drop}
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                          env={**base, "JAX_PLATFORMS": "cpu", **env})


_IMPORT_PROBE = """
import json, os, sys
# What `ne-jax train` looked like to the import that used to start the process again: an exec would
# end this probe, so record it instead.
sys.orig_argv = [sys.executable, "-m", "ne_jax.cli", "train", "scene"]
execs = []
os.execve = lambda *a: execs.append(a[1])
pid = os.getpid()
import ne_jax
jax_at_import = "jax" in sys.modules
import jax
print(json.dumps({"execs": execs, "same_pid": os.getpid() == pid, "jax_at_import": jax_at_import,
                  "config": jax.config.jax_num_cpu_devices, "devices": len(jax.devices())}))
"""


def test_import_changes_nothing():
    """``import ne_jax`` neither starts the process again (the command line of an entry point, no
    huge pages yet) nor imports JAX nor changes its device count, NE_JAX_HOST_DEVICES set or not."""
    proc = _python(_IMPORT_PROBE, **{ENV: "3"})
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout.strip().splitlines()[-1]) == {
        "execs": [], "same_pid": True, "jax_at_import": False, "config": -1, "devices": 1}


def test_setup_gives_one_device_per_core_and_the_opt_outs_work():
    """Default: one per usable core; NE_JAX_HOST_DEVICES=3; an explicit count; JAX imported, but
    not started, before ne_jax; the CLI flag; XLA_FLAGS winning over both. One process per case
    (the count is fixed per process)."""
    count = "import json, jax; print(json.dumps([n, len(jax.devices())]))"
    cases = [  # environment, code, what it returns, devices
        ({}, "import ne_jax; n = ne_jax.setup(); " + count, usable_cores(), usable_cores()),
        ({ENV: "3"}, "import ne_jax; n = ne_jax.setup(); " + count, 3, 3),
        ({ENV: "3"}, "import jax, ne_jax; n = ne_jax.setup(host_devices=2); " + count, 2, 2),
        ({}, "import ne_jax.cli as c; n = c.main(['--host-devices', '3', 'export', '/nonexistent', '--out', 'x.ply']); "
             + count, 2, 3),  # the command's exit status: no such run
        ({ENV: "3", "XLA_FLAGS": f"{XLA_FLAG}=2"}, "import ne_jax; n = ne_jax.setup(4); " + count, None, 2),
    ]
    for env, code, returned, devices in cases:
        proc = _python(code, **env)
        assert proc.returncode == 0, proc.stderr
        assert json.loads(proc.stdout.strip().splitlines()[-1]) == [returned, devices], (env, code, proc.stdout)


def test_setup_after_jax_started_says_what_to_do():
    """Too late for another count: a ``RuntimeError`` naming the fix; the count JAX already has is fine."""
    proc = _python("import jax, ne_jax; jax.numpy.zeros(1); print(ne_jax.setup(1)); ne_jax.setup(2)")
    assert proc.returncode == 1 and proc.stdout.strip() == "1", proc.stderr
    assert "RuntimeError: ne_jax.setup: JAX's backends already started with 1 CPU device(s), so it cannot have 2" \
        in proc.stderr
    assert "Call ne_jax.setup() before any JAX code runs" in proc.stderr


def test_host_devices_flag_is_parsed_and_checked(capsys):
    args = build_parser().parse_args(["--host-devices", "2", "export", "run", "--out", "x.ply"])
    assert args.host_devices == 2
    from ne_jax.cli import main

    assert main(["--host-devices", "0", "export", "run", "--out", "x.ply"]) == 2
    assert "--host-devices: expected an integer >= 1 (1 opts out), found 0" in capsys.readouterr().err

"""Huge pages for XLA:CPU's scratch memory: the tunable's effect, how ``ne_jax.setup(huge_pages=True)``
starts the process again with it (and only ``ne-jax`` run as the program asks), the
``NE_JAX_HOST_MEMORY=system`` opt-out, and a bad value naming the variable.

glibc reads its tunables when a process starts, so the effect is checked in fresh Python processes:
a worker thread (as XLA:CPU runs a device's program) allocates, touches and frees a 100 MB block
again and again. glibc maps such a block afresh every time (a thread's own arena cannot hold it),
and the page faults per block drop with huge pages from one per 4 KiB to one per 2 MiB.
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys

import pytest

from ne_jax import _host_memory
from ne_jax._host_memory import ENV, TUNABLE, requested_policy, restart_with_huge_pages, tunables_env

_PROBE = """
import ctypes, json, resource, threading
libc = ctypes.CDLL("libc.so.6")
libc.malloc.restype = ctypes.c_void_p
libc.free.argtypes = [ctypes.c_void_p]
size = 100 << 20
out = {}
def block():
    p = libc.malloc(size)
    ctypes.memset(p, 1, size)
    libc.free(p)
def work():
    block(); block()
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(5):
        block()
    out["faults_per_block"] = (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / 5
t = threading.Thread(target=work)
t.start()
t.join()
print(json.dumps(out))
"""

_LIBC = platform.libc_ver()
_GLIBC = platform.system() == "Linux" and _LIBC[0] == "glibc"
# glibc.malloc.hugetlb exists from glibc 2.35 on (older ones ignore it)
_HUGETLB_TUNABLE = _GLIBC and tuple(int(x) for x in _LIBC[1].split(".")[:2]) >= (2, 35)


def _thp_available() -> bool:
    try:
        with open("/sys/kernel/mm/transparent_hugepage/enabled") as f:
            return "[never]" not in f.read()
    except OSError:
        return False


def _probe(tunables: str | None) -> float:
    env = {k: v for k, v in os.environ.items() if k != "GLIBC_TUNABLES"}
    if tunables:
        env["GLIBC_TUNABLES"] = tunables
    out = subprocess.run([sys.executable, "-c", _PROBE], env=env, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])["faults_per_block"]


@pytest.mark.skipif(not (_HUGETLB_TUNABLE and _thp_available()), reason="glibc >= 2.35 with transparent huge pages")
def test_huge_pages_cut_the_faults_of_a_threads_large_blocks():
    system, huge = _probe(None), _probe(TUNABLE)
    assert system > 20_000  # a fresh mapping per block, a fault per 4 KiB page (25,600 pages)
    assert huge < 0.25 * system  # 50 faults with every huge page granted; margin for some 4 KiB fallbacks


def test_the_environment_to_start_again_with(monkeypatch):
    monkeypatch.setattr(_host_memory, "_is_glibc", lambda: True)
    assert tunables_env({})["GLIBC_TUNABLES"] == TUNABLE
    assert tunables_env({"GLIBC_TUNABLES": "glibc.malloc.arena_max=2", "X": "1"}) == {
        "GLIBC_TUNABLES": f"glibc.malloc.arena_max=2:{TUNABLE}", "X": "1"}
    assert tunables_env({"GLIBC_TUNABLES": "glibc.malloc.hugetlb=0"}) is None  # the user's own choice
    assert tunables_env({"GLIBC_TUNABLES": TUNABLE}) is None  # already started with it: no loop
    assert tunables_env({ENV: "system"}) is None
    monkeypatch.setattr(_host_memory, "_is_glibc", lambda: False)
    assert tunables_env({}) is None


def test_restart_replaces_the_process_only_when_it_adds_something(monkeypatch):
    """The same command line (the interpreter's, so a console script or ``-m`` run starts again as
    it was started) with the tunable added; nothing to add, nothing done; no command line, an error."""
    calls = []
    monkeypatch.setattr(os, "execve", lambda exe, argv, env: calls.append((exe, argv, env)))
    monkeypatch.setattr(_host_memory, "_is_glibc", lambda: True)
    monkeypatch.delenv("GLIBC_TUNABLES", raising=False)
    monkeypatch.delenv(ENV, raising=False)
    restart_with_huge_pages(["/venv/bin/python3", "/venv/bin/ne-jax", "train", "scene", "--out", "run"])
    ((exe, argv, env),) = calls
    assert exe == sys.executable and argv == [sys.executable, "/venv/bin/ne-jax", "train", "scene", "--out", "run"]
    assert env["GLIBC_TUNABLES"] == TUNABLE
    with pytest.raises(RuntimeError, match="no command line to start again"):
        restart_with_huge_pages(["python"])  # an interactive interpreter
    monkeypatch.setenv(ENV, "system")
    restart_with_huge_pages(["python", "-m", "ne_jax.cli"])
    monkeypatch.setenv(ENV, "huge_pages")
    monkeypatch.setenv("GLIBC_TUNABLES", TUNABLE)  # started with it: no loop
    restart_with_huge_pages(["python", "-m", "ne_jax.cli"])
    assert len(calls) == 1


@pytest.mark.skipif(not _GLIBC, reason="glibc")
def test_setup_with_huge_pages_starts_the_program_again_once_with_the_tunable():
    code = ("import os, ne_jax; print('started', os.getpid(), flush=True); ne_jax.setup(huge_pages=True); "
            "print('tunables', os.environ['GLIBC_TUNABLES'])")
    env = {k: v for k, v in os.environ.items() if k not in ("GLIBC_TUNABLES", ENV)}
    out = subprocess.run([sys.executable, "-c", code], env={**env, "JAX_PLATFORMS": "cpu"}, capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.split()
    assert lines[0::2] == ["started", "started", "tunables"]  # one restart (the same process), then on
    assert lines[1] == lines[3] and lines[-1] == TUNABLE


def test_only_the_program_ne_jax_starts_itself_again(monkeypatch):
    """``ne-jax ...`` (``main()`` reading the command line) asks for huge pages; ``main([...])``
    called from Python never starts the caller's process again."""
    from ne_jax import _platform
    from ne_jax.cli import main

    asked = []
    monkeypatch.setattr(_platform, "restart_with_huge_pages", lambda: asked.append(True))
    command = ["--host-devices", "1", "export", "/nonexistent", "--out", "x.ply"]
    assert main(command) == 2 and asked == []  # no such run
    monkeypatch.setattr(sys, "argv", ["ne-jax", *command])
    assert main() == 2 and asked == [True]


@pytest.mark.parametrize("env, expected", [({}, "huge_pages"), ({ENV: " Huge_Pages "}, "huge_pages"),
                                           ({ENV: "system"}, "system"), ({ENV: ""}, "huge_pages")])
def test_the_policy_from_the_environment(env, expected):
    assert requested_policy(env) == expected


def test_an_unknown_policy_names_the_variable():
    with pytest.raises(ValueError, match=rf"{ENV}: expected 'huge_pages' \(the default\) or 'system', found 'keep'"):
        requested_policy({ENV: "keep"})


def test_the_command_line_names_a_bad_policy():
    env = {**os.environ, ENV: "keep"}
    out = subprocess.run([sys.executable, "-m", "ne_jax.cli", "export", "/nonexistent", "--out", "x.ply"], env=env,
                         capture_output=True, text=True)
    assert out.returncode == 2 and f"ne-jax export: error: {ENV}: expected 'huge_pages'" in out.stderr

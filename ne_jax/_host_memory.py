"""Huge pages for XLA:CPU's scratch memory: 25x fewer page faults per training step.

Each call of a compiled program on a CPU device allocates one large block of scratch memory (about
150 MB per device for a ``default`` training step, 130 MB for a 4,096-ray render chunk) and frees
it at the end. XLA's worker threads allocate from glibc's per-thread arenas, which cannot hold a
block that size, so glibc maps it afresh on every call and unmaps it when it is freed: each call
touches its scratch memory page by page for the first time, about 73,000 page faults per ``default``
training step, a quarter of the step's CPU time spent in the kernel.

glibc's tunable ``glibc.malloc.hugetlb=1`` asks for transparent huge pages on such mappings
(``madvise``): one fault per 2 MiB instead of per 4 KiB. Tunables are read when a process starts,
so a process started as ``ne-jax``, ``python -m ne_jax.<name>`` or ``python -m experiments.<name>``
starts itself again with ``GLIBC_TUNABLES`` extended by it when ``ne_jax`` is imported, before JAX
loads (:func:`reexec_entry_point`), and ``run.sh`` exports it; for your own scripts and notebooks,
start Python with ``GLIBC_TUNABLES=glibc.malloc.hugetlb=1``. ``NE_JAX_HOST_MEMORY=system`` keeps glibc's defaults.
``python -m experiments.bench_host_memory`` measures both in one run (docs/studies/profile.md,
"Page faults").

Keeping the scratch memory mapped instead (``mallopt``: one arena, no separate mappings) removes
the faults too, but funnels every thread through one arena lock: compiles slow down, and a ``tiny``
training took 1.2x as long (the same benchmark at commit 3d0d52c, which did that).
"""

from __future__ import annotations

import os
import platform
import sys

ENV = "NE_JAX_HOST_MEMORY"
"""Environment variable: ``huge_pages`` (default) or ``system`` (glibc's own settings)."""

TUNABLE = "glibc.malloc.hugetlb=1"

CONSOLE_SCRIPTS = {"ne-jax": "ne_jax.cli"}
"""Console scripts (``pyproject.toml``) and the module each runs."""

ENTRY_PACKAGES = ("ne_jax", "experiments")
"""Packages whose modules, run as ``python -m <package>.<name>``, start again with huge pages."""


def requested_policy(environ=None) -> str:
    """``"huge_pages"`` or ``"system"`` from ``NE_JAX_HOST_MEMORY`` in ``environ`` (default
    ``os.environ``); raises ``ValueError`` naming the variable for anything else."""
    env = os.environ if environ is None else environ
    raw = env.get(ENV, "").strip().lower() or "huge_pages"
    if raw not in ("huge_pages", "system"):
        raise ValueError(f"{ENV}: expected 'huge_pages' (the default) or 'system', found {env.get(ENV)!r}")
    return raw


def _is_glibc() -> bool:
    return platform.system() == "Linux" and platform.libc_ver()[0] == "glibc"


def tunables_env(environ=None) -> dict | None:
    """The environment to start this process again with (``environ`` with :data:`TUNABLE` added to
    ``GLIBC_TUNABLES``), or ``None`` when there is nothing to do: not glibc, ``NE_JAX_HOST_MEMORY=system``,
    or ``GLIBC_TUNABLES`` already says something about ``glibc.malloc.hugetlb``."""
    env = dict(os.environ if environ is None else environ)
    if requested_policy(env) == "system" or not _is_glibc():
        return None
    current = env.get("GLIBC_TUNABLES", "")
    if "glibc.malloc.hugetlb" in current:
        return None
    env["GLIBC_TUNABLES"] = f"{current}:{TUNABLE}" if current else TUNABLE
    return env


def reexec_with_huge_pages(module: str, args: list[str]) -> None:
    """Replace this process by ``python -m module *args`` started with :func:`tunables_env`, if it
    has something to add; else return. Call it first thing in a command-line entry point."""
    env = tunables_env()
    if env is not None:
        sys.stdout.flush()
        sys.stderr.flush()
        os.execve(sys.executable, [sys.executable, "-m", module, *args], env)


def entry_point(orig_argv: list[str]) -> tuple[str, list[str]] | None:
    """``(module, args)`` when ``orig_argv`` (the interpreter's command line, ``sys.orig_argv``) runs
    one of :data:`CONSOLE_SCRIPTS` or ``python [options] -m <package>.<name> [args]`` for a package of
    :data:`ENTRY_PACKAGES`, else ``None`` (imported by a test, a notebook, another program)."""
    if len(orig_argv) > 1 and not orig_argv[1].startswith("-"):  # a script: a console script?
        module = CONSOLE_SCRIPTS.get(os.path.basename(orig_argv[1]))
        return (module, orig_argv[2:]) if module else None
    if "-m" not in orig_argv[1:]:
        return None
    i = orig_argv.index("-m", 1)
    if i + 1 >= len(orig_argv) or not orig_argv[i + 1].startswith(tuple(p + "." for p in ENTRY_PACKAGES)):
        return None
    return orig_argv[i + 1], orig_argv[i + 2:]


def reexec_entry_point() -> None:
    """:func:`reexec_with_huge_pages` when this process's command line runs an entry point
    (:func:`entry_point`); ``import ne_jax`` calls it before JAX loads. A bad ``NE_JAX_HOST_MEMORY``
    ends the process with a one-line error (exit status 2)."""
    run = entry_point(list(getattr(sys, "orig_argv", [])))
    if run is None:
        return
    try:
        reexec_with_huge_pages(*run)
    except ValueError as e:
        name = next((k for k, v in CONSOLE_SCRIPTS.items() if v == run[0]), run[0])
        print(f"{name}: error: {e}", file=sys.stderr)
        sys.exit(2)


__all__ = ["CONSOLE_SCRIPTS", "ENTRY_PACKAGES", "ENV", "TUNABLE", "entry_point", "reexec_entry_point",
           "reexec_with_huge_pages", "requested_policy", "tunables_env"]

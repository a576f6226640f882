"""Huge pages for XLA:CPU's scratch memory: 25x fewer page faults per training step.

Each call of a compiled program on a CPU device allocates one large block of scratch memory (about
150 MB per device for a ``default`` training step, 130 MB for a 4,096-ray render chunk) and frees
it at the end. XLA's worker threads allocate from glibc's per-thread arenas, which cannot hold a
block that size, so glibc maps it afresh on every call and unmaps it when it is freed: each call
touches its scratch memory page by page for the first time, about 73,000 page faults per ``default``
training step, a quarter of the step's CPU time spent in the kernel.

glibc's tunable ``glibc.malloc.hugetlb=1`` asks for transparent huge pages on such mappings
(``madvise``): one fault per 2 MiB instead of per 4 KiB. Tunables are read when a process starts,
so they cannot be set from inside a running process, and importing ``ne_jax`` does not try: an
entry point asks for them explicitly with ``ne_jax.setup(huge_pages=True)``
(:func:`restart_with_huge_pages`: the same command line started again with ``GLIBC_TUNABLES``
extended by it), which ``ne-jax`` and ``python -m experiments.<name>`` do first thing, and
``run.sh`` exports the tunable. For your own scripts and notebooks, start Python with
``GLIBC_TUNABLES=glibc.malloc.hugetlb=1`` (or call ``ne_jax.setup(huge_pages=True)`` first thing
in a script). ``NE_JAX_HOST_MEMORY=system`` keeps glibc's defaults.
What they save: docs/decisions.md, huge pages.

Keeping the scratch memory mapped instead (``mallopt``: one arena, no separate mappings) removes
the faults too, but funnels every thread through one arena lock, and compiles slow down
(docs/decisions.md, huge pages).
"""

from __future__ import annotations

import os
import platform
import sys

ENV = "NE_JAX_HOST_MEMORY"
"""Environment variable: ``huge_pages`` (default) or ``system`` (glibc's own settings)."""

TUNABLE = "glibc.malloc.hugetlb=1"
"""The glibc tunable that gives large ``malloc`` mappings transparent huge pages."""


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


def restart_with_huge_pages(orig_argv: list[str] | None = None) -> None:
    """Replace this process by its own command line (``orig_argv``, default ``sys.orig_argv``: the
    interpreter's, so ``ne-jax train ...``, ``python -m experiments.<name> ...`` and ``python
    script.py ...`` all start again as they were started) under :func:`tunables_env`, if that adds
    something; else return. For a program's entry point, first thing (the program starts over);
    ``ValueError`` for a bad ``NE_JAX_HOST_MEMORY``, ``RuntimeError`` for an interactive interpreter
    (no command line to start again: start it with ``GLIBC_TUNABLES`` instead)."""
    env = tunables_env()
    if env is None:
        return
    argv = list(sys.orig_argv if orig_argv is None else orig_argv)
    if len(argv) < 2 or argv[1] == "-":
        raise RuntimeError(f"huge pages: this interpreter has no command line to start again ({argv!r}); "
                           f"start Python with GLIBC_TUNABLES={TUNABLE} instead")
    sys.stdout.flush()
    sys.stderr.flush()
    os.execve(sys.executable, [sys.executable, *argv[1:]], env)


__all__ = ["ENV", "TUNABLE", "requested_policy", "restart_with_huge_pages", "tunables_env"]

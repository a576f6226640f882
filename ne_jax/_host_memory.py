"""Host memory that stays mapped: no page faults for XLA:CPU's per-call scratch memory.

Each call of a compiled program on a CPU device allocates one large block of scratch memory (about
150 MB per device for a ``default`` training step, 130 MB for a 4,096-ray render chunk) and frees
it at the end. Under glibc's default settings a block that size is a fresh ``mmap`` each time:
XLA's worker threads allocate from per-thread arenas, whose heaps cannot hold more than 64 MB, so
glibc maps the block directly, whatever its mmap settings say, and unmaps it when it is freed.
Every call then touches its scratch memory page by page for the first time: about 77,000 page
faults per training step, a fifth of the step's CPU time spent in the kernel.

So when ``ne_jax`` is imported it tells glibc (``mallopt``) to serve every thread from one arena
(``M_ARENA_MAX = 1``), never to map blocks on their own (``M_MMAP_MAX = 0``) and to give freed
memory back to the system only above 1 GiB at the heap's top (``M_TRIM_THRESHOLD``). The scratch
blocks are then reused from the heap without a fault. The price: the process keeps its peak heap
(less what exceeds that threshold) until it exits. ``python -m experiments.bench_host_memory``
measures both settings in one run (docs/studies/profile.md, "Page faults").

It must happen before XLA's threads first allocate (before the first JAX computation): a thread
that already has an arena keeps it. Only glibc has ``mallopt``; elsewhere nothing changes.
``NE_JAX_HOST_MEMORY=system`` keeps glibc's defaults.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import platform

ENV = "NE_JAX_HOST_MEMORY"
"""Environment variable: ``keep`` (default) or ``system`` (glibc's own settings)."""

M_TRIM_THRESHOLD, M_MMAP_MAX, M_ARENA_MAX = -1, -4, -8  # glibc's malloc.h
TRIM_THRESHOLD = 1 << 30
SETTINGS = ((M_ARENA_MAX, 1), (M_MMAP_MAX, 0), (M_TRIM_THRESHOLD, TRIM_THRESHOLD))

_applied: bool | None = None


def requested_policy(environ=None) -> str:
    """``"keep"`` or ``"system"`` from ``NE_JAX_HOST_MEMORY`` in ``environ`` (default
    ``os.environ``); raises ``ValueError`` naming the variable for anything else."""
    env = os.environ if environ is None else environ
    raw = env.get(ENV, "").strip().lower() or "keep"
    if raw not in ("keep", "system"):
        raise ValueError(f"{ENV}: expected 'keep' (the default) or 'system', found {env.get(ENV)!r}")
    return raw


def _glibc():
    """glibc's ``libc`` (``None`` on other C libraries and platforms)."""
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return None
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:
        return None


def configure_host_memory(environ=None) -> bool:
    """Apply :data:`SETTINGS` with ``mallopt`` unless ``NE_JAX_HOST_MEMORY=system``. Returns whether
    they were applied (``False`` off glibc, or when opted out). Called on ``import ne_jax``; once per
    process (later calls return the first answer)."""
    global _applied
    if _applied is not None:
        return _applied
    libc = _glibc() if requested_policy(environ) == "keep" else None
    _applied = libc is not None and all(libc.mallopt(param, value) == 1 for param, value in SETTINGS)
    return _applied


__all__ = ["ENV", "SETTINGS", "configure_host_memory", "requested_policy"]

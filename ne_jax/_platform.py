"""Setting a process up for ne_jax: :func:`setup`, which an entry point calls; importing changes nothing.

Importing ``ne_jax`` leaves the process as it is: JAX keeps its defaults (one CPU device) and glibc
its malloc settings. A program that wants what the ``ne-jax`` command line gets calls
:func:`setup` (exported as ``ne_jax.setup``) before any JAX code runs. The command line
(``ne_jax.cli.main``) and the experiments' entry points (``python -m experiments.<name>``) call it
themselves, and ``run.sh`` exports the huge-page tunable as well.

**Host devices.** One XLA:CPU program keeps only part of a multi-core machine busy, while the
renderer and the training step split their rays over every device JAX sees
(:mod:`ne_jax.devices`). So :func:`setup` sets JAX's ``jax_num_cpu_devices`` (the config equivalent
of ``XLA_FLAGS=--xla_force_host_platform_device_count=N``) to ``N`` = the cores this process may run
on (``os.sched_getaffinity``). Only the host platform changes: on a GPU or TPU the default devices,
and with them the default mesh, are the accelerator's.

What decides ``N`` (:func:`requested_host_devices`), first match wins:

1. a device count given to JAX itself is kept as it is: ``--xla_force_host_platform_device_count``
   in ``XLA_FLAGS``, ``JAX_NUM_CPU_DEVICES`` or ``jax.config.update("jax_num_cpu_devices", n)``;
2. an accelerator platform requested (``JAX_PLATFORMS`` set to anything but ``cpu``): left alone;
3. ``setup(host_devices=N)`` (the ``ne-jax --host-devices N`` global flag);
4. ``NE_JAX_HOST_DEVICES=N`` (an integer >= 1; ``1`` keeps JAX's own default of one device);
5. otherwise the number of usable cores.

The count must be set before JAX starts its backends (the first array or ``jax.devices()`` call);
:func:`setup` called later raises ``RuntimeError``, saying what to do, unless JAX already has the
count asked for.

**Huge pages** (``setup(huge_pages=True)``, :mod:`ne_jax._host_memory`): glibc reads its tunables
when a process starts, so this starts the process again, from its own command line, with
``GLIBC_TUNABLES=glibc.malloc.hugetlb=1`` added (unless it has it already, ``NE_JAX_HOST_MEMORY=system``,
or the C library is not glibc). Only for a program's entry point, first thing; in a notebook, start
the kernel with that variable instead.

Separate from the device count: XLA:CPU keeps one intra-op thread pool for the whole process (not
one per device), so N devices on N cores do not multiply the threads (measured in
``experiments/bench_devices.py``).
"""

from __future__ import annotations

import os

from ne_jax._host_memory import restart_with_huge_pages

ENV = "NE_JAX_HOST_DEVICES"
"""Environment variable: how many host (CPU) devices :func:`setup` asks JAX for; 1 keeps JAX's default."""

XLA_FLAG = "--xla_force_host_platform_device_count"

_applied: int | None = None  # the count setup() gave jax_num_cpu_devices, if any


def usable_cores() -> int:
    """The number of CPU cores this process may run on (its affinity mask; ``os.cpu_count()``
    where the platform has none)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def _count(raw, where: str) -> int:
    try:
        n = int(str(raw).strip())
    except ValueError:
        n = 0
    if isinstance(raw, bool) or n < 1:
        raise ValueError(f"{where}: expected an integer >= 1 (the number of host devices; 1 keeps JAX's default), "
                         f"found {raw!r}")
    return n


def requested_host_devices(environ=None, host_devices: int | None = None) -> int | None:
    """The host device count :func:`setup` asks for under ``environ`` (default ``os.environ``) and
    an explicit ``host_devices``, or ``None`` where it leaves JAX's setting alone (a count given to
    JAX itself, or an accelerator platform requested). Raises ``ValueError`` for a count (argument or
    ``NE_JAX_HOST_DEVICES``) that is not an integer >= 1."""
    env = os.environ if environ is None else environ
    if host_devices is not None:
        host_devices = _count(host_devices, "host_devices")
    if XLA_FLAG in env.get("XLA_FLAGS", "") or env.get("JAX_NUM_CPU_DEVICES", "").strip():
        return None
    platforms = {p.strip().lower() for p in env.get("JAX_PLATFORMS", "").split(",") if p.strip()}
    if platforms - {"cpu"}:
        return None
    if host_devices is not None:
        return host_devices
    raw = env.get(ENV, "").strip()
    return _count(raw, ENV) if raw else usable_cores()


def setup(host_devices: int | None = None, *, huge_pages: bool = False) -> int | None:
    """Set this process up as the ``ne-jax`` command line does; call it before any JAX code runs.

    Args:
      host_devices: how many host (CPU) devices JAX shows, so the rays split over that many
        (:mod:`ne_jax.devices`); ``None``: ``NE_JAX_HOST_DEVICES``, else one per usable core. A
        count given to JAX itself (``XLA_FLAGS=--xla_force_host_platform_device_count=N``,
        ``JAX_NUM_CPU_DEVICES``, ``jax.config.update("jax_num_cpu_devices", n)``) and an
        accelerator platform (``JAX_PLATFORMS=cuda``) are left as they are.
      huge_pages: also give XLA:CPU's scratch memory huge pages, by starting this process again
        from its command line with ``GLIBC_TUNABLES=glibc.malloc.hugetlb=1`` where it lacks it
        (:mod:`ne_jax._host_memory`; ``NE_JAX_HOST_MEMORY=system`` declines). The program starts
        over, so only for a script's entry point, first thing; not in a notebook.

    Returns:
      The host device count JAX will have, or ``None`` where JAX's own setting decides.

    Raises:
      RuntimeError: JAX's backends already started with another CPU device count (JAX code ran
        before this call: call it first, or in a notebook restart the kernel and call it first).
      ValueError: a count that is not an integer >= 1, or a bad ``NE_JAX_HOST_MEMORY``.

    Safe to call again: a second call with the same request does nothing.
    """
    global _applied
    if huge_pages:
        restart_with_huge_pages()  # returns only where there is nothing to add
    n = requested_host_devices(host_devices=host_devices)
    import jax

    current = jax.config.jax_num_cpu_devices
    if n is None or (current != -1 and current != _applied):  # JAX's own setting decides
        return None
    if n == current:
        return n
    try:
        jax.config.update("jax_num_cpu_devices", n)  # JAX refuses once its backends run
    except RuntimeError:
        have = jax.local_device_count("cpu")
        if have == n:
            return n
        raise RuntimeError(
            f"ne_jax.setup: JAX's backends already started with {have} CPU device(s), so it cannot have {n} any "
            f"more. Call ne_jax.setup() before any JAX code runs (in a notebook: restart the kernel and call it "
            f"first), set XLA_FLAGS={XLA_FLAG}={n} before starting Python, or ask for the devices JAX has "
            f"(host_devices={have}, {ENV}={have}).") from None
    _applied = n
    return n


__all__ = ["ENV", "XLA_FLAG", "requested_host_devices", "setup", "usable_cores"]

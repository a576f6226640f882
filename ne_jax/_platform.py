"""Every CPU core by default: on the CPU platform, JAX sees one host device per usable core.

One XLA:CPU program keeps only part of a multi-core machine busy, while the renderer and the
training step split their rays over every device JAX sees (:mod:`ne_jax.devices`). So when
``ne_jax`` is imported it sets JAX's ``jax_num_cpu_devices`` (the config equivalent of
``XLA_FLAGS=--xla_force_host_platform_device_count=N``) to ``N`` = the cores this process may run
on (``os.sched_getaffinity``). Only the host platform changes: on a GPU or TPU the default devices,
and with them the default mesh, are the accelerator's.

What decides ``N`` (:func:`requested_host_devices`), first match wins:

1. a device count given to JAX itself is kept as it is: ``--xla_force_host_platform_device_count``
   in ``XLA_FLAGS``, ``JAX_NUM_CPU_DEVICES`` or ``jax.config.update("jax_num_cpu_devices", n)``;
2. an accelerator platform requested (``JAX_PLATFORMS`` set to anything but ``cpu``): left alone;
3. ``NE_JAX_HOST_DEVICES=N`` (an integer >= 1; ``1`` is the opt-out: one device, JAX's own
   default), which the ``ne-jax --host-devices N`` global flag sets;
4. otherwise the number of usable cores.

The count must be set before JAX starts its backends (the first array or ``jax.devices()`` call).
If that already happened when ``ne_jax`` is imported (a notebook that ran JAX code first), the
count cannot change any more: :func:`configure_host_devices` warns once, saying what to do, and
everything runs on the devices JAX has.

Separate from the device count: XLA:CPU keeps one intra-op thread pool for the whole process (not
one per device), so N devices on N cores do not multiply the threads (measured in
``experiments/bench_devices.py``).
"""

from __future__ import annotations

import os
import warnings

ENV = "NE_JAX_HOST_DEVICES"
"""Environment variable: how many host (CPU) devices ne_jax asks JAX for; 1 opts out."""

XLA_FLAG = "--xla_force_host_platform_device_count"

_applied: int | None = None  # the count this module gave jax_num_cpu_devices, if any
_warned = False


def usable_cores() -> int:
    """The number of CPU cores this process may run on (its affinity mask; ``os.cpu_count()``
    where the platform has none)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def requested_host_devices(environ=None) -> int | None:
    """The host device count ne_jax asks for under ``environ`` (default ``os.environ``), or
    ``None`` where it leaves JAX's setting alone (a count given to JAX itself, or an accelerator
    platform requested). Raises ``ValueError`` for an ``NE_JAX_HOST_DEVICES`` that is not an
    integer >= 1."""
    env = os.environ if environ is None else environ
    if XLA_FLAG in env.get("XLA_FLAGS", "") or env.get("JAX_NUM_CPU_DEVICES", "").strip():
        return None
    platforms = {p.strip().lower() for p in env.get("JAX_PLATFORMS", "").split(",") if p.strip()}
    if platforms - {"cpu"}:
        return None
    raw = env.get(ENV, "").strip()
    if raw:
        try:
            n = int(raw)
        except ValueError:
            n = 0
        if n < 1:
            raise ValueError(f"{ENV}: expected an integer >= 1 (the number of host devices; 1 opts out), found {raw!r}")
        return n
    return usable_cores()


def configure_host_devices(environ=None) -> int | None:
    """Give JAX ``requested_host_devices(environ)`` host devices, before its backends start.

    Returns the count set, or ``None`` where nothing was set (JAX's own setting kept, an
    accelerator platform, or the backends already running: then one warning per process, if the
    count JAX has differs from the one asked for). Called on ``import ne_jax`` and again by the
    ``ne-jax --host-devices`` flag; safe to call again while JAX has not started."""
    global _applied, _warned
    import jax
    from jax._src import xla_bridge

    current = jax.config.jax_num_cpu_devices
    if current != -1 and current != _applied:  # the user's own jax.config.update
        return None
    n = requested_host_devices(environ)
    if n is None:
        n = -1  # JAX's default (or the XLA flag) decides
    if n == current:
        return None if n == -1 else n
    if xla_bridge.backends_are_initialized():
        cpu = xla_bridge._backends.get("cpu")
        have = None if cpu is None else cpu.device_count()
        if n != -1 and have is not None and have != n and not _warned:
            _warned = True
            warnings.warn(
                f"ne_jax: JAX started before ne_jax could give it {n} host devices (one per usable core), so rays "
                f"run on {have}. Import ne_jax before running any JAX code (in a notebook: restart the kernel and "
                f"import ne_jax first), or set XLA_FLAGS={XLA_FLAG}={n} before starting Python; "
                f"{ENV}=1 silences this and keeps one device.", RuntimeWarning, stacklevel=2)
        return None
    jax.config.update("jax_num_cpu_devices", n)
    _applied = None if n == -1 else n
    return _applied


__all__ = ["ENV", "XLA_FLAG", "configure_host_devices", "requested_host_devices", "usable_cores"]

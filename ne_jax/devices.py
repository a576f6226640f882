"""Many devices with JAX's own sharding: rays split over a one-axis device mesh, everything else
replicated.

Every ray renders independently of the others, so a batch of rays splits over devices with no
communication at all: :func:`shard_rays` runs a per-ray function under ``jax.shard_map`` with the
ray arrays split along the mesh axis ``"rays"`` and the point state, the K-D tree and the model
replicated. The KNN's gather + ``top_k`` then stays on each device (under plain ``jit``, ``top_k``
would gather the whole tensor to every device, docs/design.md). Training reduces what the devices
computed on their rays with ``pmean`` over the same axis (:mod:`ne_jax.train.step`): the loss terms
are means over rays (or over points, identical on every device), so the mean over equal shards is
the batch's mean.

One code path: the renderer and the training step always run through the mesh, and one device is
the mesh of size 1. :func:`default_mesh` spans every device JAX sees (all hosts' after
:func:`initialize_distributed`): the accelerators on a GPU/TPU machine, and on a CPU one host
device per usable core where the process was set up with ``ne_jax.setup()`` (as ``ne-jax`` is;
:mod:`ne_jax._platform`; ``NE_JAX_HOST_DEVICES=1`` or ``ne-jax --host-devices 1`` opts out), else
JAX's default of one. A ray batch must split evenly:
render chunks are padded to a multiple of the mesh size (:func:`padded_size`), and a training batch
that does not split over the whole mesh runs on the largest leading part of it that it does split
over (:func:`even_mesh`; e.g. 1024 rays on 3 devices use 2).

Multi-host: start one process per host with the same ``--coordinator host:port`` and
``--num-processes N`` and its own ``--process-id`` (the ``ne-jax`` global flags), which call
:func:`initialize_distributed` (``jax.distributed.initialize``) before anything else touches JAX.
"""

from __future__ import annotations

import functools

import jax
from jax.sharding import AxisType, Mesh
from jax.sharding import PartitionSpec as P

RAYS = "rays"
"""The name of the mesh axis rays are split over."""


def ray_mesh(num_devices: int | None = None) -> Mesh:
    """A one-axis mesh ``("rays",)`` over the first ``num_devices`` devices (default: all). Axis
    type ``Auto`` (an explicit axis would make plain gathers of replicated arrays a sharding type
    error, docs/design.md)."""
    available = len(jax.devices())
    n = available if num_devices is None else int(num_devices)
    if not 1 <= n <= available:
        raise ValueError(f"ray_mesh: expected 1 to {available} devices (what JAX sees: {jax.devices()[0].platform} "
                         f"x {available}), found num_devices={num_devices}")
    return jax.make_mesh((n,), (RAYS,), axis_types=(AxisType.Auto,), devices=jax.devices()[:n])


@functools.cache
def default_mesh() -> Mesh:
    """The mesh over every device JAX sees (cached: create it after :func:`initialize_distributed`)."""
    return ray_mesh()


def padded_size(num_rays: int, mesh: Mesh) -> int:
    """The smallest multiple of the mesh size that holds ``num_rays`` rays."""
    n = mesh.devices.size
    return -(-int(num_rays) // n) * n


def even_mesh(num_rays: int, mesh: Mesh) -> Mesh:
    """``mesh`` if ``num_rays`` splits evenly over it, else the one-axis mesh over its first ``d``
    devices, ``d`` the largest size that divides ``num_rays`` (1 at worst): results equal the
    whole mesh's, only fewer devices share the work."""
    n = mesh.devices.size
    d = max(k for k in range(1, n + 1) if int(num_rays) % k == 0)
    if d == n:
        return mesh
    return jax.make_mesh((d,), (RAYS,), axis_types=(AxisType.Auto,), devices=list(mesh.devices.flat)[:d])


def shard_rays(fn, mesh: Mesh, num_replicated: int, out_specs=P(RAYS)):
    """``fn(*replicated, *per_ray)`` under ``jax.shard_map`` on ``mesh``: the first ``num_replicated``
    arguments replicated (``P()``), the rest split along their leading (ray) axis; outputs split
    along ``"rays"`` unless ``out_specs`` says otherwise (``P()`` for values reduced inside ``fn``).
    Not jitted here: jit the caller."""

    def wrapped(*args):
        specs = tuple(P() for _ in args[:num_replicated]) + tuple(P(RAYS) for _ in args[num_replicated:])
        # check_vma=False: the renderer's scans carry device-invariant values next to per-ray ones
        return jax.shard_map(fn, mesh=mesh, in_specs=specs, out_specs=out_specs, check_vma=False)(*args)

    return wrapped


def initialize_distributed(coordinator: str, num_processes: int, process_id: int) -> None:
    """``jax.distributed.initialize`` with named errors; call before anything else uses JAX."""
    if not coordinator or ":" not in coordinator:
        raise ValueError(f"--coordinator: expected host:port of process 0, found {coordinator!r}")
    if num_processes < 1 or not 0 <= process_id < num_processes:
        raise ValueError(f"--num-processes/--process-id: expected N >= 1 and 0 <= id < N, found "
                         f"{num_processes} and {process_id}")
    jax.distributed.initialize(coordinator_address=coordinator, num_processes=num_processes, process_id=process_id)
    default_mesh.cache_clear()


__all__ = ["RAYS", "default_mesh", "even_mesh", "initialize_distributed", "padded_size", "ray_mesh", "shard_rays"]

"""Suite-wide settings: one host device per test process, compiled programs freed before a process
runs out of memory mappings, and programs compiled for compile speed (XLA's optimisation level 0,
loop emitters).

Importing ``ne_jax`` changes nothing, so the suite's own process runs on JAX's default of one
CPU device. ``ne_jax.setup()``, which the CLI's ``main()`` and the experiments' entry points call,
would ask for one per usable core; the suite keeps one: ``bash run.sh test`` runs two pytest-xdist
workers on a 2-core machine, so a device per core in each would oversubscribe the cores, and the
tests' tolerances and timings were set on one device. ``NE_JAX_HOST_DEVICES=1`` is set here unless
the environment already sets it: read by the ``ne-jax`` and experiment processes tests start, and
by ``ne_jax.cli.main([...])`` called in this process (which, once JAX has started on one device,
refuses any other count); a count given to JAX itself still wins, which is how the multi-device step
(``XLA_FLAGS=--xla_force_host_platform_device_count=4 pytest -m multidevice tests/devices``) gets
its four devices.

Every XLA:CPU executable holds a few memory mappings of its own, and JAX keeps each one it
compiled for as long as the process lives. A worker that runs hundreds of test files compiles
tens of thousands of programs and reaches the kernel's limit on mappings per process
(``vm.max_map_count``, 65,530 by default); the next compile then crashes the worker (a segfault
or an abort inside ``backend_compile_and_load``). So after a test file that leaves the process
holding more than half that limit, the compiled programs are dropped (:func:`jax.clear_caches`),
which bounds a worker's mappings by half the limit plus one file's. Until then later files reuse
what earlier ones compiled: on ten render/geometry files, 19% fewer compiles than clearing after
every file.

About 70% of the suite's time at XLA's default settings is compiling, much of it making fast code
that then runs for milliseconds. So the tests compile with ``--xla_backend_optimization_level=0``
(XLA's default is 3) and with XLA:CPU's loop emitters instead of its MLIR fusion emitters
(``--xla_cpu_use_fusion_emitters=false``), each added to ``XLA_FLAGS`` unless it already names that
flag: ``XLA_FLAGS="--xla_backend_optimization_level=3 --xla_cpu_use_fusion_emitters=true" bash run.sh
test`` runs the suite as users' programs are compiled (what both flags cost a ``default`` render
and training step: docs/decisions.md). Results agree to the tests' tolerances either
way; comparisons of two programs bit for bit compile both with the same flags.
"""

import gc
import os
from pathlib import Path

import pytest

os.environ.setdefault("NE_JAX_HOST_DEVICES", "1")
_COMPILE_FAST = {"xla_backend_optimization_level": "0", "xla_cpu_use_fusion_emitters": "false"}
for _flag, _value in _COMPILE_FAST.items():
    if _flag not in os.environ.get("XLA_FLAGS", ""):
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + f" --{_flag}={_value}").strip()


def _mappings_near_the_limit() -> bool:
    """Whether this process holds more than half the kernel's memory mappings per process (always
    true where ``/proc`` cannot tell)."""
    try:
        limit = int(Path("/proc/sys/vm/max_map_count").read_text())
        with open("/proc/self/maps", "rb") as maps:
            held = sum(1 for _ in maps)
    except OSError:
        return True
    return held > limit // 2


@pytest.fixture(autouse=True, scope="module")
def _free_compiled_programs():
    """After a test file, when the process holds more than half its allowed memory mappings: drop
    JAX's compiled programs (and the mappings they hold). Until then later files reuse the programs
    earlier ones compiled (the small programs of eager array operations, above all)."""
    yield
    if _mappings_near_the_limit():
        import jax

        jax.clear_caches()
        gc.collect()

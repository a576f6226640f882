"""The test suite runs on one host device unless told otherwise.

``import ne_jax`` gives JAX one host device per usable CPU core (:mod:`ne_jax._platform`). The
suite keeps one: ``bash run.sh test`` runs two pytest-xdist workers on a 2-core machine, so a
device per core in each worker would oversubscribe the cores, and the tests' tolerances and
timings were set on one device. ``NE_JAX_HOST_DEVICES=1`` is set here, before any test module
imports ne_jax or starts JAX (and inherited by the subprocesses tests start), unless the
environment already sets it; a count given to JAX itself still wins, which is how the multi-device
step (``XLA_FLAGS=--xla_force_host_platform_device_count=4 pytest -m multidevice tests/devices``)
gets its four devices.
"""

import os

os.environ.setdefault("NE_JAX_HOST_DEVICES", "1")

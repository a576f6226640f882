"""XLA:CPU's scratch memory stays mapped between calls (``import ne_jax`` sets glibc's ``mallopt``),
``NE_JAX_HOST_MEMORY=system`` opts out, and a bad value names the variable.

glibc's settings hold for the whole process, so the end-to-end check runs fresh Python processes
and count the page faults of a worker thread (as XLA:CPU runs a device's program) that allocates,
touches and frees a 100 MB block again and again: glibc maps such a block afresh every time under
its defaults (a thread's own arena cannot hold it), and reuses it with the memory kept.
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys

import pytest

from ne_jax._host_memory import ENV, requested_policy

_PROBE = """
import json, resource, threading
import numpy as np
import ne_jax
from ne_jax import _host_memory
out = {}
def work():  # like an XLA worker thread: a 100 MB scratch block, allocated, touched and freed per call
    for _ in range(2):
        np.ones(12_500_000)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(5):
        np.ones(12_500_000)
    out["faults_per_call"] = (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / 5
t = threading.Thread(target=work)
t.start()
t.join()
print(json.dumps({"applied": _host_memory._applied, **out}))
"""


def _probe(setting: str) -> dict:
    env = {**os.environ, ENV: setting}
    out = subprocess.run([sys.executable, "-c", _PROBE], env=env, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc's mallopt")
def test_repeated_calls_reuse_their_memory():
    """Page faults per 100 MB block: hundreds under glibc's defaults (a fresh mapping each time; numpy
    asks for huge pages, so not one per 4 KiB), none with the memory kept."""
    kept, system = _probe("keep"), _probe("system")
    assert kept["applied"] is True and system["applied"] is False
    assert system["faults_per_call"] > 40  # the probe exercises what it should (>= 50 huge pages)
    assert kept["faults_per_call"] < 0.05 * system["faults_per_call"]


@pytest.mark.parametrize("env, expected", [({}, "keep"), ({ENV: " Keep "}, "keep"), ({ENV: "system"}, "system"),
                                           ({ENV: ""}, "keep")])
def test_the_policy_from_the_environment(env, expected):
    assert requested_policy(env) == expected


def test_an_unknown_policy_names_the_variable():
    with pytest.raises(ValueError, match=rf"{ENV}: expected 'keep' \(the default\) or 'system', found 'always'"):
        requested_policy({ENV: "always"})

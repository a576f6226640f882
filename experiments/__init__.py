"""Experiments and benchmarks of ``ne_jax``, one module a study.

Run one from the repository root as ``python -m experiments.<name> [args]`` (``--help`` lists its
arguments). Results go to ``experiments/results/``; each records the commit, the config key(s) and
the command that re-runs it. Shared helpers live in :mod:`experiments.common`.

Started that way, an experiment runs with huge pages for XLA's scratch memory, as ``ne-jax`` does
(:mod:`ne_jax._host_memory`): importing ``ne_jax`` first starts the process again with them when it
was started without (``NE_JAX_HOST_MEMORY=system`` keeps glibc's defaults).
"""

import ne_jax  # noqa: F401  (started as `python -m experiments.<name>`, this starts the process again with huge pages)

"""Experiments and benchmarks of ``ne_jax``, one module a study.

Run one from the repository root as ``python -m experiments.<name> [args]`` (``--help`` lists its
arguments). Results go to ``experiments/results/``; each records the commit, the config key(s) and
the command that re-runs it. Shared helpers live in :mod:`experiments.common`.

Each module's entry point (its ``if __name__ == "__main__"`` block, not ``main()``, which tests call
in their own process) sets the process up as ``ne-jax`` does (:func:`experiments.common.entry`,
``ne_jax.setup(huge_pages=True)``): one host device per usable core, and huge pages for XLA's scratch
memory, starting the process again with them when it was started without (``NE_JAX_HOST_MEMORY=system``
keeps glibc's defaults). The speed benchmarks share one test scene and timing loop (``common.bench_cloud``,
``best_time``, ``time_test_render``, ``timed_steps``)."""

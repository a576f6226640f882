"""Experiments and benchmarks of ``ne_jax``, one module a study.

Run one from the repository root as ``python -m experiments.<name> [args]`` (``--help`` lists its
arguments). Results go to ``experiments/results/``; each records the commit, the config key(s) and
the command that re-runs it. Each module's entry point (its ``if __name__ == "__main__"`` block, not
``main()``, which tests call in their own process) sets the process up as ``ne-jax`` does
(:func:`experiments.common.entry`). Shared helpers live in :mod:`experiments.common`."""

"""Experiments and benchmarks of ``ne_jax``, one module a study.

Run one from the repository root as ``python -m experiments.<name> [args]`` (``--help`` lists its
arguments). Results go to ``experiments/results/``; each records the commit, the config key(s) and
the command that re-runs it. Shared helpers live in :mod:`experiments.common`.
"""

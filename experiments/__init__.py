"""Experiments and benchmarks of ``ne_jax``, one module a study.

Run one from the repository root as ``python -m experiments.<name> [args]`` (``--help`` lists its
arguments). Results go to ``experiments/results/``; each records the commit, the config key(s) and
the command that re-runs it. Shared helpers live in :mod:`experiments.common`.

Started that way, an experiment runs with huge pages for XLA's scratch memory, as ``ne-jax`` does
(:mod:`ne_jax._host_memory`): importing this package starts the process again with them when it
was started without (``NE_JAX_HOST_MEMORY=system`` keeps glibc's defaults).
"""

import sys


def module_run(orig_argv: list[str]) -> tuple[str, list[str]] | None:
    """``(module, args)`` when ``orig_argv`` (the interpreter's command line) runs
    ``python [options] -m experiments.<name> [args]``, else ``None`` (imported by a test, a script)."""
    if "-m" not in orig_argv[1:]:
        return None
    i = orig_argv.index("-m", 1)
    if i + 1 >= len(orig_argv) or not orig_argv[i + 1].startswith("experiments."):
        return None
    return orig_argv[i + 1], orig_argv[i + 2:]


_run = module_run(list(getattr(sys, "orig_argv", [])))
if _run is not None:
    from ne_jax._host_memory import reexec_with_huge_pages

    reexec_with_huge_pages(*_run)

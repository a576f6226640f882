"""Where ``experiments/gpu_check.py`` finds :func:`time_steps` (a preset's training step timed on one
cloud), which now lives in :mod:`experiments.common`. The preset-cost study that was here is decided
(docs/decisions.md); remove this module once the GPU check imports from ``experiments.common``."""

from experiments.common import time_steps

__all__ = ["time_steps"]

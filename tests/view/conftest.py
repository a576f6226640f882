"""A tiny trained model for the viewer's tests (the ``browser`` tests, which drive a real headless
Chromium, run only when asked for: ``pytest -m browser``, run.sh's browser step)."""

from __future__ import annotations

import pytest

from ne_jax.benchmark.generate import generate_scene
from ne_jax.train.loop import train

from tests.mini_presets import mini_benchmark, short_run


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory):
    """A run directory of the ``blocks`` benchmark scene (24 px), trained for 4 steps."""
    root = tmp_path_factory.mktemp("view_bench")
    generate_scene("blocks", mini_benchmark(train_views=4), root, seed=0)
    out = tmp_path_factory.mktemp("view_run") / "blocks"
    train(short_run(), root / "blocks", out, progress=False, log=lambda s: None)
    return out

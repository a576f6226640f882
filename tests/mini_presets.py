"""The small settings the tests share: benchmark scenes of a few pixels and views, and a training run
of a few steps on them. A test asks for what it needs with keyword arguments
(``mini_benchmark(resolution=16)``, ``mini_run(epochs=1)``) instead of spelling a preset out.

Import it as ``from tests.mini_presets import ...`` (the suite runs from the repository root).
"""

from __future__ import annotations

import dataclasses

from ne_jax.benchmark.generate import BenchmarkPreset
from ne_jax.geometry.capacity import Capacities
from ne_jax.geometry.kdtree import KDTreeConfig
from ne_jax.pointcloud.rounds import RoundConfig
from ne_jax.render.quadrature import QuadratureConfig
from ne_jax.render.renderer import RenderConfig
from ne_jax.train.run import InitConfig, RunConfig
from ne_jax.train.sampler import SamplerConfig
from ne_jax.train.state import TrainConfig


def mini_benchmark(*, resolution: int = 24, train_views: int = 5, test_views: int = 1, detail: float = 0.4,
                   surface_samples: int = 2000, name: str = "mini") -> BenchmarkPreset:
    """A benchmark preset of a few views: ``resolution`` px, one validation view, no supersampling.
    The defaults (24 px, 5 training views) give a scene a few training steps learn something of."""
    return BenchmarkPreset(name, resolution=resolution, train_views=train_views, val_views=1, test_views=test_views,
                           supersample=1, detail=detail, surface_samples=surface_samples)


TRAIN_SCENE = mini_benchmark()
"""The scene the training tests learn (24 px, 5 training views)."""
GEN_SCENES = mini_benchmark(resolution=16, train_views=3, test_views=2, detail=0.5, surface_samples=400)
"""The scenes the generation tests make and check (16 px, 3 training and 2 test views)."""


def tiny_tree(**changes) -> KDTreeConfig:
    """A small tree for tests and toy scenes (16 candidates, K = 8, 2 rendering levels), with
    ``changes``."""
    return KDTreeConfig(candidate_min=16, knn_k=8, num_render_levels=2).replace(**changes)


def tiny_caps(**changes) -> Capacities:
    """Small buffers for tests and toy scenes (16 frontier and segment slots), with ``changes``."""
    return Capacities(frontier=16, max_segments=16).replace(**changes)


def tiny_render(**changes) -> RenderConfig:
    """A small render config for tests and toy scenes: :func:`tiny_tree`, 4, 6, 8 samples per level,
    chunks of 1024 rays, with ``changes``."""
    return RenderConfig(kdtree=tiny_tree(), quadrature=QuadratureConfig(samples_per_level=(4, 6, 8)),
                        chunk=1024).replace(**changes)


def mini_render(**changes) -> RenderConfig:
    """:func:`tiny_render` with 3, 4, 5 samples per level, and ``changes``."""
    return tiny_render(quadrature=QuadratureConfig(samples_per_level=(3, 4, 5))).replace(**changes)


MINI_CAPS = tiny_caps(max_segments=24)
"""The buffers :func:`mini_run` starts with (16 frontier nodes, 24 segment slots)."""


def mini_init(*, resolution: int = 48, num_points: int = 1500) -> InitConfig:
    """Carving at ``resolution`` voxels a side, keeping ``num_points`` points (an SfM start as many)."""
    return InitConfig(carve=dataclasses.replace(InitConfig().carve, resolution=resolution, num_points=num_points),
                      sfm_points=num_points)


def mini_run(**changes) -> RunConfig:
    """A training run of 3 epochs x 3 steps of 128 rays on :func:`mini_render`, point-cloud rounds
    after epochs 1 and 2, with ``changes`` (:meth:`RunConfig.replace`)."""
    run = RunConfig(name="test", render=mini_render(), capacities=MINI_CAPS, sampler=SamplerConfig(batch_size=128),
                    train=TrainConfig(lr=5e-3), init=mini_init(),
                    rounds=RoundConfig(grow_rays=256, grow_chunk=128, outlier_neighbors=16),
                    epochs=3, steps_per_epoch=3, round_epochs=(1, 2))
    return run.replace(**changes)


def short_run(**changes) -> RunConfig:
    """:func:`mini_run` for one epoch of 4 steps, no point-cloud round, coarser carving (a model to
    evaluate or edit, trained in seconds)."""
    return mini_run(init=mini_init(resolution=40, num_points=1200), epochs=1, steps_per_epoch=4,
                    round_epochs=(1, 0)).replace(**changes)


__all__ = ["GEN_SCENES", "MINI_CAPS", "TRAIN_SCENE", "mini_benchmark", "mini_init", "mini_render", "mini_run",
           "short_run", "tiny_caps", "tiny_render", "tiny_tree"]

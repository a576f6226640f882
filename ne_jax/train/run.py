"""The run config: everything a training run needs, its named presets (one registry), and reading
it back from a run directory's ``config.json``."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from ne_jax.config_json import BUFFER_SIZES, ConfigError, config_from_json
from ne_jax.geometry.capacity import Capacities
from ne_jax.geometry.kdtree import KDTreeConfig
from ne_jax.pointcloud.init import (
    CarveConfig,
)
from ne_jax.pointcloud.normals import NormalConfig
from ne_jax.pointcloud.rounds import RoundConfig
from ne_jax.render.quadrature import QuadratureConfig
from ne_jax.render.renderer import RenderConfig
from ne_jax.train.sampler import SamplerConfig
from ne_jax.train.state import TrainConfig

INIT_SOURCES = ("auto", "carving", "sfm", "ply", "ground_truth")
CONFIG_FILE = "config.json"


INIT_CAPACITY_HEADROOM = 1.5
"""A run's initial point capacity is ``ceil(N * INIT_CAPACITY_HEADROOM)`` for ``N`` initial points:
room for growth before a re-allocation."""


@dataclasses.dataclass(frozen=True)
class InitConfig:
    """Where the initial cloud comes from (hashable)."""

    source: str = "auto"
    """``"auto"`` (the capture's SfM points where the scene folder has them, else carving where the
    images have alpha masks; the run records which and why), ``"carving"`` (visual hull of the
    training masks), ``"sfm"`` (the capture's structure-from-motion points, cleaned and densified:
    :mod:`ne_jax.pointcloud.sfm_init`), ``"ply"`` (``ply_path``), or ``"ground_truth"`` (the
    benchmark's surface samples: only when asked for; results are labelled)."""
    ply_path: str | None = None
    """The user's PLY for ``source="ply"``."""
    carve: CarveConfig = CarveConfig(bounds=((-1.1,) * 3, (1.1,) * 3), resolution=128, num_points=20_000)
    """Carving settings (the benchmark's objects lie in ``[-1, 1]^3``, and a capture is brought there:
    :mod:`ne_jax.data.scene`)."""
    sfm_points: int = 100_000
    """The size a sparse SfM start (``source="sfm"``) is densified to. A capture spreads its points over
    the ground and the objects, so it starts denser than a carving (docs/decisions.md, the capture
    variant's start)."""
    def __post_init__(self):
        if self.source not in INIT_SOURCES:
            raise ValueError(f"InitConfig.source: expected one of {INIT_SOURCES}, found {self.source!r}")
        if int(self.sfm_points) < 1:
            raise ValueError(f"InitConfig.sfm_points: expected an integer >= 1, found {self.sfm_points}")
        if self.source == "ply" and not self.ply_path:
            raise ValueError("InitConfig.ply_path: expected a PLY file for source='ply', found None")


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """Everything a training run needs (hashable, saved as ``config.json``). Presets :meth:`tiny`,
    :meth:`default`, :meth:`paper`; change a preset with :meth:`replace` / :meth:`with_schedule`.

    The learning-rate schedule's cosine decay always spans the run: its length is
    :attr:`total_steps` (``epochs * steps_per_epoch``), not a setting of its own."""

    name: str = "custom"
    """Preset name (informational; a config built by hand is ``"custom"``, not the ``default`` preset)."""
    render: RenderConfig = RenderConfig()
    train: TrainConfig = TrainConfig()
    sampler: SamplerConfig = SamplerConfig()
    rounds: RoundConfig = RoundConfig()
    """The point-cloud round: grow, prune, denoise (:mod:`ne_jax.pointcloud.rounds`)."""
    normals: NormalConfig = NormalConfig()
    init: InitConfig = InitConfig()
    epochs: int = 16
    steps_per_epoch: int = 1000
    round_epochs: tuple[int, int] = (4, 12)
    """A point-cloud round follows epochs ``first .. last`` (1-based, inclusive; docs/design.md: 4-12)."""
    downscale: int = 1
    """Images are read downscaled by this integer factor (area average; intrinsics divided): every
    command on the run reads its scene at this resolution."""
    background: str = "white"
    """The colour behind the object in training and evaluation (``"white"``, ``"black"``)."""
    seed: int = 0
    capacities: Capacities = dataclasses.field(default=Capacities(), metadata={BUFFER_SIZES: True})
    """The buffer sizes the run starts with (traversal frontier and slots, packing budget): not a
    setting, so not in the run's key; grown when a batch loses segments, and the sizes in use are
    saved with each checkpoint (``metrics.json``: ``capacities`` per epoch)."""

    def __post_init__(self):
        if int(self.epochs) < 1 or int(self.steps_per_epoch) < 1:
            raise ValueError(f"RunConfig: expected epochs >= 1 and steps_per_epoch >= 1, found "
                             f"{self.epochs} and {self.steps_per_epoch}")
        if isinstance(self.downscale, bool) or int(self.downscale) != self.downscale or self.downscale < 1:
            raise ValueError(f"RunConfig.downscale: expected an integer >= 1, found {self.downscale!r}")
        a, b = self.round_epochs
        if not 1 <= a <= b + 1:
            raise ValueError("RunConfig.round_epochs: expected (first, last) with 1 <= first <= last + 1, "
                             f"found {self.round_epochs}")

    def replace(self, **changes) -> RunConfig:
        """This config with ``changes``."""
        return dataclasses.replace(self, **changes)

    def with_schedule(self, epochs: int | None = None, steps_per_epoch: int | None = None) -> RunConfig:
        """Change the length of the run (``None``: keep); the cosine decay spans the new length."""
        epochs = self.epochs if epochs is None else int(epochs)
        steps = self.steps_per_epoch if steps_per_epoch is None else int(steps_per_epoch)
        return dataclasses.replace(self, epochs=epochs, steps_per_epoch=steps)

    @property
    def total_steps(self) -> int:
        """Steps of the whole run: ``epochs * steps_per_epoch``, the length of the learning-rate
        schedule (:meth:`~ne_jax.train.state.TrainConfig.schedule`)."""
        return self.epochs * self.steps_per_epoch

    @property
    def train_render(self) -> RenderConfig:
        """The render config of the training step and its batches: :attr:`render` (what images are
        rendered with) on the training batches' grid, ``sampler.pixel_samples``."""
        return self.render.replace(pixel_samples=int(self.sampler.pixel_samples))

    def round_after(self, epoch: int) -> bool:
        """Whether a point-cloud round follows epoch ``epoch`` (1-based); never after the last."""
        a, b = self.round_epochs
        return a <= epoch <= b and epoch < self.epochs

    @classmethod
    def tiny(cls, **changes) -> RunConfig:
        """The demo: 64 px tiny benchmark scenes, minutes per model on one CPU core. K = 16 of 16
        candidates, s = 2, 3, 4 and 6 x 125 steps (the accuracy-vs-time study's pick). A pixel is the
        mean of 2 x 2 rays in training and in images, as the benchmark's ground truth is area-averaged;
        the density gate with confidences learning at ten times the rate, and denoising that spares
        confident points (docs/decisions.md)."""
        render = RenderConfig(kdtree=KDTreeConfig(candidate_min=16, knn_k=16, num_render_levels=2, density_falloff=1.0),
                              quadrature=QuadratureConfig(samples_per_level=(2, 3, 4)), chunk=1024,
                              pixel_samples=2)
        base = cls(name="tiny", render=render, capacities=Capacities(frontier=32, max_segments=32),
                   sampler=SamplerConfig(batch_size=1024, pixel_samples=2),
                   train=TrainConfig(lr=5e-3, confidence_lr=10.0),
                   rounds=RoundConfig(grow_rays=4096, outlier_keep_confidence=0.5),
                   epochs=6, steps_per_epoch=125, round_epochs=(2, 4))
        return base.replace(**changes)

    @classmethod
    def default(cls, **changes) -> RunConfig:
        """The benchmark's ``default`` preset (200 px scenes), sized to train in about an hour on one
        CPU core: K = 16 of 32 candidates, 2 rendering levels, s = 4, 6, 8. The tree is walked in two
        passes, 16 nodes wide and then 64 for at most a quarter of the rays (the same model as one
        64-wide pass, in less time); the boxes' margins are 1.5x the tree's default, so rays do not
        pass between the boxes of a sparse part of the surface. It trains on pixel centres and renders
        its images with 2 x 2 rays per pixel (docs/decisions.md, docs/rendering.md)."""
        render = RenderConfig(kdtree=KDTreeConfig(knn_k=16, candidate_min=32, num_render_levels=2, margin_factor=1.5),
                              quadrature=QuadratureConfig(samples_per_level=(4, 6, 8)), pixel_samples=2)
        base = cls(name="default", render=render, capacities=Capacities(first_pass_frontier=16, retry_share=0.25),
                   init=InitConfig(carve=dataclasses.replace(InitConfig().carve, num_points=100_000)),
                   sampler=SamplerConfig(batch_size=2048, pixel_samples=1), train=TrainConfig(lr=5e-3),
                   epochs=12, steps_per_epoch=500, round_epochs=(3, 9))
        return base.replace(**changes)

    @classmethod
    def paper(cls, **changes) -> RunConfig:
        """The paper's settings: 4096 rays per batch, the fixed 21-level tree, lr 2e-3, rounds after
        epochs 4-12 (a GPU-sized run); 64 segment slots a ray, as a ray meets more, smaller voxels at
        21 levels. The growth scan walks 128 rays a call: its memory grows with the slots and samples
        a ray holds (docs/devices.md)."""
        base = cls(name="paper", render=RenderConfig(kdtree=KDTreeConfig(depth=21)),
                   capacities=Capacities(max_segments=64),
                   init=InitConfig(carve=dataclasses.replace(InitConfig().carve, resolution=256, num_points=300_000),
                                   sfm_points=300_000),
                   sampler=SamplerConfig(batch_size=4096), train=TrainConfig(lr=2e-3),
                   rounds=RoundConfig(grow_chunk=128), epochs=16, steps_per_epoch=5000, round_epochs=(4, 12))
        return base.replace(**changes)


PRESETS = {"tiny": RunConfig.tiny, "default": RunConfig.default, "paper": RunConfig.paper}


def get_run_preset(name: str) -> RunConfig:
    if name not in PRESETS:
        raise KeyError(f"unknown training preset {name!r}; expected one of {sorted(PRESETS)}")
    return PRESETS[name]()


def load_run_config(path: str | Path) -> RunConfig:
    """A :class:`RunConfig` from a run directory's ``config.json`` (or the file itself)."""
    path = Path(path)
    file = path / CONFIG_FILE if path.is_dir() else path
    if not file.is_file():
        raise FileNotFoundError(f"{file}: expected a run config (config.json of a training run), found nothing")
    try:
        cfg = config_from_json(json.loads(file.read_text(encoding="utf-8")))
    except (json.JSONDecodeError, UnicodeDecodeError, TypeError, ConfigError) as e:
        raise ValueError(f"{file}: expected a RunConfig in JSON, found unreadable data ({e})") from None
    if not isinstance(cfg, RunConfig):
        raise ValueError(f"{file}: expected a RunConfig, found {type(cfg).__name__}")
    return cfg


__all__ = ["CONFIG_FILE", "INIT_SOURCES", "PRESETS", "InitConfig", "RunConfig", "get_run_preset", "load_run_config"]

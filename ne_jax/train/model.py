"""A trained model as one object (:class:`TrainedModel`), and its run directory on disk.

A run directory holds::

    run_dir/
        config.json      the resolved RunConfig (typed; :func:`~ne_jax.train.run.load_run_config`)
        metrics.json     the scene folder, the initial cloud's provenance and one record per epoch
        scene_record.json  the scene's layout, splits, normalisation and near/far (SCENE_RECORD_FILE)
        checkpoints/     ckpt_<step>/ and latest (see :mod:`ne_jax.train.checkpoint`)
        tree_rest.npz    only for an edited model whose K-D tree is carried (:data:`REST_FILE`)
"""

from __future__ import annotations

import dataclasses
import io
import json
import math
from pathlib import Path

import numpy as np

from ne_jax.atomic import atomic_directory, atomic_write_bytes, atomic_write_text
from ne_jax.config_json import config_to_json
from ne_jax.data.nerf_synthetic import parse_background
from ne_jax.data.rays import Camera
from ne_jax.data.scene import SCENE_RECORD_FILE, Normalisation
from ne_jax.geometry.capacity import Capacities
from ne_jax.geometry.points import PointState
from ne_jax.render.driver import render_image
from ne_jax.render.renderer import PointScene, RenderConfig, RenderOut
from ne_jax.train.checkpoint import load_checkpoint, save_checkpoint
from ne_jax.train.run import CONFIG_FILE, RunConfig, load_run_config
from ne_jax.train.state import TrainState

METRICS_FILE = "metrics.json"
CHECKPOINT_DIR = "checkpoints"
REST_FILE = "tree_rest.npz"
"""In a run directory whose K-D tree is carried through an edit: the positions and mask the tree was
built on (``xyz``, ``alive``), from which :func:`load_trained` carries it again."""


def _write_rest(run_dir: Path, scene: PointScene) -> None:
    """Record where ``scene``'s tree was built (a carried tree only; otherwise remove the record)."""
    path = Path(run_dir) / REST_FILE
    if scene.rest_xyz is None:
        path.unlink(missing_ok=True)
        return
    buf = io.BytesIO()
    np.savez(buf, xyz=np.asarray(scene.rest_xyz), alive=np.asarray(scene.rest_alive))
    atomic_write_bytes(path, buf.getvalue())


def _scene_of(points: PointState, render: RenderConfig, run_dir: Path, capacities: Capacities) -> PointScene:
    """The scene of ``points``: the tree carried from the run directory's rest record when it has one
    (an edited model), else built."""
    path = Path(run_dir) / REST_FILE
    if not path.is_file():
        return PointScene.build(points, render, capacities)
    with np.load(path) as rest:
        return PointScene.carried(rest["xyz"], rest["alive"], points, render, capacities)


def saved_capacities(meta: dict, start: Capacities) -> Capacities:
    """The capacities a checkpoint was saved with (its ``extra``), else ``start``; a checkpoint that
    recorded only its packing budget gets ``start`` with that budget."""
    extra = meta.get("extra", {})
    if "capacities" in extra:
        return Capacities(**extra["capacities"])
    if extra.get("segments_per_ray") is not None:
        return start.replace(segments_per_ray=extra["segments_per_ray"])
    return start


def _json_safe(x):
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_safe(v) for v in x]
    return x


@dataclasses.dataclass(frozen=True)
class TrainedModel:
    """A trained (or edited) model as one object: the run config (render, train and sampler configs,
    background, near/far), the train state (MLP parameters and the point cloud), the point scene
    (the cloud with its K-D tree), and where it came from. :func:`~ne_jax.train.loop.train` returns
    one, :func:`load_trained` reads one from a run directory, :func:`save_trained` writes one.

    ``scene_dir``: the scene folder it was trained on (or the edited scene's ground truth; ``None``
    when unknown); ``run_dir``: its run directory (``None`` for a model only in memory);
    ``history``: one record per epoch (as in ``metrics.json``); ``initial``: the initial cloud's
    provenance; ``meta``: the checkpoint's metadata; ``frame``: the similarity from the capture's
    coordinates to the model's (:mod:`ne_jax.data.scene`; identity for a NeRF Synthetic scene), which
    exported clouds and edit files are converted through."""

    run: RunConfig
    state: TrainState
    scene: PointScene
    scene_dir: Path | None = None
    run_dir: Path | None = None
    history: list = dataclasses.field(default_factory=list)
    initial: dict = dataclasses.field(default_factory=dict)
    meta: dict = dataclasses.field(default_factory=dict)
    frame: Normalisation = Normalisation()

    @property
    def params(self):
        """The colour model's parameters (a pytree)."""
        return self.state.params

    @property
    def near(self) -> float:
        return self.run.sampler.near

    @property
    def far(self) -> float:
        return self.run.sampler.far

    @property
    def background(self):
        return self.run.background

    def _timed_parts(self) -> list[tuple[float, float | None]]:
        """``(wall s, CPU s or None)`` of each part the loop timed: the initial cloud (none for a run
        started from a model), every epoch with its compiles, every point-cloud round."""
        parts = [(self.initial["seconds"], self.initial.get("cpu_seconds"))] if "seconds" in self.initial else []
        for e in self.history:
            parts.append((e.get("train_seconds", 0.0), e.get("train_cpu_seconds")))
            if "points" in e:
                parts.append((e["points"].get("seconds", 0.0), e["points"].get("cpu_seconds")))
        return parts

    @property
    def recorded_seconds(self) -> float:
        """Training wall time as the loop recorded it (initial cloud, epochs with their compiles,
        point-cloud rounds), summed over every session of a resumed run."""
        return float(sum(wall for wall, _ in self._timed_parts()))

    @property
    def recorded_cpu_seconds(self) -> float | None:
        """The process's CPU time (all its threads) over the same parts as :attr:`recorded_seconds`,
        summed over every session of a resumed run; None if a part was recorded without it."""
        cpu = [c for _, c in self._timed_parts()]
        return None if None in cpu else float(sum(cpu))

    def render_image(self, camera: Camera, *, progress: bool = False) -> RenderOut:
        """Render one camera's image (see :func:`~ne_jax.render.driver.render_image`)."""
        return render_image(self.run.render, self.params, self.scene, camera, parse_background(self.background),
                            self.near, self.far, progress=progress)

    def replace(self, **changes) -> TrainedModel:
        return dataclasses.replace(self, **changes)


def load_trained(run_dir: str | Path) -> TrainedModel:
    """The latest checkpoint of a run directory written by :func:`train`, with its config and the
    K-D tree rebuilt (or carried, for an edited model: :data:`REST_FILE`). ``scene_dir``,
    ``history`` and ``initial`` are read from ``metrics.json`` (``None``/empty if absent). Raises
    ``FileNotFoundError`` / :class:`CheckpointError` naming what is missing or wrong."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise FileNotFoundError(f"{run_dir}: expected a training run directory (from `ne-jax train`), found nothing")
    run = load_run_config(run_dir)
    state, points, meta = load_checkpoint(run_dir / CHECKPOINT_DIR, run.train, run.render)
    file = run_dir / METRICS_FILE
    metrics = json.loads(file.read_text(encoding="utf-8")) if file.is_file() else {}
    scene_dir = Path(metrics["scene_dir"]) if metrics.get("scene_dir") else None
    scene = _scene_of(points, run.render, run_dir, saved_capacities(meta, run.capacities))
    return TrainedModel(run=run, state=state, scene=scene, scene_dir=scene_dir,
                        run_dir=run_dir, history=list(metrics.get("epochs", [])),
                        initial=dict(metrics.get("initial_cloud", {})), meta=meta, frame=read_frame(run_dir))


def read_frame(run_dir: str | Path) -> Normalisation:
    """The capture-to-model similarity a run directory records (:data:`SCENE_RECORD_FILE`);
    identity when it records none (a NeRF Synthetic scene, or a run of an earlier version)."""
    file = Path(run_dir) / SCENE_RECORD_FILE
    if not file.is_file():
        return Normalisation()
    record = json.loads(file.read_text(encoding="utf-8"))
    return Normalisation.from_dict(record["normalisation"]) if "normalisation" in record else Normalisation()


def save_trained(model: TrainedModel, run_dir: str | Path, metrics: dict | None = None,
                 extra: dict | None = None) -> Path:
    """Write ``model`` as a run directory that :func:`load_trained` reads (``config.json``,
    ``metrics.json`` — ``metrics`` plus the model's ``scene_dir`` — and one checkpoint with ``extra``),
    atomically: the directory appears complete or not at all."""
    metrics = {"scene_dir": str(Path(model.scene_dir).resolve()) if model.scene_dir is not None else None,
               **(metrics or {})}
    points = model.state.point_state(model.scene.points)
    with atomic_directory(run_dir) as tmp:
        atomic_write_text(tmp / CONFIG_FILE, json.dumps(config_to_json(model.run), indent=2) + "\n")
        atomic_write_text(tmp / METRICS_FILE, json.dumps(_json_safe(metrics), indent=2, allow_nan=False) + "\n")
        extra = {"capacities": dataclasses.asdict(model.scene.capacities), **(extra or {})}
        save_checkpoint(tmp / CHECKPOINT_DIR, model.state, points, model.run.train, model.run.render,
                        extra=extra, keep=1)
        _write_rest(tmp, model.scene)
        frame = {"normalisation": model.frame.as_dict()}
        atomic_write_text(tmp / SCENE_RECORD_FILE, json.dumps(frame, indent=2) + "\n")
    return Path(run_dir)


__all__ = ["CHECKPOINT_DIR", "METRICS_FILE", "REST_FILE", "TrainedModel", "load_trained", "save_trained"]

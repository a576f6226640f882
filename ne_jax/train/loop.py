"""The training run: initial cloud, epochs of jitted steps, point-cloud optimisation between
epochs, checkpoints, and a run directory a person can read.

``result = train(RunConfig.tiny(), scene_dir, run_dir)``. A run directory holds::

    run_dir/
        config.json      the resolved RunConfig (typed; ``load_run_config`` reads it back)
        metrics.json     the initial cloud's provenance and one record per epoch (losses, PSNR,
                         skipped steps, segments lost, compilations, point-cloud report, seconds)
        checkpoints/     ckpt_<step>/ and latest (see :mod:`ne_jax.train.checkpoint`)

Exact resume: the batch of step ``i`` is drawn with ``fold_in(batch_key, i)`` and the rays of a
point-cloud round with ``fold_in(points_key, epoch)``, so a run resumed from the checkpoint written
at the end of an epoch continues bit for bit as if it had never stopped (tested: 2 + 2 epochs equal
4). The step compiles once per shape: within an epoch nothing recompiles; a round that changes the
capacity or the tree depth compiles the step once more (counted in ``metrics.json``).
"""

from __future__ import annotations

import dataclasses
import functools
import io
import json
import math
import shutil
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from ne_jax.atomic import atomic_directory, atomic_write_bytes, atomic_write_text
from ne_jax.compiles import count_compiles
from ne_jax.config_json import ConfigError, config_diff, config_from_json, config_to_json
from ne_jax.data.nerf_synthetic import SceneSplit, load_split
from ne_jax.geometry.intersect import intersect
from ne_jax.geometry.kdtree import KDTreeConfig
from ne_jax.geometry.points import PointState
from ne_jax.pointcloud.init import (
    CarveConfig,
    InitialCloud,
    Views,
    carve_visual_hull,
    ground_truth_cloud,
    load_ply_cloud,
)
from ne_jax.pointcloud.normals import NormalConfig, estimate_normals
from ne_jax.pointcloud.optimise import PointOptConfig, optimise_points
from ne_jax.render.quadrature import QuadratureConfig
from ne_jax.render.renderer import PointScene, RenderConfig
from ne_jax.train.checkpoint import CheckpointError, latest_checkpoint, load_checkpoint, save_checkpoint
from ne_jax.train.sampler import SamplerConfig, build_pool, sample_batch
from ne_jax.train.state import TrainConfig, TrainState, init_train_state
from ne_jax.train.step import make_train_step

INIT_SOURCES = ("carving", "ply", "ground_truth")
CONFIG_FILE = "config.json"
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


def _scene_of(points: PointState, render: RenderConfig, run_dir: Path) -> PointScene:
    """The scene of ``points``: the tree carried from the run directory's rest record when it has one
    (an edited model), else built."""
    path = Path(run_dir) / REST_FILE
    if not path.is_file():
        return PointScene.build(points, render)
    with np.load(path) as rest:
        return PointScene.carried(rest["xyz"], rest["alive"], points, render)

# The jitted step per (train config, packing budget), shared by the train() calls of one process: a
# second run of the same configs (a notebook cell run again, a resume) compiles nothing new.
_train_step = functools.lru_cache(maxsize=8)(make_train_step)


@dataclasses.dataclass(frozen=True)
class InitConfig:
    """Where the initial cloud comes from (hashable)."""

    source: str = "carving"
    """``"carving"`` (visual hull of the training masks), ``"ply"`` (``ply_path``), or
    ``"ground_truth"`` (the benchmark's surface samples: only when asked for; results are labelled)."""
    ply_path: str | None = None
    """The user's PLY for ``source="ply"``."""
    carve: CarveConfig = CarveConfig(bounds=((-1.1,) * 3, (1.1,) * 3), resolution=128, num_points=20_000)
    """Carving settings (the benchmark's objects lie in ``[-1, 1]^3``)."""
    capacity_headroom: float = 1.5
    """Initial capacity ``ceil(N * headroom)``: room for growth before a re-allocation."""

    def __post_init__(self):
        if self.source not in INIT_SOURCES:
            raise ValueError(f"InitConfig.source: expected one of {INIT_SOURCES}, found {self.source!r}")
        if self.source == "ply" and not self.ply_path:
            raise ValueError("InitConfig.ply_path: expected a PLY file for source='ply', found None")
        if not self.capacity_headroom >= 1:
            raise ValueError(f"InitConfig.capacity_headroom: expected >= 1, found {self.capacity_headroom}")


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """Everything a training run needs (hashable, saved as ``config.json``). Presets :meth:`tiny`,
    :meth:`default`, :meth:`paper`; change a preset with :meth:`replace` / :meth:`with_schedule`.

    The learning-rate schedule (``train.total_steps``) of a preset spans the run
    (``epochs * steps_per_epoch``), and keeps spanning it however the length is changed: the preset's
    keyword arguments, :meth:`replace` and :meth:`with_schedule` all re-fit it. A schedule of another
    length is kept only when asked for: ``replace(train=...)`` with another ``total_steps``, or a
    config built with one (``RunConfig(...)`` without :meth:`with_schedule`)."""

    name: str = "default"
    """Preset name (informational)."""
    render: RenderConfig = RenderConfig()
    train: TrainConfig = TrainConfig()
    sampler: SamplerConfig = SamplerConfig()
    points: PointOptConfig = PointOptConfig()
    normals: NormalConfig = NormalConfig()
    init: InitConfig = InitConfig()
    epochs: int = 16
    steps_per_epoch: int = 1000
    point_rounds: tuple[int, int] = (4, 12)
    """The cloud is optimised after epochs ``first .. last`` (1-based, inclusive; docs/design.md: 4-12)."""
    background: str = "white"
    """The colour behind the object in training and evaluation (``"white"``, ``"black"``)."""
    seed: int = 0
    checkpoint_keep: int = 3
    log_every: int = 25
    """Steps between progress-bar updates (each reads the metrics back from the device)."""

    def __post_init__(self):
        if int(self.epochs) < 1 or int(self.steps_per_epoch) < 1:
            raise ValueError(f"RunConfig: expected epochs >= 1 and steps_per_epoch >= 1, found "
                             f"{self.epochs} and {self.steps_per_epoch}")
        a, b = self.point_rounds
        if not 1 <= a <= b + 1:
            raise ValueError("RunConfig.point_rounds: expected (first, last) with 1 <= first <= last + 1, "
                             f"found {self.point_rounds}")

    def replace(self, **changes) -> RunConfig:
        """This config with ``changes``; a schedule that spans the run (:attr:`schedule_spans_run`)
        is re-fitted to a new ``epochs`` / ``steps_per_epoch``, unless ``changes`` give a ``train``
        with another ``total_steps`` (then that one is kept)."""
        new = dataclasses.replace(self, **changes)
        explicit = "train" in changes and changes["train"].total_steps != self.train.total_steps
        if self.schedule_spans_run and not explicit and not new.schedule_spans_run:
            new = dataclasses.replace(new, train=new.train.replace(total_steps=new.total_steps))
        return new

    def with_schedule(self, epochs: int | None = None, steps_per_epoch: int | None = None) -> RunConfig:
        """Change the length of the run (``None``: keep); the cosine decay spans the new length
        (also when it did not span the old one)."""
        epochs = self.epochs if epochs is None else int(epochs)
        steps = self.steps_per_epoch if steps_per_epoch is None else int(steps_per_epoch)
        return dataclasses.replace(self, epochs=epochs, steps_per_epoch=steps,
                                   train=self.train.replace(total_steps=epochs * steps))

    @property
    def total_steps(self) -> int:
        """Steps of the whole run: ``epochs * steps_per_epoch``."""
        return self.epochs * self.steps_per_epoch

    @property
    def schedule_spans_run(self) -> bool:
        """Whether the learning-rate schedule decays over exactly the run's :attr:`total_steps`."""
        return int(self.train.total_steps) == self.total_steps

    def optimises_points_after(self, epoch: int) -> bool:
        """Whether a point-cloud round follows epoch ``epoch`` (1-based); never after the last."""
        a, b = self.point_rounds
        return a <= epoch <= b and epoch < self.epochs

    @classmethod
    def tiny(cls, **changes) -> RunConfig:
        """The demo: 64 px tiny benchmark scenes, about 2.5 minutes per model on one CPU core. K = 16
        of 16 candidates, s = 2, 3 and 6 x 125 steps: the pick of the accuracy-vs-time training study
        over the four benchmark scenes (docs/studies/accuracy_vs_time.md, part 3)."""
        render = RenderConfig.tiny(tree=KDTreeConfig.tiny(max_segments=32, frontier_capacity=32, knn_k=16),
                                   quadrature=QuadratureConfig(samples_per_level=(2, 3, 4)))
        base = cls(name="tiny", render=render, sampler=SamplerConfig(batch_size=1024),
                   train=TrainConfig(lr=5e-3), points=PointOptConfig(grow_rays=4096),
                   epochs=6, steps_per_epoch=125, point_rounds=(2, 4))
        return base.with_schedule().replace(**changes)

    @classmethod
    def default(cls, **changes) -> RunConfig:
        """The benchmark's ``default`` preset (200 px scenes), sized to train in about an hour on one
        CPU core: K = 16 of 32 candidates, 2 rendering levels, s = 4, 6 (the paper's per-sample
        settings, :meth:`RenderConfig.default`, cost about 4x the time per step; see
        docs/studies/accuracy_vs_time.md). The tree is walked in two passes, 16 nodes wide and then
        64 for at most a quarter of the rays: on the benchmark's glossy scene this trains the same model bit for
        bit as one 64-wide pass, in 0.885x the time."""
        render = RenderConfig.default(tree=KDTreeConfig.default(knn_k=16, candidate_min=32, num_render_levels=2,
                                                                first_pass_frontier=16, retry_share=0.25),
                                      quadrature=QuadratureConfig(samples_per_level=(4, 6, 8)))
        base = cls(name="default", render=render,
                   init=InitConfig(carve=dataclasses.replace(InitConfig().carve, num_points=100_000)),
                   sampler=SamplerConfig(batch_size=2048), train=TrainConfig(lr=5e-3),
                   epochs=12, steps_per_epoch=500, point_rounds=(3, 9))
        return base.with_schedule().replace(**changes)

    @classmethod
    def paper(cls, **changes) -> RunConfig:
        """The paper's settings: 4096 rays per batch, the fixed 21-level tree, lr 2e-3, rounds after
        epochs 4-12 (a GPU-sized run)."""
        base = cls(name="paper", render=RenderConfig.paper(quadrature=QuadratureConfig()),
                   init=InitConfig(carve=dataclasses.replace(InitConfig().carve, resolution=256, num_points=300_000)),
                   sampler=SamplerConfig(batch_size=4096), train=TrainConfig(lr=2e-3),
                   epochs=16, steps_per_epoch=5000, point_rounds=(4, 12))
        return base.with_schedule().replace(**changes)


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


# ---------------------------------------------------------------- the initial cloud


def initial_cloud(cfg: InitConfig, scene_dir: Path, views: Views) -> InitialCloud:
    """The run's initial cloud (see :class:`InitConfig`); carving with one view uses ``min_views=1``."""
    if cfg.source == "ply":
        return load_ply_cloud(cfg.ply_path)
    if cfg.source == "ground_truth":
        return ground_truth_cloud(scene_dir)
    carve = cfg.carve
    if views.num_views < carve.min_views:
        warnings.warn(f"carving: {views.num_views} training view(s) < min_views={carve.min_views}; "
                      f"carving with min_views={views.num_views}", stacklevel=2)
        carve = dataclasses.replace(carve, min_views=views.num_views)
    return carve_visual_hull(carve, views)


def initial_points(run: RunConfig, cloud: InitialCloud, views: Views, key: jax.Array) -> PointState:
    """The cloud as a :class:`PointState` with Open3D normals, random features, confidence 0.5 and
    capacity ``ceil(N * headroom)``."""
    normals = estimate_normals(run.normals, cloud.xyz, views)
    capacity = max(int(math.ceil(len(cloud) * run.init.capacity_headroom)), 1)
    return PointState.from_numpy(cloud.xyz, capacity, run.render.shading.feature_dim, normal=normals, key=key)


# ---------------------------------------------------------------- the run


@dataclasses.dataclass
class TrainResult:
    """What :func:`train` returns: the final state, cloud and scene (tree built), the per-epoch
    history (as in ``metrics.json``), the run directory and the run's config."""

    state: TrainState
    scene: PointScene
    history: list
    run_dir: Path
    initial: dict
    run: RunConfig | None = None

    @property
    def recorded_seconds(self) -> float:
        """Training wall time as the loop recorded it (initial cloud, epochs with their compiles,
        point-cloud rounds), summed over every session of a resumed run."""
        s = float(self.initial.get("seconds", 0.0))
        for e in self.history:
            s += float(e.get("train_seconds", 0.0)) + float(e.get("points", {}).get("seconds", 0.0))
        return s


@dataclasses.dataclass
class StartFrom:
    """Start a run from a model instead of an initial cloud (fine-tuning): the colour model's
    ``params``, the ``points`` (features, confidences, ISTs) and a ``note`` recorded in
    ``metrics.json`` as the run's ``initial_cloud``. The optimiser starts afresh."""

    params: dict
    points: PointState
    note: dict
    scene: PointScene | None = None
    """The model's scene, when its tree is carried through an edit (kept until a point-cloud round
    rebuilds it); ``None``: the tree is built on ``points``."""


class TrainingDiverged(RuntimeError):
    """Every step of an epoch was refused for non-finite values; the message names the terms."""


def _keys(seed: int):
    base = jax.random.key(seed)
    k_points, k_model, k_batch, k_rounds = jax.random.split(base, 4)
    return k_points, k_model, k_batch, k_rounds


def _epoch_summary(metrics: list[dict]) -> dict:
    host = jax.device_get(metrics)
    ok = np.array([bool(m["ok"]) for m in host])
    out = {"steps": int(ok.size), "skipped": int((~ok).sum())}
    for k in host[0]:
        if k.startswith("loss/") or k in ("psnr", "grad_norm", "opacity"):
            vals = np.array([float(m[k]) for m, good in zip(host, ok) if good])
            out[k] = float(vals.mean()) if vals.size else float("nan")
    out["lr_last"] = float(host[-1]["lr"])
    out["overflow"] = int(sum(int(m["overflow"]) for m in host))
    out["dropped"] = int(sum(int(m["dropped"]) for m in host))
    bad = sorted({k.split("/", 1)[1] for m in host for k, v in m.items() if k.startswith("finite/") and not bool(v)})
    if bad:
        out["non_finite"] = bad
    return out


def _json_safe(x):
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_safe(v) for v in x]
    return x


def _write_metrics(run_dir: Path, scene_dir: Path, initial: dict, history: list) -> None:
    data = {"scene_dir": str(scene_dir.resolve()), "initial_cloud": initial, "epochs": history}
    atomic_write_text(run_dir / METRICS_FILE, json.dumps(_json_safe(data), indent=2, allow_nan=False) + "\n")


def _check_resume_config(run_dir: Path, run: RunConfig) -> None:
    file = run_dir / CONFIG_FILE
    if not file.is_file():
        return
    found = json.loads(file.read_text(encoding="utf-8"))
    diffs = config_diff(found, config_to_json(run))
    if diffs:
        raise CheckpointError(f"{file}: the run directory was trained with another config ({len(diffs)} field(s) "
                              "differ: " + "; ".join(diffs[:8]) + (" ..." if len(diffs) > 8 else "")
                              + "); use another --out or start over")


def train(run: RunConfig, scene_dir: str | Path, run_dir: str | Path, *, resume: bool = True,
          progress: bool = True, log: Callable[[str], None] = print, stop_after_epoch: int | None = None,
          split: SceneSplit | None = None, start: StartFrom | None = None) -> TrainResult:
    """Train a model of the scene in ``scene_dir`` (NeRF Synthetic layout, ``train`` split).

    Args:
        run: the :class:`RunConfig`.
        scene_dir: the scene folder.
        run_dir: output folder (created); resumed from its latest checkpoint when ``resume`` and one
            exists (the config must be the same: a clear error lists the differences). With
            ``resume=False`` an earlier run's checkpoints and metrics there are removed (logged).
        progress: a progress bar with ETA, running loss and PSNR.
        log: where one-line messages go (``print``; ``lambda s: None`` to silence).
        stop_after_epoch: return after this epoch (as if the run were stopped there).
        split: the training split, if already loaded (else read from ``scene_dir``).
        start: begin from this model instead of ``run.init``'s cloud (ignored when resuming).

    Raises:
        DataError / ValueError: a bad scene folder (named), masks without foreground, a bad config.
        CheckpointError: resuming a run directory of another config.
        TrainingDiverged: an epoch in which every step was refused for non-finite values.
    """
    scene_dir, run_dir = Path(scene_dir), Path(run_dir)
    split = load_split(scene_dir, "train") if split is None else split
    views = Views.from_split(split)
    sampler = run.sampler
    pool = build_pool(sampler, split, run.background)  # fails early (named) on empty masks
    ckpt_dir = run_dir / CHECKPOINT_DIR
    if resume:
        _check_resume_config(run_dir, run)
    elif ckpt_dir.is_dir():  # a restart: an earlier run's checkpoints would mix with this one's
        old = sorted(p.name for p in ckpt_dir.iterdir() if p.is_dir())
        shutil.rmtree(ckpt_dir)
        (run_dir / METRICS_FILE).unlink(missing_ok=True)
        log(f"restarting {run_dir} (resume=False): removed the earlier run's checkpoints {old} and its metrics")
    run_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(run_dir / CONFIG_FILE, json.dumps(config_to_json(run), indent=2) + "\n")
    k_points, k_model, k_batch, k_rounds = _keys(run.seed)

    history: list = []
    extra: dict = {}
    latest = latest_checkpoint(ckpt_dir) if resume and ckpt_dir.exists() else None
    if latest is not None:
        state, points, meta = load_checkpoint(latest, run.train, run.render)
        extra = meta.get("extra", {})
        history, initial = list(extra.get("history", [])), extra.get("initial_cloud", {})
        log(f"resuming {run_dir} from {latest.name} (step {int(state.step)}, epoch {len(history)})")
    elif start is not None:
        points = start.points
        state = init_train_state(run.train, run.render, points, k_model).replace(params=start.params)
        initial = {"source": "model", "points": int(np.asarray(points.alive).sum()), "capacity": points.capacity,
                   "ground_truth": False, **_json_safe(dict(start.note))}
    else:
        t0 = time.perf_counter()
        cloud = initial_cloud(run.init, scene_dir, views)
        points = initial_points(run, cloud, views, k_points)
        initial = {"source": cloud.source, "points": len(cloud), "capacity": points.capacity,
                   "ground_truth": cloud.is_ground_truth, "seconds": round(time.perf_counter() - t0, 2),
                   "info": _json_safe(dict(cloud.info))}
        if cloud.is_ground_truth:
            log("note: the initial cloud is the benchmark's ground-truth surface samples (as asked); "
                "results of this run are labelled 'initial cloud: ground truth'")
        state = init_train_state(run.train, run.render, points, k_model)
    if latest is None:
        carried = start is not None and start.scene is not None
        scene = start.scene.replace(points=points) if carried else PointScene.build(points, run.render)
        _write_rest(run_dir, scene)
    else:
        scene = _scene_of(points, run.render, run_dir)
    budget = extra.get("segments_per_ray") if latest is not None else None
    render = run.render if budget is None else run.render.replace(segments_per_ray=budget)
    step_fns: dict = {}  # one compiled step per packing budget

    def fit(render, scene, epoch):  # the budget for the next epoch's scene, probed on its rays
        probe = sample_batch(sampler, pool, jax.random.fold_in(k_rounds, 10_000 + epoch)).rays
        return fit_segment_budget(render, scene, probe)

    render = fit(render, scene, len(history))

    total = run.total_steps
    first_epoch = len(history) + 1
    bar = tqdm(total=total, initial=int(state.step), desc=f"train[{run.name}]", unit="step",
               disable=not progress, dynamic_ncols=True)
    try:
        for epoch in range(first_epoch, run.epochs + 1):
            t0 = time.perf_counter()
            if render not in step_fns:
                step_fns[render] = _train_step(run.train, render)
            step_fn = step_fns[render]
            metrics = []
            step0 = (epoch - 1) * run.steps_per_epoch
            with count_compiles() as compiles:  # the step's (its batches' sampler compiled in fit())
                for i in range(step0, step0 + run.steps_per_epoch):
                    batch = sample_batch(sampler, pool, jax.random.fold_in(k_batch, i))
                    state, m = step_fn(state, scene, batch)
                    metrics.append(m)
                    if (i + 1) % run.log_every == 0 or i + 1 == step0 + run.steps_per_epoch:
                        last = jax.device_get({"loss": m["loss/total"], "psnr": m["psnr"]})
                        bar.set_postfix(epoch=epoch, loss=f"{float(last['loss']):.4f}",
                                        psnr=f"{float(last['psnr']):.1f}")
                    bar.update(1)
            record = {"epoch": epoch, "step": int(state.step), **_epoch_summary(metrics),
                      "compiles": compiles.count}
            if record["skipped"] == record["steps"]:
                raise TrainingDiverged(
                    f"epoch {epoch}: all {record['steps']} steps were refused because of non-finite values "
                    f"(terms: {', '.join(record.get('non_finite', ['?']))}); parameters were left unchanged")
            record["train_seconds"] = round(time.perf_counter() - t0, 2)
            record["segments_per_ray"] = render.segments_per_ray
            if record["dropped"] > 0:  # the budget was too small for some batches: double it
                render = render.replace(segments_per_ray=2.0 * render.segments_per_ray)
            if run.optimises_points_after(epoch):
                t1 = time.perf_counter()
                trained = state.scene(scene)
                rays = sample_batch(sampler.replace(batch_size=run.points.grow_rays), pool,
                                    jax.random.fold_in(k_rounds, epoch)).rays
                new_points, report = optimise_points(run.points, render, state.params, trained, rays,
                                                     pool.background, views, run.normals)
                reset = _changed_slots(trained.points, new_points)
                state = state.with_points(new_points, reset)
                scene = PointScene.build(new_points, run.render)
                _write_rest(run_dir, scene)  # before the checkpoint: a resume never carries a rebuilt cloud
                report["seconds"] = round(time.perf_counter() - t1, 2)
                record["points"] = report
            render = fit(render, scene, epoch)
            record["alive"] = int(np.asarray(scene.points.alive).sum())
            history.append(record)
            save_checkpoint(ckpt_dir, state, state.point_state(scene.points), run.train, run.render,
                            extra=_json_safe({"history": history, "initial_cloud": initial,
                                              "segments_per_ray": render.segments_per_ray}),
                            keep=run.checkpoint_keep)
            _write_metrics(run_dir, scene_dir, initial, history)
            log(_epoch_line(record))
            if stop_after_epoch is not None and epoch >= stop_after_epoch:
                break
    finally:
        bar.close()
    return TrainResult(state=state, scene=state.scene(scene), history=history, run_dir=run_dir, initial=initial,
                       run=run)


@dataclasses.dataclass
class TrainedModel:
    """A trained model read back from a run directory (:func:`load_trained`)."""

    run: RunConfig
    state: TrainState
    scene: PointScene
    scene_dir: Path | None
    meta: dict


def load_trained(run_dir: str | Path) -> TrainedModel:
    """The latest checkpoint of a run directory written by :func:`train`, with its config and the
    K-D tree rebuilt (or carried, for an edited model: :data:`REST_FILE`). ``scene_dir`` is the
    training scene recorded in ``metrics.json`` (``None`` if absent). Raises ``FileNotFoundError`` /
    :class:`CheckpointError` naming what is missing or wrong."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise FileNotFoundError(f"{run_dir}: expected a training run directory (from `ne-jax train`), found nothing")
    run = load_run_config(run_dir)
    state, points, meta = load_checkpoint(run_dir / CHECKPOINT_DIR, run.train, run.render)
    scene_dir = None
    metrics = run_dir / METRICS_FILE
    if metrics.is_file():
        recorded = json.loads(metrics.read_text(encoding="utf-8")).get("scene_dir")
        scene_dir = Path(recorded) if recorded else None
    return TrainedModel(run=run, state=state, scene=_scene_of(points, run.render, run_dir), scene_dir=scene_dir,
                        meta=meta)


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
        save_checkpoint(tmp / CHECKPOINT_DIR, model.state, points, model.run.train, model.run.render,
                        extra=extra, keep=1)
        _write_rest(tmp, model.scene)
    return Path(run_dir)


def fit_segment_budget(render: RenderConfig, scene: PointScene, rays, headroom: float = 1.25) -> RenderConfig:
    """``render`` with a packing budget (``segments_per_ray``) that holds ``headroom`` times the mean
    segments per ray of ``rays`` in ``scene``: the preset's budget doubled as often as needed, never
    lowered. Segments beyond the budget would be dropped from the end of the batch, and the rays
    that lose them would train on the background colour."""
    if render.segments_per_ray is None:
        return render
    need = headroom * float(jnp.mean(intersect(scene.tree, rays, render.tree).num_segments))
    budget = render.segments_per_ray
    while budget < need:
        budget *= 2.0
    return render.replace(segments_per_ray=budget)


def _changed_slots(old: PointState, new: PointState) -> np.ndarray:
    """``[C_new]`` bool: slots that hold a point now but did not before (new points)."""
    before = np.zeros(new.capacity, bool)
    before[:old.capacity] = np.asarray(old.alive)
    return np.asarray(new.alive) & ~before


def _epoch_line(r: dict) -> str:
    line = (f"epoch {r['epoch']}: step {r['step']}, loss {r.get('loss/total', float('nan')):.4f}, "
            f"train PSNR {r.get('psnr', float('nan')):.2f} dB, {r['train_seconds']:.1f} s")
    if r["skipped"]:
        line += f", {r['skipped']} step(s) refused (non-finite: {', '.join(r.get('non_finite', []))})"
    if r["overflow"] or r["dropped"]:
        line += f", segments lost: {r['overflow']} overflow + {r['dropped']} dropped"
    if "points" in r:
        p = r["points"]
        g = p.get("grown", {})
        line += (f"; points {p['alive_before']} -> {p['alive_after']} (+{g.get('added', 0)} grown, "
                 f"-{p.get('pruned', 0)} pruned, -{p.get('denoised', 0)} outliers"
                 f"{', capacity ' + str(p['capacity']) if g.get('reallocated') else ''})")
    return line


__all__ = ["CONFIG_FILE", "INIT_SOURCES", "METRICS_FILE", "PRESETS", "InitConfig", "RunConfig", "StartFrom",
           "TrainResult", "TrainedModel", "TrainingDiverged", "get_run_preset", "initial_cloud", "initial_points",
           "load_run_config", "load_trained", "save_trained", "train"]

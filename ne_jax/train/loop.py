"""The training run: initial cloud, epochs of jitted steps, point-cloud rounds between
epochs, checkpoints, and a run directory a person can read.

``model = train(RunConfig.tiny(), scene_dir, run_dir)`` returns a
:class:`~ne_jax.train.model.TrainedModel`; the run directory (:mod:`ne_jax.train.model`) holds the
resolved config, ``metrics.json`` (one record per epoch: losses, PSNR, skipped steps, segments lost,
compilations, point-cloud report, seconds) and the checkpoints.

Exact resume: the batch of step ``i`` is drawn with ``fold_in(batch_key, i)`` and the rays of a
point-cloud round with ``fold_in(points_key, epoch)``, so a run resumed from the checkpoint written
at the end of an epoch continues bit for bit as if it had never stopped (tested: 2 + 2 epochs equal
4). The step compiles once per shape: within an epoch nothing recompiles; a round that changes the
capacity or the tree depth compiles the step once more (counted in ``metrics.json``).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import shutil
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import jax
import numpy as np
from tqdm.auto import tqdm

from ne_jax.atomic import atomic_write_text
from ne_jax.compiles import count_compiles
from ne_jax.config_json import config_diff, config_to_json
from ne_jax.data.nerf_synthetic import SceneSplit
from ne_jax.data.scene import (
    Normalisation,
    detect_format,
    load_split,
    scene_near_far,
    scene_normalisation,
    scene_points,
    scene_record,
)
from ne_jax.geometry.capacity import LostCounts
from ne_jax.geometry.points import PointState
from ne_jax.pointcloud.init import (
    CarvingError,
    InitialCloud,
    Views,
    carve_visual_hull,
    ground_truth_cloud,
    load_ply_cloud,
)
from ne_jax.pointcloud.normals import estimate_normals
from ne_jax.pointcloud.rounds import point_round
from ne_jax.pointcloud.sfm_init import sfm_cloud
from ne_jax.render.renderer import PointScene
from ne_jax.train.checkpoint import CheckpointError, latest_checkpoint, load_checkpoint, save_checkpoint
from ne_jax.train.model import (
    CHECKPOINT_DIR,
    METRICS_FILE,
    SCENE_RECORD_FILE,
    TrainedModel,
    _json_safe,
    _scene_of,
    _write_rest,
    saved_capacities,
)
from ne_jax.train.run import CONFIG_FILE, INIT_CAPACITY_HEADROOM, InitConfig, RunConfig
from ne_jax.train.sampler import build_pool, sample_batch
from ne_jax.train.state import init_train_state
from ne_jax.train.step import make_train_step

# The jitted step per (train config, packing budget), shared by the train() calls of one process: a
# second run of the same configs (a notebook cell run again, a resume) compiles nothing new.
_train_step = functools.lru_cache(maxsize=8)(make_train_step)


# ---------------------------------------------------------------- the initial cloud


def initial_cloud(cfg: InitConfig, scene_dir: Path, views: Views) -> InitialCloud:
    """The run's initial cloud (see :class:`InitConfig`); carving with one view uses ``min_views=1``.
    ``info["why"]`` says why ``"auto"`` chose its source."""
    source, why = cfg.source, f"init.source = {cfg.source!r}"
    found = scene_points(scene_dir) if source in ("auto", "sfm") else None
    if source == "auto":
        has_masks = bool((views.alpha < 0.99).any())
        if found is not None:
            source, why = "sfm", f"auto: the {detect_format(scene_dir)} scene has structure-from-motion points"
        elif has_masks:
            source, why = "carving", "auto: the training images have alpha masks (a visual hull)"
        else:
            raise CarvingError(
                f"{scene_dir}: init.source='auto' found neither structure-from-motion points (COLMAP points3D, "
                "nerfstudio ply_file_path) nor alpha masks in the training images to start a cloud from; run "
                "`ne-jax process-images PHOTOS --out SCENE` to make a COLMAP scene, or pass --init ply --ply FILE")
    if source in ("ply", "ground_truth"):  # a PLY is in the capture's coordinates, as the user sees them
        cloud = load_ply_cloud(cfg.ply_path) if source == "ply" else ground_truth_cloud(scene_dir)
        cloud = _to_scene_frame(cloud, scene_normalisation(scene_dir))
    elif source == "sfm":
        if found is None:
            raise CarvingError(f"{scene_dir}: init.source='sfm' but the scene folder has no structure-from-motion "
                               "points (COLMAP points3D, nerfstudio ply_file_path)")
        xyz, _, error = found
        cloud = sfm_cloud(xyz, views, cfg.sfm_points, error=error, seed=cfg.carve.seed)
    else:
        carve = cfg.carve
        if views.num_views < carve.min_views:
            warnings.warn(f"carving: {views.num_views} training view(s) < min_views={carve.min_views}; "
                          f"carving with min_views={views.num_views}", stacklevel=2)
            carve = dataclasses.replace(carve, min_views=views.num_views)
        cloud = carve_visual_hull(carve, views)
    return dataclasses.replace(cloud, info={**cloud.info, "why": why})


def _to_scene_frame(cloud: InitialCloud, norm: Normalisation) -> InitialCloud:
    """``cloud`` (capture coordinates) in the scene frame of ``norm``; unchanged for the identity."""
    if norm.is_identity:
        return cloud
    normals = None if cloud.normals is None else norm.rotate_to_scene(cloud.normals).astype(np.float32)
    return dataclasses.replace(cloud, xyz=norm.to_scene(cloud.xyz).astype(np.float32), normals=normals)


def fit_to_scene(run: RunConfig, scene_dir: Path) -> RunConfig:
    """``run`` with what its scene folder decides: for a capture with
    ``sampler.bounds_from_scene``, ``near``/``far`` from its cameras and points
    (:func:`~ne_jax.data.scene.scene_near_far`); a NeRF Synthetic folder changes nothing."""
    bounds = scene_near_far(scene_dir) if run.sampler.bounds_from_scene else None
    if bounds is None:
        return run
    near, far = (float(f"{x:.6g}") for x in bounds)
    return run.replace(sampler=run.sampler.replace(near=near, far=far))


def initial_points(run: RunConfig, cloud: InitialCloud, views: Views, key: jax.Array) -> PointState:
    """The cloud as a :class:`PointState` with Open3D normals, random features, confidence 0.5 and
    capacity ``ceil(N * headroom)``."""
    normals = estimate_normals(run.normals, cloud.xyz, views)
    capacity = max(int(math.ceil(len(cloud) * INIT_CAPACITY_HEADROOM)), 1)
    return PointState.from_numpy(cloud.xyz, capacity, run.render.shading.feature_dim, normal=normals, key=key)


# ---------------------------------------------------------------- the run


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


def _clock() -> tuple[float, float]:
    """Now, as ``(wall, CPU)`` seconds: ``perf_counter`` and this process's CPU time (all threads)."""
    return time.perf_counter(), time.process_time()


def _since(start: tuple[float, float]) -> tuple[float, float]:
    """Wall and CPU seconds since ``start`` (a :func:`_clock` reading), rounded to 10 ms."""
    return tuple(round(now - then, 2) for now, then in zip(_clock(), start))


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
    out["lost"] = lost_counts(host).as_dict()
    bad = sorted({k.split("/", 1)[1] for m in host for k, v in m.items() if k.startswith("finite/") and not bool(v)})
    if bad:
        out["non_finite"] = bad
    return out


INFLIGHT_STEPS = 8
"""At most this many training steps run ahead of the host: every ``INFLIGHT_STEPS``-th step waits for
its loss. Unbounded, the host queues dozens of steps, and XLA:CPU (jaxlib 0.10) can then deadlock a
step split over several devices: one device waits in the step's all-reduce while the other's launch
waits, on a thread of the same pool, for a slot of its 32 computations in flight (docs/devices.md)."""

TRAINING_GROWS = ("packing",)
"""The buffers a training run grows after an epoch that lost into them. The traversal's frontier and
slots are a training step's speed settings (a preset is chosen with them, docs/studies/
accuracy_vs_time.md): what a batch loses there (about one frontier node or segment per 1,000 rays
at ``tiny`` and ``default``, docs/geometry.md) is counted in each epoch's record, not grown, while a
render grows every buffer."""


def lost_counts(metrics: list[dict]) -> LostCounts:
    """What the training steps of ``metrics`` (host values, :func:`~ne_jax.train.step.make_train_step`'s
    ``lost/*``) lost to the scene's capacities, over their batches."""
    total = LostCounts()
    for m in metrics:
        total += LostCounts(frontier=int(m["lost/frontier"]), slots=int(m["lost/slots"]),
                            packing=int(m["lost/packing"]), max_emitted=int(m["lost/max_emitted"]),
                            emitted=int(m["lost/emitted"]), rays=int(m["lost/rays"]))
    return total


def _write_metrics(run_dir: Path, scene_dir: Path, initial: dict, history: list, notes: dict) -> None:
    data = {"scene_dir": str(scene_dir.resolve()), "initial_cloud": initial, "epochs": history}
    if notes:
        data["notes"] = notes
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
          split: SceneSplit | None = None, start: StartFrom | None = None, notes: dict | None = None,
          log_every: int = 25) -> TrainedModel:
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
        notes: recorded in ``metrics.json`` as ``notes`` (e.g. why the run declares its effects,
            :func:`~ne_jax.train.effects.declare_effects`); a resume keeps the first run's.
        log_every: steps between progress-bar updates (each reads the metrics back from the device).

    Raises:
        DataError / ValueError: a bad scene folder (named), masks without foreground, a bad config.
        CheckpointError: resuming a run directory of another config.
        TrainingDiverged: an epoch in which every step was refused for non-finite values.
    """
    scene_dir, run_dir = Path(scene_dir), Path(run_dir)
    run = fit_to_scene(run, scene_dir)
    split = load_split(scene_dir, "train", run.downscale) if split is None else split
    views = Views.from_split(split)
    if run.render.shading.effects.background_model == "constant" and not (views.alpha < 0.99).any():
        warnings.warn(f"{scene_dir}: every training pixel is opaque (the images hold their background) but the run "
                      "models a constant background; declare the background sphere (background_model='sphere', "
                      "e.g. ne_jax.train.effects.declare_effects(run.render, 'auto', scene_dir, split, None))",
                      stacklevel=2)
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
    seen = {**scene_record(scene_dir), "downscale": run.downscale, "train_views": list(split.file_paths)}
    atomic_write_text(run_dir / SCENE_RECORD_FILE, json.dumps(_json_safe(seen), indent=2) + "\n")
    k_points, k_model, k_batch, k_rounds = _keys(run.seed)

    history: list = []
    extra: dict = {}
    latest = latest_checkpoint(ckpt_dir) if resume and ckpt_dir.exists() else None
    if latest is not None:
        state, points, meta = load_checkpoint(latest, run.train, run.render)
        extra = meta.get("extra", {})
        history, initial = list(extra.get("history", [])), extra.get("initial_cloud", {})
        notes = extra.get("notes", notes)
        log(f"resuming {run_dir} from {latest.name} (step {int(state.step)}, epoch {len(history)})")
    elif start is not None:
        points = start.points
        state = init_train_state(run.train, run.render, points, k_model,
                                 total_steps=run.total_steps).replace(params=start.params)
        initial = {"source": "model", "points": int(np.asarray(points.alive).sum()), "capacity": points.capacity,
                   "ground_truth": False, **_json_safe(dict(start.note))}
    else:
        began = _clock()
        cloud = initial_cloud(run.init, scene_dir, views)
        points = initial_points(run, cloud, views, k_points)
        seconds, cpu_seconds = _since(began)
        initial = {"source": cloud.source, "points": len(cloud), "capacity": points.capacity,
                   "ground_truth": cloud.is_ground_truth, "seconds": seconds, "cpu_seconds": cpu_seconds,
                   "info": _json_safe(dict(cloud.info))}
        if cloud.is_ground_truth:
            log("note: the initial cloud is the benchmark's ground-truth surface samples (as asked); "
                "results of this run are labelled 'initial cloud: ground truth'")
        state = init_train_state(run.train, run.render, points, k_model, total_steps=run.total_steps)
    if latest is None:
        carried = start is not None and start.scene is not None
        scene = (start.scene.replace(points=points) if carried
                 else PointScene.build(points, run.render, run.capacities))
        _write_rest(run_dir, scene)
    else:
        scene = _scene_of(points, run.render, run_dir, saved_capacities(meta, run.capacities))
    render = run.train_render  # the images' config on the training batches' grid
    # compiles once per capacities the scene carries; the length is a key of the cache, so a run of
    # another length (a fine-tune) gets its own step
    step_fn = _train_step(run.train, render, total_steps=run.total_steps)

    def fit(scene, epoch):  # the packing budget for the next epoch's scene, probed on its rays
        probe = sample_batch(sampler, pool, jax.random.fold_in(k_rounds, 10_000 + epoch), render.pixel_samples).rays
        return scene.fitted(render, probe)

    scene = fit(scene, len(history))

    total = run.total_steps
    first_epoch = len(history) + 1
    bar = tqdm(total=total, initial=int(state.step), desc=f"train[{run.name}]", unit="step",
               disable=not progress, dynamic_ncols=True)
    try:
        for epoch in range(first_epoch, run.epochs + 1):
            began = _clock()
            metrics = []
            step0 = (epoch - 1) * run.steps_per_epoch
            with count_compiles() as compiles:  # the step's (its batches' sampler compiled in fit())
                for i in range(step0, step0 + run.steps_per_epoch):
                    batch = sample_batch(sampler, pool, jax.random.fold_in(k_batch, i), render.pixel_samples)
                    state, m = step_fn(state, scene, batch)
                    metrics.append(m)
                    if (i + 1) % INFLIGHT_STEPS == 0:
                        jax.block_until_ready(m["loss/total"])
                    if (i + 1) % log_every == 0 or i + 1 == step0 + run.steps_per_epoch:
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
            record["train_seconds"], record["train_cpu_seconds"] = _since(began)
            record["capacities"] = dataclasses.asdict(scene.capacities)
            # a batch lost segments to the packing budget: grow it (the traversal's losses are counted)
            scene = scene.grown(LostCounts(**record["lost"]), TRAINING_GROWS) or scene
            if run.round_after(epoch):
                round_began = _clock()
                trained = state.scene(scene)
                rays = sample_batch(sampler.replace(batch_size=run.rounds.grow_rays), pool,
                                    jax.random.fold_in(k_rounds, epoch)).rays
                new_points, report = point_round(run.rounds, render, state.params, trained, rays,
                                             pool.background, views, run.normals)
                reset = _changed_slots(trained.points, new_points)
                state = state.with_points(new_points, reset)
                scene = PointScene.build(new_points, run.render, scene.capacities)
                _write_rest(run_dir, scene)  # before the checkpoint: a resume never carries a rebuilt cloud
                report["seconds"], report["cpu_seconds"] = _since(round_began)
                record["points"] = report
            scene = fit(scene, epoch)
            record["alive"] = int(np.asarray(scene.points.alive).sum())
            history.append(record)
            save_checkpoint(ckpt_dir, state, state.point_state(scene.points), run.train, run.render,
                            extra=_json_safe({"history": history, "initial_cloud": initial, "notes": notes or {},
                                              "capacities": dataclasses.asdict(scene.capacities)}))
            _write_metrics(run_dir, scene_dir, initial, history, notes or {})
            log(_epoch_line(record))
            if stop_after_epoch is not None and epoch >= stop_after_epoch:
                break
    finally:
        bar.close()
    return TrainedModel(run=run, state=state, scene=state.scene(scene), scene_dir=scene_dir, run_dir=run_dir,
                        frame=Normalisation.from_dict(seen["normalisation"]),
                        history=history, initial=initial)


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
    lost = r["lost"]
    if lost["frontier"] or lost["slots"] or lost["packing"]:
        # TRAINING_GROWS: only the packing budget grows; the traversal's losses are counted
        line += (f", lost: {lost['frontier']} frontier nodes and {lost['slots']} segments beyond the slots "
                 f"(counted), {lost['packing']} beyond the packing budget (grown)")
    if "points" in r:
        p = r["points"]
        g = p.get("grown", {})
        line += (f"; points {p['alive_before']} -> {p['alive_after']} (+{g.get('added', 0)} grown, "
                 f"-{p.get('pruned', 0)} pruned, -{p.get('denoised', 0)} outliers"
                 f"{', capacity ' + str(p['capacity']) if g.get('reallocated') else ''})")
    return line


__all__ = ["StartFrom", "TrainingDiverged", "initial_cloud", "fit_to_scene", "initial_points", "lost_counts", "train"]

"""Editing a trained model and fine-tuning the result.

* :func:`edit_model`: a trained model (:class:`~ne_jax.train.model.TrainedModel`) plus an edit gives an
  edited model: the same colour model and per-point features, the edited cloud (positions, deletions,
  normals, IST) and the ``ist`` effect declared. Written to a run directory of its own (``config.json``,
  ``checkpoints/``, ``metrics.json`` with the edit's report), so every command that reads a run
  (``ne-jax eval``, ``render``, ``export``, ``finetune``) reads an edited model too.
* :func:`finetune`: train an edited model on the edited scene's training views for a few epochs with
  the same loop as training (:func:`~ne_jax.train.loop.train`), optionally with trainable ISTs and
  point-cloud rounds (the paper: one warm-up epoch, then rounds for up to five epochs).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ne_jax.edit.apply import EditConfig, EditContext, apply_edit_with_report, edit_context, edited_render_config
from ne_jax.edit.deformations import Edit
from ne_jax.edit.targets import EditError, EditSource, edit_target
from ne_jax.train.loop import StartFrom, train
from ne_jax.train.model import TrainedModel, save_trained
from ne_jax.train.run import RunConfig


def model_edit_context(model: TrainedModel, cfg: EditConfig = EditConfig(), alive=None) -> EditContext:
    """The :class:`~ne_jax.edit.apply.EditContext` of edits of ``model`` with ``cfg`` (its cloud's
    IST neighbour table, its tree's carry context), for a caller that edits one model repeatedly
    and passes it to every :func:`edit_model`. ``alive``: ``[C]`` bool the points alive after the
    edits (default: the model's alive points)."""
    return edit_context(cfg, model.state.point_state(model.scene.points), model.scene, model.run.render, alive)


def edit_model(model: TrainedModel, edit: EditSource, out_dir: str | Path | None = None, *,
               ist: bool = True, cfg: EditConfig = EditConfig(), scene_dir: str | Path | None = None,
               label: str | None = None, context: EditContext | None = None) -> tuple[TrainedModel, dict]:
    """Apply ``edit`` to ``model``'s cloud. Returns ``(edited model, report)``.

    ``ist=False`` declares no IST effect (the "without IST" variant; the IST is still computed and
    stored, so the same edited directory can be rendered either way). ``scene_dir``: the edited
    scene's ground truth, recorded for ``eval`` and ``finetune`` (for a benchmark edit by name,
    :func:`ne_jax.benchmark.edits.resolve_edit` gives the edit and its folder). ``label`` names the
    edit in the report (default: the edit's name or the file). With ``out_dir`` the edited model is
    written there as a run directory (atomically). ``context``: :func:`model_edit_context` of
    ``model`` and ``cfg``, held by a caller that edits the model repeatedly (made on the spot when
    ``None``).

    The edit is read in the capture's coordinates (``model.frame``: a file's positions, a named
    benchmark edit's motion), as a user wrote it; for a NeRF Synthetic scene they are the model's.
    """
    label = label if label is not None else edit.name if isinstance(edit, Edit) else str(edit)
    before = model.state.point_state(model.scene.points)
    points, report = apply_edit_with_report(before, in_model_frame(before, edit, model.frame), cfg, context)
    run = model.run.replace(render=edited_render_config(model.run.render, ist))
    state = model.state.with_points(points, np.zeros(points.capacity, bool))
    edited = TrainedModel(run=run, state=state, scene=cfg.scene(model.scene, points, run.render, context),
                          scene_dir=None if scene_dir is None else Path(scene_dir), meta=dict(model.meta),
                          frame=model.frame)
    report = {"edit": label, "ist": ist, **report}
    if out_dir is not None:
        source = {"scene_dir": str(model.scene_dir) if model.scene_dir else None, "step": int(model.state.step)}
        save_trained(edited, out_dir, {"edit": report, "source": source, "epochs": []},
                     extra={"history": [], "edit": report})
    return edited, report


def in_model_frame(points, edit: EditSource, frame) -> EditSource:
    """``edit``, written in the capture's coordinates, as new positions in the model's: the edit's
    target is taken on the points seen in the capture's frame and brought back by ``frame``
    (a :class:`~ne_jax.data.scene.Normalisation`); ``edit`` itself where ``frame`` is the identity.
    Returns rows ``[alive, 3]`` (NaN rows delete), as :func:`~ne_jax.edit.targets.edit_target` reads."""
    if frame.is_identity:
        return edit
    alive = np.asarray(points.alive)
    seen = points.replace(xyz=np.asarray(frame.to_capture(np.asarray(points.xyz)), np.float32))
    target = edit_target(seen, edit)
    rows = frame.to_scene(target.xyz[alive])
    rows[target.deleted[alive]] = np.nan
    return rows


def finetune_config(run: RunConfig, epochs: int = 1, *, steps_per_epoch: int | None = None,
                    train_ist: bool = False, rounds: bool = False) -> RunConfig:
    """The run config of fine-tuning an edited model for ``epochs`` epochs: a fresh cosine schedule
    over them, trainable ISTs (kept orthogonal by ``ist_orthogonality = 1``) when ``train_ist``, and
    point-cloud rounds after epochs ``1 .. min(5, epochs - 1)`` when ``rounds`` (paper:
    one warm-up epoch, then rounds)."""
    loss = run.train.loss.replace(ist_orthogonality=1.0 if train_ist else 0.0)
    run = run.replace(train=run.train.replace(train_ist=train_ist, loss=loss),
                      round_epochs=(1, min(5, epochs - 1)) if rounds else (1, 0))
    return run.with_schedule(epochs, steps_per_epoch).replace(name=f"{run.name}-finetune")


def finetune(model: TrainedModel, run_dir: str | Path, epochs: int = 1, *, scene_dir: str | Path | None = None,
             steps_per_epoch: int | None = None, train_ist: bool = False, rounds: bool = False,
             resume: bool = True, progress: bool = True, log=print) -> TrainedModel:
    """Fine-tune an edited ``model`` on the training views of ``scene_dir`` (default: the edited
    scene recorded with the model) into ``run_dir``; see :func:`finetune_config`.

    Raises:
        EditError: no edited scene to fine-tune on.
    """
    scene_dir = scene_dir if scene_dir is not None else model.scene_dir
    if scene_dir is None:
        raise EditError("finetune: expected the edited scene's folder (training views of the edited scene), "
                        "found none recorded with the model; pass scene_dir / --scene")
    run = finetune_config(model.run, epochs, steps_per_epoch=steps_per_epoch, train_ist=train_ist,
                          rounds=rounds)
    start = StartFrom(params=model.state.params, points=model.state.point_state(model.scene.points),
                      scene=model.scene if model.scene.rest_xyz is not None else None,
                      note={"from_step": int(model.state.step), "edit": model.meta.get("extra", {}).get("edit")})
    return train(run, scene_dir, run_dir, resume=resume, progress=progress, log=log, start=start)


__all__ = ["edit_model", "finetune", "finetune_config", "in_model_frame", "model_edit_context"]

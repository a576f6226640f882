"""Benchmark edits by name: the edits a benchmark scene defines (:mod:`ne_jax.benchmark.scenes`),
looked up from the scene folder a model was trained on (its ``scene.json`` names the scene)."""

from __future__ import annotations

import json
from pathlib import Path

from ne_jax.benchmark.scenes import HELDOUT_SCENES, SCENES, get_scene
from ne_jax.edit.deformations import Edit
from ne_jax.edit.targets import EditError, EditSource


def _scene_meta(scene_dir: Path | None) -> dict:
    if scene_dir is None or not (Path(scene_dir) / "scene.json").is_file():
        return {}
    return json.loads((Path(scene_dir) / "scene.json").read_text(encoding="utf-8"))


def benchmark_edit(scene_dir: str | Path | None, name: str) -> tuple[Edit, Path | None]:
    """The benchmark edit ``name`` of the scene in ``scene_dir`` (its ``scene.json`` names the scene)
    and the folder of the edited scene's ground truth (``None`` when not generated). In a capture
    scene (``scene.json`` with a ``ground``, :mod:`ne_jax.benchmark.capture`) the edit acts only on
    the points above the ground (:func:`~ne_jax.benchmark.capture.objects_only`), as its ground
    truth was rendered.

    Raises:
        EditError: ``scene_dir`` is not a benchmark scene, the scene has no edit ``name`` (the
            message lists the edits it has), or its ground truth was generated for another
            definition of the edit.
    """
    meta = _scene_meta(scene_dir)
    if meta.get("scene") not in SCENES and meta.get("scene") not in HELDOUT_SCENES:
        raise EditError(f"edit {name!r}: expected the model's scene folder to be a benchmark scene (scene.json "
                        f"naming one of {sorted(SCENES) + sorted(HELDOUT_SCENES)}), found {scene_dir} "
                        f"({meta.get('scene', 'no scene.json')})")
    scene = get_scene(meta["scene"])
    if name not in scene.edits:
        raise EditError(f"edit {name!r}: expected one of the edits of scene {scene.name!r}: {sorted(scene.edits)}")
    edit, truth = scene.edits[name], Path(scene_dir) / "edits" / name
    if "ground" in meta:  # a capture scene: its edits move the objects, the ground stays
        from ne_jax.benchmark.capture import objects_only

        edit = objects_only(edit, meta["ground"]["objects_above"])
    if not (truth / "transforms_test.json").is_file():
        return edit, None
    made_for = _scene_meta(truth).get("edit_description")
    if made_for != edit.description:
        raise EditError(f"edit {name!r}: the ground truth in {truth} was generated for the edit {made_for!r}, but the "
                        f"scene now defines {edit.description!r}; regenerate the benchmark "
                        "(python -m experiments.make_benchmark)")
    return edit, truth


def resolve_edit(scene_dir: str | Path | None, edit: EditSource) -> tuple[EditSource, str, Path | None]:
    """``(edit, label, ground-truth folder)`` for an edit given as a benchmark name, a file or an
    :class:`Edit`: a string that is not an existing file is looked up among the edits of the benchmark
    scene in ``scene_dir`` (the folder the model was trained on)."""
    if isinstance(edit, str) and not Path(edit).exists() and not edit.lower().endswith((".npy", ".ply")):
        fn, truth = benchmark_edit(scene_dir, edit)
        return fn, edit, truth
    label = edit.name if isinstance(edit, Edit) else str(edit)
    return edit, label, None


__all__ = ["benchmark_edit", "resolve_edit"]

"""Edit targets: the indexed target cloud ``Q(P)`` an edit asks for.

An :class:`EditTarget` gives every slot of a capacity-``C`` :class:`~ne_jax.geometry.points.PointState`
a new position and says which alive points are deleted. It is made by :func:`edit_target` from

* an :class:`~ne_jax.edit.deformations.Edit` (a function of the original positions, e.g. the
  benchmark's edits; deletions decided in the original space);
* a ``.npy`` file or an array: ``[N, 3]`` new positions of the ``N`` alive points in slot order
  (the order of :func:`~ne_jax.pointcloud.export.export_ply`), or ``[C, 3]`` for every slot; a row
  of NaN deletes the point;
* a PLY file with ``x y z`` and an integer ``index`` property (the slot, as ``ne-jax export``
  writes it): the listed points move there; alive points missing from the file are deleted;
* a sequence of any of these, applied in order (each to the result of the previous one; a point is
  deleted if any step deletes it).

Bad edits get a :class:`EditError` naming the source, what was expected and what was found: the
wrong number of rows, NaN/inf in a row that is not all-NaN, PLY indices that are duplicated, out of
range or of dead slots, or an edit that deletes every point.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from ne_jax.data.ply import PlyError, read_ply
from ne_jax.edit.deformations import Edit
from ne_jax.geometry.points import PointState


class EditError(ValueError):
    """A bad edit: the message names the edit's source, the expectation and what was found."""


EditSource = Edit | str | os.PathLike | np.ndarray | Sequence
"""What :func:`edit_target` accepts."""


@dataclasses.dataclass(frozen=True)
class EditTarget:
    """``xyz [C, 3]`` target positions of every slot (dead and deleted slots: their old position)
    and ``deleted [C]`` bool (alive points the edit removes)."""

    xyz: np.ndarray
    deleted: np.ndarray


def _from_function(points: PointState, edit: Edit) -> EditTarget:
    alive = np.asarray(points.alive)
    xyz = np.asarray(points.xyz)
    moved, deleted = edit.apply(xyz)
    moved, deleted = np.asarray(moved, xyz.dtype), np.asarray(deleted) & alive
    bad = alive & ~deleted & ~np.isfinite(moved).all(1)
    if bad.any():
        raise EditError(f"edit {edit.name!r}: expected finite positions, found NaN/inf for {int(bad.sum())} "
                        f"point(s) (first slot {int(np.flatnonzero(bad)[0])})")
    return EditTarget(xyz=np.where(alive[:, None] & ~deleted[:, None], moved, xyz), deleted=deleted)


def _from_rows(points: PointState, rows: np.ndarray, source: str) -> EditTarget:
    alive = np.asarray(points.alive)
    idx = np.flatnonzero(alive)
    if rows.ndim != 2 or rows.shape[1] != 3 or rows.shape[0] not in (idx.size, points.capacity):
        raise EditError(f"{source}: expected new positions of shape [{idx.size}, 3] (one row per alive point, "
                        f"in slot order) or [{points.capacity}, 3] (one per slot), found shape {rows.shape}")
    if not np.issubdtype(rows.dtype, np.number):
        raise EditError(f"{source}: expected numbers, found dtype {rows.dtype}")
    slots = idx if rows.shape[0] == idx.size else np.arange(points.capacity)
    rows = rows.astype(np.float64)
    nan_rows = np.isnan(rows).all(1)
    partial = ~np.isfinite(rows).all(1) & ~nan_rows & alive[slots]
    if partial.any():
        r = int(np.flatnonzero(partial)[0])
        raise EditError(f"{source}: expected finite rows, or all-NaN rows for deleted points, found "
                        f"{int(partial.sum())} row(s) with NaN/inf (first row {r}: {rows[r].tolist()})")
    xyz = np.asarray(points.xyz).copy()
    deleted = np.zeros(points.capacity, bool)
    deleted[slots] = nan_rows & alive[slots]
    keep = slots[alive[slots] & ~nan_rows]
    xyz[keep] = rows[alive[slots] & ~nan_rows]
    return EditTarget(xyz=xyz, deleted=deleted)


def _from_ply(points: PointState, path: Path) -> EditTarget:
    try:
        props = read_ply(path)
    except PlyError as e:
        raise EditError(str(e)) from None
    missing = [k for k in ("x", "y", "z", "index") if k not in props]
    if missing:
        raise EditError(f"{path}: expected vertex properties x, y, z and index (the slot, as `ne-jax export` "
                        f"writes it), found {sorted(props)} (missing {missing})")
    index = props["index"]
    if not np.issubdtype(index.dtype, np.integer):
        raise EditError(f"{path}: expected an integer 'index' property, found dtype {index.dtype}")
    index = index.astype(np.int64)
    alive = np.asarray(points.alive)
    out = (index < 0) | (index >= points.capacity)
    if out.any():
        raise EditError(f"{path}: expected indices in [0, {points.capacity}), found {int(index[out][0])}")
    dead = ~alive[index]
    if dead.any():
        raise EditError(f"{path}: expected indices of alive points, found {int(dead.sum())} of dead slots "
                        f"(first: {int(index[dead][0])})")
    uniq, counts = np.unique(index, return_counts=True)
    if (counts > 1).any():
        raise EditError(f"{path}: expected each index once, found index {int(uniq[counts > 1][0])} "
                        f"{int(counts[counts > 1][0])} times")
    xyz_new = np.stack([props["x"], props["y"], props["z"]], 1).astype(np.float64)
    bad = ~np.isfinite(xyz_new).all(1)
    if bad.any():
        raise EditError(f"{path}: expected finite positions, found NaN/inf at index {int(index[bad][0])} "
                        "(delete a point by leaving it out of the file)")
    xyz = np.asarray(points.xyz).copy()
    xyz[index] = xyz_new
    deleted = alive.copy()
    deleted[index] = False
    return EditTarget(xyz=xyz, deleted=deleted)


def _one(points: PointState, edit) -> EditTarget:
    if isinstance(edit, Edit):
        return _from_function(points, edit)
    if isinstance(edit, (str, os.PathLike)):
        path = Path(edit)
        if not path.is_file():
            raise EditError(f"{path}: expected an edit file (.npy or .ply), found nothing")
        suffix = path.suffix.lower()
        if suffix == ".npy":
            try:
                rows = np.load(path, allow_pickle=False)
            except (ValueError, OSError) as e:
                raise EditError(f"{path}: expected a NumPy .npy array, found unreadable data ({e})") from None
            return _from_rows(points, rows, str(path))
        if suffix == ".ply":
            return _from_ply(points, path)
        raise EditError(f"{path}: expected a .npy or .ply edit file, found suffix {path.suffix!r}")
    if isinstance(edit, (np.ndarray, jnp.ndarray)):
        return _from_rows(points, np.asarray(edit), "edit array")
    raise EditError(f"edit: expected an Edit, a .npy/.ply path, an [N, 3] array or a sequence of these, "
                    f"found {type(edit).__name__}")


def edit_target(points: PointState, edit: EditSource) -> EditTarget:
    """The :class:`EditTarget` of ``edit`` on ``points`` (see the module docstring). Raises
    :class:`EditError` for a bad edit, including one that deletes every alive point."""
    steps = list(edit) if isinstance(edit, (list, tuple)) else [edit]
    if not steps:
        raise EditError("edit: expected at least one edit, found an empty sequence")
    current, deleted = points, np.zeros(points.capacity, bool)
    target = None
    for step in steps:
        target = _one(current, step)
        deleted |= target.deleted
        current = current.replace(xyz=jnp.asarray(target.xyz, points.xyz.dtype),
                                  alive=jnp.asarray(np.asarray(points.alive) & ~deleted))
    if not (np.asarray(points.alive) & ~deleted).any():
        raise EditError(f"edit: expected at least one point to remain, found all {int(np.asarray(points.alive).sum())} "
                        "alive points deleted")
    return EditTarget(xyz=np.asarray(target.xyz), deleted=deleted)


__all__ = ["EditError", "EditSource", "EditTarget", "edit_target"]

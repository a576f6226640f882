"""The viewer's edits as pure functions, separate from the browser GUI (:mod:`ne_jax.view.viewer`).

* a :class:`Region` (a box or a sphere the user places with a gizmo) selects the alive points inside it
  (:func:`select_region`); a rectangle dragged on the screen selects the points it covers
  (:func:`select_screen_rect`);
* a :class:`Transform` (the gizmo's translation and rotation about a pivot, and a uniform scale) moves
  a selection (:func:`move_points`); :func:`delete_points` deletes one; a selection of zero points is
  refused with a :class:`SelectionError`;
* a :class:`ViewEdit` is the edit so far: the target position of every slot and the deleted points,
  i.e. an :class:`~ne_jax.edit.targets.EditTarget`. It becomes the ``[C, 3]`` rows
  :func:`~ne_jax.edit.model.edit_model` takes (:meth:`ViewEdit.rows`) or the indexed PLY ``ne-jax edit``
  reads (:func:`write_edit_ply`); :func:`save_view_edit` writes both, the PLY inside the edited run
  directory, atomically.

Positions are kept in float32, the dtype of a model's cloud and of the PLY, so the in-memory edit, the
saved PLY and the edited run directory hold the same numbers.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np

from ne_jax.atomic import atomic_directory
from ne_jax.data.ply import write_ply
from ne_jax.edit.targets import EditError, EditSource, edit_target
from ne_jax.geometry.points import PointState

EDIT_PLY = "edit.ply"
"""The indexed PLY of the edit inside a run directory written by :func:`save_view_edit`."""


class SelectionError(EditError):
    """An edit step asked for on a selection it cannot use (no points, or indices out of range)."""


def quat_to_matrix(wxyz) -> np.ndarray:
    """Rotation matrix ``[3, 3]`` float64 of a quaternion ``(w, x, y, z)`` (normalised first)."""
    q = np.asarray(wxyz, np.float64).reshape(4)
    n = np.linalg.norm(q)
    if not (np.isfinite(n) and n > 0):
        raise ValueError(f"quat_to_matrix: expected a non-zero finite quaternion (w, x, y, z), found {q.tolist()}")
    w, x, y, z = q / n
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def euler_deg_to_matrix(angles_deg) -> np.ndarray:
    """``R = Rz @ Ry @ Rx`` ``[3, 3]`` of rotations about the world ``x``, ``y``, ``z`` axes (degrees)."""
    ax, ay, az = np.deg2rad(np.asarray(angles_deg, np.float64).reshape(3))
    cx, sx, cy, sy, cz, sz = np.cos(ax), np.sin(ax), np.cos(ay), np.sin(ay), np.cos(az), np.sin(az)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ ry @ rx


def matrix_to_euler_deg(rot) -> np.ndarray:
    """``[3]`` angles (degrees) about ``x``, ``y``, ``z`` with :func:`euler_deg_to_matrix` of them equal
    to ``rot`` ``[3, 3]`` (``y`` in ``[-90, 90]``)."""
    r = np.asarray(rot, np.float64)
    ay = np.arcsin(np.clip(-r[2, 0], -1.0, 1.0))
    if abs(r[2, 0]) < 1 - 1e-9:
        ax, az = np.arctan2(r[2, 1], r[2, 2]), np.arctan2(r[1, 0], r[0, 0])
    else:  # gimbal lock: put the whole turn about z
        ax, az = 0.0, np.arctan2(-r[0, 1], r[1, 1])
    return np.rad2deg(np.array([ax, ay, az]))


def offsets_to_model(frame, translation, angles_deg) -> tuple[np.ndarray, np.ndarray]:
    """The viewer's move fields, in the capture's coordinates (``translation`` ``[3]`` in its units,
    ``angles_deg`` ``[3]`` about its axes as :func:`euler_deg_to_matrix` reads them), as the model
    frame's translation ``[3]`` and rotation ``[3, 3]``; ``frame``: the model's
    :class:`~ne_jax.data.scene.Normalisation` (identity for a NeRF Synthetic scene)."""
    rn = np.asarray(frame.rotation, np.float64)
    return (frame.scale * rn @ np.asarray(translation, np.float64).reshape(3),
            rn @ euler_deg_to_matrix(angles_deg) @ rn.T)


def offsets_to_capture(frame, translation, rotation) -> tuple[np.ndarray, np.ndarray]:
    """The inverse of :func:`offsets_to_model`: the model frame's ``translation`` ``[3]`` and
    ``rotation`` ``[3, 3]`` as the capture's translation ``[3]`` and angles ``[3]`` (degrees)."""
    rn = np.asarray(frame.rotation, np.float64)
    return (rn.T @ np.asarray(translation, np.float64).reshape(3) / frame.scale,
            matrix_to_euler_deg(rn.T @ np.asarray(rotation, np.float64) @ rn))


def matrix_to_quat(rot) -> np.ndarray:
    """``[4]`` quaternion ``(w, x, y, z)`` (``w >= 0``) of a rotation matrix ``[3, 3]``."""
    r = np.asarray(rot, np.float64)
    t = np.trace(r)
    if t > 0:
        s = 2.0 * np.sqrt(t + 1.0)
        q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = 2.0 * np.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        q = [(r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s]
    elif r[1, 1] > r[2, 2]:
        s = 2.0 * np.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        q = [(r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        q = [(r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return -q if q[0] < 0 else q


@dataclasses.dataclass(frozen=True)
class Region:
    """A selection region: ``kind`` ``"box"`` (``size`` the full edge lengths ``[3]``, oriented by
    ``rotation``) or ``"sphere"`` (``size[0]`` the radius), centred at ``center`` ``[3]``;
    ``rotation`` ``[3, 3]`` maps the region's axes to the world's."""

    kind: str
    center: tuple[float, float, float]
    size: tuple[float, float, float]
    rotation: tuple[tuple[float, ...], ...] = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))

    def __post_init__(self):
        if self.kind not in ("box", "sphere"):
            raise ValueError(f"Region.kind: expected 'box' or 'sphere', found {self.kind!r}")
        size = np.asarray(self.size, np.float64)
        if size.shape != (3,) or not (np.isfinite(size).all() and (size > 0).all()):
            raise ValueError(f"Region.size: expected 3 positive finite lengths, found {self.size!r}")
        if np.asarray(self.center, np.float64).shape != (3,) or np.asarray(self.rotation).shape != (3, 3):
            raise ValueError(f"Region: expected center [3] and rotation [3, 3], found {np.shape(self.center)} "
                             f"and {np.shape(self.rotation)}")

    @classmethod
    def make(cls, kind: str, center, size, wxyz=(1.0, 0.0, 0.0, 0.0)) -> Region:
        """A region from arrays; ``size`` a scalar (a cube's edge, a sphere's radius) or ``[3]``."""
        size = np.broadcast_to(np.asarray(size, np.float64), (3,))
        rot = quat_to_matrix(wxyz)
        return cls(kind, tuple(map(float, np.asarray(center, np.float64).reshape(3))), tuple(map(float, size)),
                   tuple(tuple(map(float, r)) for r in rot))

    def contains(self, xyz) -> np.ndarray:
        """``[N]`` bool: which of ``xyz`` ``[N, 3]`` lie inside (boundary included)."""
        local = (np.asarray(xyz, np.float64) - np.asarray(self.center)) @ np.asarray(self.rotation)
        if self.kind == "sphere":
            return np.einsum("ij,ij->i", local, local) <= self.size[0] ** 2
        return (np.abs(local) <= 0.5 * np.asarray(self.size)).all(axis=1)


@dataclasses.dataclass(frozen=True)
class Transform:
    """``x -> pivot + translation + scale * rotation @ (x - pivot)``; ``rotation`` ``[3, 3]``."""

    rotation: tuple[tuple[float, ...], ...] = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    translation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    scale: float = 1.0
    pivot: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self):
        r = np.asarray(self.rotation, np.float64)
        if r.shape != (3, 3) or not np.allclose(r @ r.T, np.eye(3), atol=1e-5) or np.linalg.det(r) < 0:
            raise ValueError(f"Transform.rotation: expected a 3x3 rotation matrix, found {self.rotation!r}")
        if not (np.isfinite(self.scale) and self.scale > 0):
            raise ValueError(f"Transform.scale: expected a positive finite factor, found {self.scale!r}")
        if not (np.isfinite(self.translation).all() and np.isfinite(self.pivot).all()):
            raise ValueError(f"Transform: expected finite translation and pivot, found {self.translation!r}, "
                             f"{self.pivot!r}")

    @classmethod
    def from_gizmo(cls, pivot, start_wxyz, end_position, end_wxyz, scale: float = 1.0) -> Transform:
        """The motion of a gizmo placed at ``pivot`` with orientation ``start_wxyz`` and dragged to
        ``end_position`` / ``end_wxyz``, with a uniform ``scale`` about the pivot."""
        rot = quat_to_matrix(end_wxyz) @ quat_to_matrix(start_wxyz).T
        pivot = np.asarray(pivot, np.float64).reshape(3)
        return cls(tuple(tuple(map(float, r)) for r in rot),
                   tuple(map(float, np.asarray(end_position, np.float64).reshape(3) - pivot)), float(scale),
                   tuple(map(float, pivot)))

    @classmethod
    def from_euler(cls, pivot, translation=(0.0, 0.0, 0.0), angles_deg=(0.0, 0.0, 0.0),
                   scale: float = 1.0) -> Transform:
        """Rotation ``Rz Ry Rx`` of ``angles_deg`` about ``pivot``, then ``translation`` and ``scale``."""
        rot = euler_deg_to_matrix(angles_deg)
        return cls(tuple(tuple(map(float, r)) for r in rot), tuple(map(float, np.asarray(translation).reshape(3))),
                   float(scale), tuple(map(float, np.asarray(pivot).reshape(3))))

    def apply(self, xyz) -> np.ndarray:
        """``[N, 3]`` float64 moved positions of ``xyz`` ``[N, 3]``."""
        p = np.asarray(self.pivot)
        return p + np.asarray(self.translation) + self.scale * (np.asarray(xyz, np.float64) - p) @ np.asarray(
            self.rotation).T

    @property
    def is_identity(self) -> bool:
        return (np.allclose(self.rotation, np.eye(3), atol=0) and not np.any(self.translation)
                and self.scale == 1.0)


@dataclasses.dataclass(frozen=True)
class ViewEdit:
    """An edit built in the viewer: ``xyz`` ``[C, 3]`` float32 target position of every slot,
    ``alive`` ``[C]`` bool the unedited model's alive points and ``deleted`` ``[C]`` bool the alive
    points deleted so far. Every step returns a new one (undo keeps the old)."""

    xyz: np.ndarray
    alive: np.ndarray
    deleted: np.ndarray

    @classmethod
    def identity(cls, points: PointState) -> ViewEdit:
        """No edit of ``points``."""
        alive = np.asarray(points.alive, bool)
        return cls(np.asarray(points.xyz, np.float32).copy(), alive.copy(), np.zeros_like(alive))

    @classmethod
    def from_source(cls, points: PointState, edit: EditSource) -> ViewEdit:
        """The edit ``edit`` (an :class:`~ne_jax.edit.deformations.Edit`, a ``.npy``/``.ply`` file or
        rows; see :func:`~ne_jax.edit.targets.edit_target`) of ``points``."""
        target = edit_target(points, edit)
        return cls(np.asarray(target.xyz, np.float32), np.asarray(points.alive, bool).copy(),
                   np.asarray(target.deleted, bool))

    @property
    def remaining(self) -> np.ndarray:
        """``[C]`` bool: alive and not deleted (the points a selection can pick)."""
        return self.alive & ~self.deleted

    def rows(self) -> np.ndarray:
        """``[C, 3]`` float32 rows for :func:`~ne_jax.edit.model.edit_model`: the target of every slot,
        NaN rows for deleted points."""
        rows = self.xyz.copy()
        rows[self.deleted] = np.nan
        return rows

    def changed(self, points: PointState) -> bool:
        """Whether this edit moves or deletes any point of ``points``."""
        before = np.asarray(points.xyz, np.float32)[self.alive]
        return bool(self.deleted.any() or (self.xyz[self.alive] != before).any())


def _check_selection(edit: ViewEdit, indices, what: str) -> np.ndarray:
    idx = np.asarray(indices)
    if idx.ndim != 1 or (idx.size and not np.issubdtype(idx.dtype, np.integer)):
        raise SelectionError(f"{what}: expected a 1-D array of point indices, found shape {idx.shape} "
                             f"dtype {idx.dtype}")
    if idx.size == 0:
        raise SelectionError(f"{what}: expected a selection of at least one point, found none selected "
                             "(place the region over the cloud and select again)")
    idx = idx.astype(np.int64)
    bad = (idx < 0) | (idx >= edit.xyz.shape[0])
    if bad.any():
        raise SelectionError(f"{what}: expected indices in [0, {edit.xyz.shape[0]}), found {int(idx[bad][0])}")
    gone = ~edit.remaining[idx]
    if gone.any():
        raise SelectionError(f"{what}: expected indices of points that are alive and not deleted, found "
                             f"{int(gone.sum())} that are not (first: {int(idx[gone][0])})")
    return np.unique(idx)


def select_region(edit: ViewEdit, region: Region) -> np.ndarray:
    """``[K]`` int64 sorted slots of the remaining points (alive, not deleted) inside ``region``."""
    inside = region.contains(edit.xyz) & edit.remaining
    return np.flatnonzero(inside).astype(np.int64)


def select_screen_rect(edit: ViewEdit, c2w_cv, fov_y: float, aspect: float, screen_min, screen_max) -> np.ndarray:
    """``[K]`` int64 sorted slots of the remaining points in front of a camera that project inside a
    screen rectangle. ``c2w_cv`` ``[4, 4]`` (or ``[3, 4]``) camera-to-world in the OpenCV convention
    (``+z`` forward, ``+y`` down; viser's), ``fov_y`` the vertical field of view (radians), ``aspect``
    width / height; ``screen_min``/``screen_max`` the rectangle's corners in ``[0, 1]`` image
    coordinates (``(0, 0)`` the top-left)."""
    c2w = np.asarray(c2w_cv, np.float64)
    cam = (edit.xyz.astype(np.float64) - c2w[:3, 3]) @ c2w[:3, :3]
    z = cam[:, 2]
    front = z > 1e-9
    t = np.tan(0.5 * fov_y)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = 0.5 + cam[:, 0] / np.where(front, z, 1.0) / (2 * t * aspect)
        v = 0.5 + cam[:, 1] / np.where(front, z, 1.0) / (2 * t)
    lo, hi = np.minimum(screen_min, screen_max), np.maximum(screen_min, screen_max)
    inside = front & (u >= lo[0]) & (u <= hi[0]) & (v >= lo[1]) & (v <= hi[1]) & edit.remaining
    return np.flatnonzero(inside).astype(np.int64)


def selection_center(edit: ViewEdit, indices) -> np.ndarray:
    """``[3]`` float64 centre of the selected points' bounding box (the gizmo's pivot)."""
    idx = _check_selection(edit, indices, "selection_center")
    xyz = edit.xyz[idx].astype(np.float64)
    return 0.5 * (xyz.min(0) + xyz.max(0))


def move_points(edit: ViewEdit, indices, transform: Transform) -> ViewEdit:
    """``edit`` with the selected points moved by ``transform``. Raises :class:`SelectionError` for an
    empty selection or indices of points that are dead or deleted."""
    idx = _check_selection(edit, indices, "move")
    xyz = edit.xyz.copy()
    xyz[idx] = transform.apply(xyz[idx]).astype(np.float32)
    if not np.isfinite(xyz[idx]).all():
        raise SelectionError("move: expected finite moved positions, found NaN/inf (check the transform)")
    return dataclasses.replace(edit, xyz=xyz)


def delete_points(edit: ViewEdit, indices) -> ViewEdit:
    """``edit`` with the selected points deleted. Raises :class:`SelectionError` for an empty
    selection, or one that would delete every remaining point."""
    idx = _check_selection(edit, indices, "delete")
    deleted = edit.deleted.copy()
    deleted[idx] = True
    if not (edit.alive & ~deleted).any():
        raise SelectionError(f"delete: expected at least one point to remain, found all {int(edit.alive.sum())} "
                             "alive points selected for deletion")
    return dataclasses.replace(edit, deleted=deleted)


def write_edit_ply(path: str | os.PathLike, edit: ViewEdit, frame=None) -> int:
    """Write ``edit`` as the indexed PLY that ``ne-jax edit --edit FILE.ply`` reads (atomically):
    ``x y z`` float32 and ``index`` int32 (the slot) of every remaining point; deleted points are left
    out. ``frame`` (the model's :class:`~ne_jax.data.scene.Normalisation`): positions in the
    capture's coordinates, as edit files are read. Returns the number of points written."""
    keep = np.flatnonzero(edit.remaining)
    xyz = edit.xyz[keep].astype(np.float64)
    xyz = (xyz if frame is None else frame.to_capture(xyz)).astype(np.float32)
    write_ply(path, {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "index": keep.astype(np.int32)})
    return int(keep.size)


def save_view_edit(model, edit: ViewEdit, out_dir: str | os.PathLike, *, ist: bool = True, cfg=None,
                   label: str = "viewer", context=None) -> tuple[object, dict]:
    """Apply ``edit`` to ``model`` (a :class:`~ne_jax.train.model.TrainedModel`) and write the edited
    run directory to ``out_dir`` with the edit's indexed PLY inside it (:data:`EDIT_PLY`), all in one
    atomic step: ``out_dir`` appears complete or not at all (an existing one is replaced only on
    success). The edited model is made from the PLY just written, as ``ne-jax edit RUN --edit
    out_dir/edit.ply`` makes it. ``context``: :func:`~ne_jax.edit.model.model_edit_context` of
    ``model`` and ``cfg``, if held. Returns ``(edited model, report)``."""
    from ne_jax.edit.apply import EditConfig
    from ne_jax.edit.model import edit_model

    cfg = EditConfig() if cfg is None else cfg
    if not edit.changed(model.state.point_state(model.scene.points)):
        raise SelectionError(f"save {out_dir}: expected an edit that moves or deletes points, found none "
                             "(nothing to save)")
    out_dir = Path(out_dir)
    with atomic_directory(out_dir) as tmp:
        run_tmp = tmp / "run"
        ply_tmp = tmp / EDIT_PLY
        write_edit_ply(ply_tmp, edit, model.frame)
        edited, report = edit_model(model, ply_tmp, run_tmp, ist=ist, cfg=cfg, label=label, context=context)
        os.replace(ply_tmp, run_tmp / EDIT_PLY)
        # the run directory becomes out_dir itself: move its content up one level
        for child in run_tmp.iterdir():
            os.replace(child, tmp / child.name)
        run_tmp.rmdir()
    return edited.replace(run_dir=out_dir), report


__all__ = ["EDIT_PLY", "Region", "SelectionError", "Transform", "ViewEdit", "delete_points", "euler_deg_to_matrix",
           "matrix_to_euler_deg", "matrix_to_quat", "move_points", "offsets_to_capture", "offsets_to_model",
           "quat_to_matrix", "save_view_edit", "select_region", "select_screen_rect", "selection_center",
           "write_edit_ply"]

"""Edits as vectorised functions of 3-D points.

An :class:`Edit` maps original positions ``P [N, 3]`` to edited positions ``Q(P) [N, 3]`` and a
deletion mask ``[N]`` (decided in the *original* space). The same function is applied to the
benchmark's mesh vertices (to render ground truth of the edited scene) and to a model's point cloud,
so the two are edited identically. Everything is written in ``jax.numpy``: the functions are
jit-able and differentiable in their parameters (``bend_points(p, angle=...)`` with a traced angle).

Building blocks: regions (``[N, 3] -> [N] bool``), the pure deformations ``bend_points``,
``twist_points``, ``rotate_points``, ``cut_points``, and factories returning named :class:`Edit`s.
A whole-scene rigid edit (:func:`rigid_scene`) also carries its motion ``T`` (``Edit.rigid``,
``Edit.matrix``) and whether the environment moves with it (``Edit.moves_environment``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from ne_jax.numerics import safe_normalize

Region = Callable[[jax.Array], jax.Array]
"""A region: points ``[N, 3]`` -> membership mask ``[N]`` (bool)."""


def _vec(x) -> jax.Array:
    return jnp.asarray(x, jnp.float32)


# ------------------------------------------------------------------------------------- regions


def halfspace(normal, offset: float) -> Region:
    """Points with ``normal . p > offset``."""
    n = safe_normalize(_vec(normal))
    return lambda p: p @ n > offset


def ball(center, radius: float) -> Region:
    """Points within ``radius`` of ``center``."""
    return lambda p: jnp.sum((p - _vec(center)) ** 2, axis=-1) < radius**2


def axis_box(lo, hi) -> Region:
    """Points inside the axis-aligned box ``[lo, hi]``."""
    return lambda p: jnp.all((p > _vec(lo)) & (p < _vec(hi)), axis=-1)


def vertical_cylinder(center_xy, radius: float, z_lo: float = -np.inf, z_hi: float = np.inf) -> Region:
    """Points within ``radius`` of the vertical line through ``center_xy``, with ``z_lo < z < z_hi``."""
    def region(p):
        d2 = jnp.sum((p[:, :2] - _vec(center_xy)) ** 2, axis=-1)
        return (d2 < radius**2) & (p[:, 2] > z_lo) & (p[:, 2] < z_hi)
    return region


def beyond_radius(radius: float, center_xy=(0.0, 0.0)) -> Region:
    """Points farther than ``radius`` from the vertical line through ``center_xy``."""
    return lambda p: jnp.sum((p[:, :2] - _vec(center_xy)) ** 2, axis=-1) > radius**2


def intersection(*regions: Region) -> Region:
    """Points in every one of ``regions``."""
    def region(p):
        mask = regions[0](p)
        for r in regions[1:]:
            mask = mask & r(p)
        return mask
    return region


# ------------------------------------------------------------------------------- deformations


def rotation_matrix(axis, angle) -> jax.Array:
    """Rodrigues rotation ``[3, 3]`` by ``angle`` (radians) about ``axis`` (any length > 0)."""
    k = safe_normalize(_vec(axis))
    kx = jnp.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    angle = jnp.asarray(angle, jnp.float32)
    return jnp.eye(3) + jnp.sin(angle) * kx + (1.0 - jnp.cos(angle)) * (kx @ kx)


def rotate_points(p: jax.Array, axis, angle, pivot) -> jax.Array:
    """Rotate ``p [N, 3]`` by ``angle`` about the line through ``pivot`` along ``axis``."""
    pivot = _vec(pivot)
    return (p - pivot) @ rotation_matrix(axis, angle).T + pivot


def bend_points(p: jax.Array, center, along, toward, angle, length: float) -> jax.Array:
    """Bend ``p [N, 3]`` so the line through ``center`` along ``along`` becomes a circular arc that
    turns by ``angle`` (radians) over ``length`` towards ``toward`` (Barr's bend, isometric along the
    centre line). Smooth in ``angle``, exact identity at ``angle = 0``."""
    center = _vec(center)
    e_u = safe_normalize(_vec(along))
    e_w = safe_normalize(_vec(toward) - jnp.dot(_vec(toward), e_u) * e_u)
    d = p - center
    u, w = d @ e_u, d @ e_w
    rest = d - u[:, None] * e_u - w[:, None] * e_w
    k = jnp.asarray(angle, jnp.float32) / length  # curvature
    theta = k * u
    # sin(theta)/k and (1 - cos(theta))/k written with sinc so that k -> 0 is exact and smooth.
    sin_over_k = u * jnp.sinc(theta / jnp.pi)
    one_minus_cos_over_k = 0.5 * k * u**2 * jnp.sinc(theta / (2.0 * jnp.pi)) ** 2
    u_new = sin_over_k - w * jnp.sin(theta)
    w_new = one_minus_cos_over_k + w * jnp.cos(theta)
    return center + rest + u_new[:, None] * e_u + w_new[:, None] * e_w


def twist_points(p: jax.Array, center, axis, rate) -> jax.Array:
    """Rotate each point about the line through ``center`` along ``axis`` by ``rate`` radians per
    unit of distance along the axis (measured from ``center``)."""
    center = _vec(center)
    k = safe_normalize(_vec(axis))
    d = p - center
    along = d @ k
    angle = jnp.asarray(rate, jnp.float32) * along
    kxd = jnp.cross(jnp.broadcast_to(k, d.shape), d)
    kdot = along[:, None] * k
    c, s = jnp.cos(angle)[:, None], jnp.sin(angle)[:, None]
    return center + d * c + kxd * s + kdot * (1.0 - c)


def cut_points(p: jax.Array, point, normal, gap) -> jax.Array:
    """Cut along the plane through ``point`` with ``normal`` and pull the two sides apart by ``gap``
    (each side moves ``gap / 2``; points on the plane go with the negative side)."""
    n = safe_normalize(_vec(normal))
    side = jnp.where((p - _vec(point)) @ n > 0.0, 1.0, -1.0)
    return p + (0.5 * jnp.asarray(gap, jnp.float32) * side)[:, None] * n


# ------------------------------------------------------------------------------------- edits


@dataclass(frozen=True)
class Edit:
    """A named edit ``P -> (Q(P), deleted)``. ``move``: ``[N, 3] -> [N, 3]``; ``delete``: ``[N, 3] ->
    [N]`` bool evaluated on the original positions, or ``None`` for no deletion."""

    name: str
    kind: str
    move: Callable[[jax.Array], jax.Array]
    delete: Region | None = None
    description: str = ""
    rigid: tuple[tuple[float, ...], ...] | None = None
    """The rigid motion ``T`` of the whole scene as a ``4x4`` row-major nested tuple (hashable, so an
    edit stays a static jit argument) when ``move(p) = R p + t`` for every point; ``None`` for any
    other edit. :attr:`matrix` gives it as an array."""
    moves_environment: bool = False
    """For a whole-scene rigid edit: the lights and the environment move with the scene by ``T``, so
    the edited scene seen from camera ``c2w`` is the original seen from ``T^-1 @ c2w``. Only the
    benchmark's ground truth reads it; ``move`` and ``delete`` are the same either way."""

    def __call__(self, points) -> tuple[jax.Array, jax.Array]:
        """``(moved [N, 3], deleted [N] bool)`` for original ``points [N, 3]``."""
        p = _vec(points)
        deleted = self.delete(p) if self.delete is not None else jnp.zeros(p.shape[0], bool)
        return self.move(p), deleted

    def apply(self, points) -> tuple[jax.Array, jax.Array]:
        """Like calling the edit, but compiled once per edit (for large host-side clouds)."""
        return _apply_compiled(self, _vec(points))

    @property
    def matrix(self) -> np.ndarray | None:
        """``T`` ``[4, 4]`` float64 (see :attr:`rigid`), or ``None`` for an edit that is not one
        whole-scene rigid motion. Cameras move with the scene as ``T @ c2w``."""
        return None if self.rigid is None else np.array(self.rigid, np.float64)


_apply_compiled = jax.jit(lambda edit, p: edit(p), static_argnums=0)


def bend(name: str, center, along, toward, angle_deg: float, length: float) -> Edit:
    """A smooth non-rigid bend (see :func:`bend_points`)."""
    a = np.deg2rad(angle_deg)
    return Edit(name, "bend", lambda p: bend_points(p, center, along, toward, a, length),
                description=f"bend by {angle_deg:g} deg over {length:g} along {tuple(along)} towards {tuple(toward)}")


def twist(name: str, center, axis, degrees_per_unit: float) -> Edit:
    """A smooth non-rigid twist (see :func:`twist_points`)."""
    rate = np.deg2rad(degrees_per_unit)
    return Edit(name, "twist", lambda p: twist_points(p, center, axis, rate),
                description=f"twist by {degrees_per_unit:g} deg per unit about {tuple(axis)}")


def rigid_part(name: str, region: Region, axis, angle_deg: float, pivot, translation=(0.0, 0.0, 0.0),
               part: str = "a part") -> Edit:
    """Rotate (then translate) the points of ``region`` rigidly; the rest stays. ``part`` names the
    region in the description."""
    a, t = np.deg2rad(angle_deg), _vec(translation)
    def move(p):
        return jnp.where(region(p)[:, None], rotate_points(p, axis, a, pivot) + t, p)
    return Edit(name, "rigid", move, description=f"rotate {part} by {angle_deg:g} deg about {tuple(axis)}")


def rigid_motion(axis, angle_deg: float, pivot=(0.0, 0.0, 0.0), translation=(0.0, 0.0, 0.0)) -> np.ndarray:
    """``T`` ``[4, 4]`` float64: rotate by ``angle_deg`` about the line through ``pivot`` along
    ``axis`` (any length > 0), then translate by ``translation``: ``T p = R (p - pivot) + pivot + t``."""
    k = np.asarray(axis, np.float64)
    k = k / np.linalg.norm(k)
    a = np.deg2rad(angle_deg)
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    rot = np.eye(3) + np.sin(a) * kx + (1.0 - np.cos(a)) * (kx @ kx)
    pivot = np.asarray(pivot, np.float64)
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = pivot - rot @ pivot + np.asarray(translation, np.float64)
    return out


def rigid_scene(name: str, axis, angle_deg: float, pivot=(0.0, 0.0, 0.0), translation=(0.0, 0.0, 0.0),
                moves_environment: bool = False) -> Edit:
    """Move the whole scene by one rigid motion ``T`` (:func:`rigid_motion`); ``edit.rigid`` /
    ``edit.matrix`` expose ``T``. ``moves_environment``: the benchmark's lights and sky move with the
    scene (see :attr:`Edit.moves_environment`); the point function is the same either way.
    ``move(p) = p @ R^T + t`` with ``R``, ``t`` the float32 rounding of ``T``."""
    motion = rigid_motion(axis, angle_deg, pivot, translation)
    rot, shift = motion[:3, :3].astype(np.float32), motion[:3, 3].astype(np.float32)

    def move(p):
        return p @ jnp.asarray(rot.T) + jnp.asarray(shift)

    axis_unit = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    env = "lights and sky turn with it" if moves_environment else "lights and sky stay"
    shift_text = f", then shift by {tuple(float(x) for x in translation)}" if np.any(translation) else ""
    return Edit(name, "rigid_scene", move, description=(
        f"turn the whole scene by {angle_deg:g} deg about axis {tuple(np.round(axis_unit, 4).tolist())} through "
        f"{tuple(float(x) for x in pivot)}{shift_text}; {env}"),
        rigid=tuple(tuple(float(x) for x in row) for row in motion), moves_environment=moves_environment)


def cut(name: str, point, normal, gap: float) -> Edit:
    """A non-continuous cut that pulls the two sides of a plane apart (see :func:`cut_points`)."""
    return Edit(name, "cut", lambda p: cut_points(p, point, normal, gap),
                description=f"cut at plane through {tuple(point)} normal {tuple(normal)}, gap {gap:g}")


def delete_part(name: str, region: Region, part: str = "a part") -> Edit:
    """Delete the points of ``region``; nothing moves. ``part`` names the region in the description."""
    return Edit(name, "delete", lambda p: p, region, description=f"delete {part}")


def compose(name: str, *edits: Edit) -> Edit:
    """Apply ``edits`` in order; a point is deleted if any edit deletes it (at its position then)."""
    def move(p):
        for e in edits:
            p = e.move(p)
        return p

    def delete(p):
        mask = jnp.zeros(p.shape[0], bool)
        for e in edits:
            if e.delete is not None:
                mask = mask | e.delete(p)
            p = e.move(p)
        return mask

    return Edit(name, "compose", move, delete, description=" then ".join(e.name for e in edits))


def jacobian_normals(move: Callable[[jax.Array], jax.Array], points: jax.Array, normals: jax.Array) -> jax.Array:
    """Normals carried by a deformation ``move`` (``[N, 3] -> [N, 3]``): ``n' = normalize(J^{-T} n)``
    with ``J`` the ``3x3`` Jacobian of ``move`` at each point; zero normals stay zero. Differentiable
    in whatever ``move`` closes over. ``points``/``normals`` ``[N, 3]`` -> ``[N, 3]``."""
    def one(p, n):
        jac = jax.jacfwd(lambda x: move(x[None])[0])(p)
        return safe_normalize(jnp.linalg.solve(jac.T, n))
    return jax.vmap(one)(points, normals)


@partial(jax.jit, static_argnums=0)
def transform_normals(edit: Edit, points, normals) -> jax.Array:
    """Normals of the edited surface (:func:`jacobian_normals` of ``edit.move``), compiled once per
    edit. ``points``/``normals`` ``[N, 3]`` -> ``[N, 3]``."""
    return jacobian_normals(edit.move, _vec(points), _vec(normals))

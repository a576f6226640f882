"""The infinitesimal surface transformation (IST): per point, the rotation that maps directions of
the edited scene back to the original scene (paper Sec. 4; docs/design.md facts "IST").

For point ``j`` with two neighbours ``a, b`` (the same indices in both clouds) the local frames are

    original ``A = [u_a, u_b, n]``,  edited ``B = [v_a, v_b, s n']``,

with ``u = (p_a - p_j)`` projected on the tangent plane of the original normal ``n`` (and ``v`` the
same in the edited cloud with its normal ``n'``). Open3D normals are unoriented, so the sign ``s`` of
the edited normal is chosen to keep each frame's handedness (``det A`` and ``det B`` of equal sign):
an edit without reflections keeps the side of the surface a normal points to. The frame map
``M = A B^-1`` sends ``v_a -> u_a``, ``v_b -> u_b``, ``n' -> n``: on the tangent plane it is the
inverse of the edit's Jacobian, and normals go to normals. The IST is the rotation closest to ``M``
(its polar factor): for a rigid motion ``R`` it is exactly ``R^T``, like the transform between the
orthonormalised frames; for a linear map ``L = R S`` whose stretch ``S`` keeps the normal direction
it is exactly ``R^T`` whatever the two neighbours, where orthonormalising the frames would depend on
which neighbour sets the first tangent axis.

Conditioning (chosen on the host and then held fixed, like the K-D tree's topology): among the
``cfg.candidates`` nearest neighbours that are alive after the edit, the pair ``(a, b)`` maximising
``min(sin angle(u_a, u_b), sin angle(v_a, v_b))``, restricted to neighbours that the edit stretched by
at most ``cfg.max_stretch`` (a neighbour torn away by a cut or across a hinge says nothing about the
surface at ``j``). A point is *degenerate* when the best pair's sine is below ``cfg.min_sin``
(collinear or coincident neighbours), when fewer than two neighbours survive the edit, or when a
normal is zero. Degenerate points take the confidence-weighted average of their neighbours'
transforms (then the nearest rotation), over ``cfg.fill_passes`` passes so a degenerate patch fills
from its border; a point with no usable neighbour after that keeps the identity (counted). Then
``cfg.smooth_iters`` passes replace every IST by the nearest rotation to the confidence-weighted
mean over itself and its neighbours (a mean too close to singular, e.g. opposite rotations, keeps
the point's own IST).

The nearest rotation is computed by the scaled Newton iteration ``X <- (g X + (g X)^-T) / 2`` (Higham)
for a fixed number of steps: exact on rotations (a fixed point), differentiable everywhere ``M`` is
invertible (an SVD's gradient is undefined at repeated singular values, i.e. at every rotation).

Shapes: ``C`` slots (capacity), ``k = cfg.candidates``. Dead slots get the identity.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct
from scipy.spatial import cKDTree

from ne_jax.numerics import safe_div, safe_sqrt


@dataclasses.dataclass(frozen=True)
class ISTConfig:
    """Static IST settings (hashable)."""

    candidates: int = 8
    """Nearest neighbours (alive after the edit) among which the frame pair is chosen, and over which
    degenerate points average and the smoothing runs."""
    min_sin: float = 0.25
    """A pair whose tangent directions make an angle with ``|sin| <`` this (in either cloud) is
    degenerate."""
    max_stretch: float = 4.0
    """A neighbour whose distance changed by more than this factor (either way) is not used."""
    fill_passes: int = 3
    """Passes of neighbour averaging that fill degenerate points."""
    smooth_iters: int = 1
    """Passes of confidence-weighted smoothing over neighbours (0: off)."""
    polar_iters: int = 12
    """Newton steps of the nearest-rotation iteration."""

    def __post_init__(self):
        if int(self.candidates) < 2:
            raise ValueError(f"ISTConfig.candidates: expected an integer >= 2, found {self.candidates}")
        if not 0.0 < self.min_sin < 1.0:
            raise ValueError(f"ISTConfig.min_sin: expected a value in (0, 1), found {self.min_sin}")
        if not self.max_stretch > 1.0:
            raise ValueError(f"ISTConfig.max_stretch: expected a value > 1, found {self.max_stretch}")
        if min(int(self.fill_passes), int(self.smooth_iters)) < 0 or int(self.polar_iters) < 1:
            raise ValueError("ISTConfig: expected fill_passes >= 0, smooth_iters >= 0 and polar_iters >= 1, found "
                             f"{self.fill_passes}, {self.smooth_iters}, {self.polar_iters}")


@struct.dataclass
class ISTPlan:
    """The discrete choices of an IST computation (host-side, held fixed under ``jax.grad``).

    Attributes:
        pair: ``[C, 2]`` int32 the two frame neighbours of each slot (0 where unused).
        good: ``[C]`` bool the slot's frame is well conditioned (alive, two usable neighbours, normals).
        alive: ``[C]`` bool the slot is alive after the edit.
        neighbors: ``[C, k]`` int32 neighbours alive after the edit, nearest first (0 where unused).
        weight: ``[C, k]`` their confidences (0 where unused) for filling and smoothing.
        self_weight: ``[C]`` the slot's own confidence (0 for dead slots) for smoothing.
    """

    pair: jax.Array
    good: jax.Array
    alive: jax.Array
    neighbors: jax.Array
    weight: jax.Array
    self_weight: jax.Array


# ------------------------------------------------------------------------------ 3x3 linear algebra


def _det3(m: jax.Array) -> jax.Array:
    """``[..., 3, 3] -> [...]`` determinant by cofactors."""
    return jnp.sum(m[..., 0, :] * jnp.cross(m[..., 1, :], m[..., 2, :]), axis=-1)


def _inv_transpose3(m: jax.Array) -> tuple[jax.Array, jax.Array]:
    """``(M^-T, det M)`` for ``[..., 3, 3]`` by the cofactor matrix; ``M^-T`` is 0 where ``det M = 0``."""
    r0, r1, r2 = m[..., 0, :], m[..., 1, :], m[..., 2, :]
    cof = jnp.stack([jnp.cross(r1, r2), jnp.cross(r2, r0), jnp.cross(r0, r1)], axis=-2)
    det = jnp.sum(r0 * cof[..., 0, :], axis=-1)
    return safe_div(cof, det[..., None, None]), det


def nearest_rotation(m: jax.Array, iters: int = 12) -> jax.Array:
    """The orthogonal polar factor of ``m [..., 3, 3]`` (the rotation nearest in Frobenius norm when
    ``det m > 0``), by ``iters`` scaled Newton steps. Exact (a fixed point) on rotations; finite
    everywhere (a singular ``m`` gives a finite, meaningless result: callers guard it)."""
    x = m
    for _ in range(int(iters)):
        inv_t, _ = _inv_transpose3(x)
        norm_x = safe_sqrt(jnp.sum(x * x, axis=(-2, -1)))
        norm_inv = safe_sqrt(jnp.sum(inv_t * inv_t, axis=(-2, -1)))
        g = jnp.sqrt(safe_div(norm_inv, norm_x, 1.0))
        g = jnp.where(g > 0, g, 1.0)[..., None, None]
        x = 0.5 * (g * x + inv_t / g)
    return x


def _tangent(d: jax.Array, n: jax.Array) -> jax.Array:
    return d - jnp.sum(d * n, axis=-1, keepdims=True) * n


# ------------------------------------------------------------------------------ planning (host)


def _unit_rows(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    length = np.linalg.norm(x, axis=-1)
    return x / np.where(length > 0, length, 1.0)[..., None], length


@dataclasses.dataclass(frozen=True, eq=False)
class NeighborTable:
    """The IST's neighbour table of one cloud for one set of points alive after the edit (host side,
    read-only arrays), made by :func:`ist_neighbors`. Every edit of the cloud that deletes the same
    points shares it: hold it and pass it back.

    Attributes:
        xyz0: ``[C, 3]`` float64 the original positions it was made on.
        alive: ``[C]`` bool the points alive after the edit, among which neighbours are chosen.
        candidates: ``k``, the neighbours per slot (``ISTConfig.candidates``).
        neighbors: ``[C, k]`` int64 neighbours of every slot among ``alive``, nearest first (0 where unused).
        valid: ``[C, k]`` bool which entries of ``neighbors`` are used.
    """

    xyz0: np.ndarray
    alive: np.ndarray
    candidates: int
    neighbors: np.ndarray
    valid: np.ndarray


def ist_neighbors(cfg: ISTConfig, xyz0, alive1, held: NeighborTable | None = None) -> NeighborTable:
    """The ``k = cfg.candidates`` nearest neighbours of every slot of the original cloud
    ``xyz0 [C, 3]`` among the points ``alive1 [C]`` alive after the edit (host).

    ``held``: a table made earlier for the same cloud, returned as it is when made for the same
    ``alive1`` (otherwise a new table is made: the edit deletes other points).

    Raises:
        ValueError: ``held`` made for another cloud or another ``cfg.candidates``.
    """
    p0 = np.asarray(xyz0, np.float64)
    alive = np.asarray(alive1, bool)
    k = int(cfg.candidates)
    if held is not None:
        if held.candidates != k:
            raise ValueError(f"held: expected a neighbour table of {k} candidates (ISTConfig.candidates), found one "
                             f"of {held.candidates}; make it with the edit's config")
        if held.xyz0.shape != p0.shape or not np.array_equal(held.xyz0, p0, equal_nan=True):
            raise ValueError(f"held: expected the neighbour table of this cloud ({p0.shape[0]} slots), found one made "
                             f"for another cloud ({held.xyz0.shape[0]} slots"
                             f"{', other positions' if held.xyz0.shape == p0.shape else ''}); make it from the "
                             "unedited cloud this edit starts from")
        if np.array_equal(held.alive, alive):
            return held
    p0 = p0.copy()  # kept with the table: the caller may write to its own array later
    neighbors, valid = _neighbor_table(p0, alive, cfg)
    alive = alive.copy()
    for a in (p0, alive, neighbors, valid):
        a.flags.writeable = False
    return NeighborTable(xyz0=p0, alive=alive, candidates=k, neighbors=neighbors, valid=valid)


def _neighbor_table(p0: np.ndarray, alive: np.ndarray, cfg: ISTConfig) -> tuple[np.ndarray, np.ndarray]:
    c, k = alive.size, int(cfg.candidates)
    idx = np.flatnonzero(alive)
    neighbors = np.zeros((c, k), np.int64)
    valid = np.zeros((c, k), bool)
    if idx.size > 1:
        kk = min(k + 1, idx.size)
        _, nn = cKDTree(p0[idx]).query(p0[idx], k=kk, workers=-1)
        nn = idx[np.asarray(nn).reshape(idx.size, kk)]
        not_self = nn != idx[:, None]
        # drop the point itself (first, unless a duplicate sits at distance 0) and keep k
        order = np.argsort(~not_self, axis=1, kind="stable")
        nn = np.take_along_axis(nn, order, 1)[:, : kk - 1]
        ok = np.take_along_axis(not_self, order, 1)[:, : kk - 1]
        neighbors[idx, : kk - 1] = nn
        valid[idx, : kk - 1] = ok
    return neighbors, valid


def plan_ist(cfg: ISTConfig, xyz0, normal0, xyz1, normal1, alive1, confidence,
             neighbors: NeighborTable | None = None) -> ISTPlan:
    """Choose frame pairs and averaging neighbours (host, numpy float64).

    Args:
        xyz0, normal0: ``[C, 3]`` original positions and normals.
        xyz1, normal1: ``[C, 3]`` edited positions and (unoriented) normals.
        alive1: ``[C]`` bool alive after the edit.
        confidence: ``[C]`` point confidences (weights of the averages).
        neighbors: :func:`ist_neighbors` of ``xyz0`` (made for ``alive1``, or made again here).
    """
    p0, n0 = np.asarray(xyz0, np.float64), np.asarray(normal0, np.float64)
    p1, n1 = np.asarray(xyz1, np.float64), np.asarray(normal1, np.float64)
    alive = np.asarray(alive1, bool)
    conf = np.asarray(confidence, np.float64)
    c, k = alive.size, int(cfg.candidates)
    idx = np.flatnonzero(alive)
    table = ist_neighbors(cfg, p0, alive, neighbors)
    neighbors, valid = table.neighbors, table.valid
    pair = np.zeros((c, 2), np.int64)
    good = np.zeros(c, bool)
    if idx.size > 2 and k >= 2:
        j = idx[:, None]
        nb, ok = neighbors[idx], valid[idx]
        d0, d1 = p0[nb] - p0[j], p1[nb] - p1[j]
        len0, len1 = np.linalg.norm(d0, axis=-1), np.linalg.norm(d1, axis=-1)
        ratio = len1 / np.where(len0 > 0, len0, np.inf)
        usable = ok & (len0 > 0) & (len1 > 0) & (ratio <= cfg.max_stretch) & (ratio >= 1.0 / cfg.max_stretch)
        nj0, nj1 = n0[idx][:, None], n1[idx][:, None]
        u, _ = _unit_rows(d0 - np.sum(d0 * nj0, -1, keepdims=True) * nj0)
        v, _ = _unit_rows(d1 - np.sum(d1 * nj1, -1, keepdims=True) * nj1)
        combos = np.array(list(itertools.combinations(range(k), 2)))
        ia, ib = combos[:, 0], combos[:, 1]
        # |sin| of the angle between unit tangents, from their dot products (a cross product costs
        # 5x): every pair's at once as a [k, k] Gram matrix (the same sums as per pair, 2x faster)
        cos0 = np.einsum("nia,nja->nij", u, u)[:, ia, ib]
        cos1 = np.einsum("nia,nja->nij", v, v)[:, ia, ib]
        sin = np.sqrt(np.maximum(1.0 - np.maximum(cos0 * cos0, cos1 * cos1), 0.0))  # min(sin0, sin1)
        score = np.where(usable[:, ia] & usable[:, ib], sin, -1.0)
        best = np.argmax(score, axis=1)
        best_score = score[np.arange(idx.size), best]
        normals_ok = (np.linalg.norm(n0[idx], axis=-1) > 0.5) & (np.linalg.norm(n1[idx], axis=-1) > 0.5)
        good[idx] = (best_score >= cfg.min_sin) & normals_ok
        pair[idx] = np.stack([nb[np.arange(idx.size), ia[best]], nb[np.arange(idx.size), ib[best]]], 1)
    weight = np.where(valid, conf[neighbors], 0.0)
    return ISTPlan(pair=jnp.asarray(pair, jnp.int32), good=jnp.asarray(good), alive=jnp.asarray(alive),
                   neighbors=jnp.asarray(neighbors, jnp.int32), weight=jnp.asarray(weight, jnp.float32),
                   self_weight=jnp.asarray(np.where(alive, conf, 0.0), jnp.float32))


# ------------------------------------------------------------------------------ the transform (jit)


def frame_transforms(xyz0, normal0, xyz1, normal1, pair, use, iters: int = 12
                     ) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Per-slot frame rotations from the pairs: ``(ist [C, 3, 3], sign [C], det_b [C])``.

    ``sign`` orients the edited normal (``s n'`` keeps the frame's handedness); ``det_b`` is the
    edited frame's determinant (0: singular, the slot must not use its own frame). Slots outside
    ``use [C]`` compute on identity frames (so their gradients stay finite) and return the identity."""
    a, b = pair[:, 0], pair[:, 1]
    u_a, u_b = _tangent(xyz0[a] - xyz0, normal0), _tangent(xyz0[b] - xyz0, normal0)
    v_a, v_b = _tangent(xyz1[a] - xyz1, normal1), _tangent(xyz1[b] - xyz1, normal1)
    det_a = jnp.sum(jnp.cross(u_a, u_b) * normal0, axis=-1)
    det_v = jnp.sum(jnp.cross(v_a, v_b) * normal1, axis=-1)
    sign = jnp.where(det_a * det_v < 0, -1.0, 1.0).astype(normal1.dtype)
    eye = jnp.eye(3, dtype=xyz1.dtype)
    det_b = det_v * sign  # det [v_a, v_b, s n'] (columns)
    use = use & (det_b != 0)
    pick = lambda m: jnp.where(use[:, None, None], m, eye)  # noqa: E731  (double where: finite gradients)
    cols_a = pick(jnp.stack([u_a, u_b, normal0], axis=-1))  # columns
    cols_b = pick(jnp.stack([v_a, v_b, sign[:, None] * normal1], axis=-1))
    inv_bt, _ = _inv_transpose3(cols_b)
    m = cols_a @ jnp.swapaxes(inv_bt, -1, -2)  # A B^-1
    return nearest_rotation(m, iters), sign, det_b


def _average(ist: jax.Array, neighbors, weight, source: jax.Array, iters: int):
    """Nearest rotation to the ``weight``-weighted mean of the ``source`` neighbours' ISTs:
    ``(ist [C, 3, 3], has_source [C])``."""
    w = weight * source[neighbors]
    total = jnp.sum(w, axis=1)
    mean = jnp.einsum("ck,ckij->cij", w, ist[neighbors]) / jnp.where(total > 0, total, 1.0)[:, None, None]
    ok = (total > 0) & (_det3(mean) > 0.1)
    mean = jnp.where(ok[:, None, None], mean, jnp.eye(3, dtype=mean.dtype))  # finite gradients where not used
    return nearest_rotation(mean, iters), ok


@functools.partial(jax.jit, static_argnames=("cfg",))
def ist_from_plan(cfg: ISTConfig, plan: ISTPlan, xyz0, normal0, xyz1, normal1) -> tuple[jax.Array, jax.Array, dict]:
    """The IST of every slot for a fixed plan: ``(ist [C, 3, 3], normal_sign [C], counts)``.

    Differentiable in the positions (and normals); the choices in ``plan`` are constants.
    ``normal_sign`` orients ``normal1`` consistently with ``normal0`` (+1 where unknown).
    ``counts``: ``good`` frames, ``filled`` degenerate points filled from neighbours,
    ``identity`` alive points left at the identity."""
    dtype = xyz1.dtype
    eye = jnp.eye(3, dtype=dtype)
    ist, sign, det_b = frame_transforms(xyz0, normal0, xyz1, normal1, plan.pair, plan.good, cfg.polar_iters)
    good = plan.good & (det_b != 0)
    ist = jnp.where(good[:, None, None], ist, eye)
    done = good
    for _ in range(int(cfg.fill_passes)):
        avg, ok = _average(ist, plan.neighbors, plan.weight, done, cfg.polar_iters)
        fill = plan.alive & ~done & ok
        ist = jnp.where(fill[:, None, None], avg, ist)
        done = done | fill
    for _ in range(int(cfg.smooth_iters)):
        weight = jnp.concatenate([plan.self_weight[:, None], plan.weight], axis=1)
        nbrs = jnp.concatenate([jnp.arange(ist.shape[0], dtype=plan.neighbors.dtype)[:, None], plan.neighbors], axis=1)
        avg, ok = _average(ist, nbrs, weight, done, cfg.polar_iters)
        take = plan.alive & done & ok
        ist = jnp.where(take[:, None, None], avg, ist)
    ist = jnp.where(plan.alive[:, None, None], ist, eye)
    # degenerate points: orient the edited normal by the transform they received
    agree = jnp.sum(jnp.einsum("cij,cj->ci", ist, normal1) * normal0, axis=-1)
    sign = jnp.where(good, sign, jnp.where(agree < 0, -1.0, 1.0).astype(dtype))
    counts = {"good": jnp.sum(good), "filled": jnp.sum(done & ~good),
              "identity": jnp.sum(plan.alive & ~done)}
    return ist, sign, counts


def compute_ist(cfg: ISTConfig, xyz0, normal0, xyz1, normal1, alive1, confidence) -> tuple[jax.Array, jax.Array, dict]:
    """:func:`plan_ist` then :func:`ist_from_plan`: ``(ist [C, 3, 3], normal_sign [C], report)``;
    ``report`` counts ``good``/``filled``/``identity`` points (Python ints)."""
    plan = plan_ist(cfg, xyz0, normal0, xyz1, normal1, alive1, confidence)
    dtype = jnp.asarray(xyz1).dtype
    ist, sign, counts = ist_from_plan(cfg, plan, *(jnp.asarray(x, dtype) for x in (xyz0, normal0, xyz1, normal1)))
    return ist, sign, {k: int(v) for k, v in counts.items()}


__all__ = ["ISTConfig", "ISTPlan", "NeighborTable", "compute_ist", "frame_transforms", "ist_from_plan", "ist_neighbors",
           "nearest_rotation", "plan_ist"]

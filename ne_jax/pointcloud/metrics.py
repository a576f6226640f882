"""Point-cloud accuracy against a reference cloud: Chamfer distance and normal agreement.

Distances are Euclidean nearest-neighbour distances found with ``scipy.spatial.cKDTree`` (not
squared). Shapes: ``N`` predicted points, ``G`` reference (ground-truth) points.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial import cKDTree

from ne_jax.geometry.points import as_cloud


@dataclasses.dataclass(frozen=True)
class Chamfer:
    """Nearest-neighbour distances between a cloud ``P`` and a reference ``G`` (world units).

    ``accuracy_*``: from each point of ``P`` to ``G`` (how far the points are from the surface);
    ``completeness_*``: from each point of ``G`` to ``P`` (how well the surface is covered);
    ``mean``: ``(accuracy_mean + completeness_mean) / 2``, the symmetric Chamfer distance."""

    accuracy_mean: float
    accuracy_median: float
    completeness_mean: float
    completeness_median: float

    @property
    def mean(self) -> float:
        return 0.5 * (self.accuracy_mean + self.completeness_mean)

    def as_dict(self) -> dict[str, float]:
        return {**dataclasses.asdict(self), "mean": self.mean}


def chamfer(points, reference, workers: int = -1) -> Chamfer:
    """Chamfer distance between ``points`` ``[N, 3]`` and ``reference`` ``[G, 3]`` (both directions,
    mean and median); see :class:`Chamfer`."""
    p, g = as_cloud(points, "points"), as_cloud(reference, "reference")
    d_pg, _ = cKDTree(g).query(p, k=1, workers=workers)
    d_gp, _ = cKDTree(p).query(g, k=1, workers=workers)
    return Chamfer(float(d_pg.mean()), float(np.median(d_pg)), float(d_gp.mean()), float(np.median(d_gp)))


@dataclasses.dataclass(frozen=True)
class NormalAgreement:
    """Agreement of normals with those of the nearest reference point.

    ``abs_cos``: mean ``|cos|`` (ignores orientation; 1 is perfect, 2/pi ~ 0.64 is random in 3-D);
    ``cos``: mean signed cosine (orientation included; -1..1); ``oriented``: fraction with
    ``cos > 0``; ``zero``: fraction of zero-length normals (counted as ``cos = 0``)."""

    abs_cos: float
    cos: float
    oriented: float
    zero: float

    def as_dict(self) -> dict[str, float]:
        return dataclasses.asdict(self)


def normal_agreement(points, normals, reference, reference_normals, workers: int = -1) -> NormalAgreement:
    """Compare ``normals`` ``[N, 3]`` at ``points`` ``[N, 3]`` with ``reference_normals`` ``[G, 3]``
    of the nearest ``reference`` point ``[G, 3]``; see :class:`NormalAgreement`. Normals need not be
    unit length (they are normalised; zero-length ones score 0)."""
    p, g = as_cloud(points, "points"), as_cloud(reference, "reference")
    n = np.asarray(normals, np.float64)
    gn = np.asarray(reference_normals, np.float64)
    if n.shape != p.shape:
        raise ValueError(f"normals: expected shape {p.shape} like points, found {n.shape}")
    if gn.shape != g.shape:
        raise ValueError(f"reference_normals: expected shape {g.shape} like reference, found {gn.shape}")
    for name, a in (("normals", n), ("reference_normals", gn)):
        if not np.isfinite(a).all():
            raise ValueError(f"{name}: expected finite values, found NaN/inf")
    _, idx = cKDTree(g).query(p, k=1, workers=workers)
    ln = np.linalg.norm(n, axis=1)
    lg = np.linalg.norm(gn[idx], axis=1)
    ok = (ln > 1e-12) & (lg > 1e-12)
    cos = np.zeros(len(p))
    cos[ok] = np.sum(n[ok] * gn[idx][ok], axis=1) / (ln[ok] * lg[ok])
    return NormalAgreement(float(np.abs(cos).mean()), float(cos.mean()), float((cos > 0).mean()), float((~ok).mean()))

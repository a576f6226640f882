"""The point cloud as state: a fixed-capacity, frozen pytree.

``PointState`` holds ``C`` slots (a capacity). Deleting or pruning a point flips ``alive`` to
``False``; it never changes ``C`` or any index, so an indexed edit ``P -> Q(P)`` keeps every
point's identity (STYLE.md habits 2-3). Dead slots keep finite placeholder values so that every
array stays NaN-free under ``jax.grad``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct


def as_cloud(x, name: str) -> np.ndarray:
    """``x`` as a float64 ``[N, 3]`` cloud of at least one finite point; otherwise a ``ValueError``
    naming ``name``, what was expected and what was found (the first bad row)."""
    x = np.asarray(x, np.float64)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"{name}: expected an [N, 3] point cloud, found shape {x.shape}")
    if x.shape[0] == 0:
        raise ValueError(f"{name}: expected at least one point, found none")
    if not np.isfinite(x).all():
        row = int(np.flatnonzero(~np.isfinite(x).all(axis=1))[0])
        raise ValueError(f"{name}: expected finite positions, found {x[row].tolist()} at row {row}")
    return x


@struct.dataclass
class PointState:
    """Per-point arrays of a capacity-``C`` cloud (``F`` feature channels).

    Attributes:
        xyz: ``[C, 3]`` positions (dead slots: finite placeholder, by default the origin).
        alive: ``[C]`` bool; only alive points take part in trees, KNN and rendering.
        feature: ``[C, F]`` per-point feature vectors (model parameters).
        conf_logit: ``[C]`` confidence logits; the confidence is ``sigmoid(conf_logit)``.
        normal: ``[C, 3]`` unit normals (zeros until estimated).
        ist: ``[C, 3, 3]`` infinitesimal surface transformations (identity until edited).
    """

    xyz: jax.Array
    alive: jax.Array
    feature: jax.Array
    conf_logit: jax.Array
    normal: jax.Array
    ist: jax.Array

    @property
    def capacity(self) -> int:
        """``C``: the number of slots (static: it sets array shapes)."""
        return self.xyz.shape[0]

    @property
    def feature_dim(self) -> int:
        return self.feature.shape[-1]

    @property
    def confidence(self) -> jax.Array:
        """``[C]`` confidences in ``(0, 1)``."""
        return jax.nn.sigmoid(self.conf_logit)

    @classmethod
    def from_numpy(
        cls,
        xyz,
        capacity: int | None = None,
        feature_dim: int = 32,
        *,
        feature=None,
        confidence: float = 0.5,
        normal=None,
        dtype=jnp.float32,
        key: jax.Array | None = None,
    ) -> PointState:
        """Host-side constructor from an ``[N, 3]`` cloud; slots ``N .. C-1`` are dead padding.

        Args:
            xyz: ``[N, 3]`` finite positions (numpy or anything array-like).
            capacity: ``C >= N`` slots (default ``N``).
            feature_dim: ``F`` when ``feature`` is not given (features then ``N(0, 1) * 0.1`` from
                ``key``, or zeros when ``key`` is ``None``).
            feature: optional ``[N, F]`` initial features.
            confidence: initial confidence of every alive point, in ``(0, 1)`` (the paper grows new
                points at 0.5).
            normal: optional ``[N, 3]`` normals (default zeros).
            dtype: floating dtype of the state (float32 by default).
            key: PRNG key for random initial features.

        Raises:
            ValueError: naming the argument, what was expected and what was found.
        """
        pts = np.asarray(xyz)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"xyz: expected an array of shape [N, 3], found shape {pts.shape}")
        if not np.issubdtype(pts.dtype, np.number):
            raise ValueError(f"xyz: expected a numeric array, found dtype {pts.dtype}")
        n = pts.shape[0]
        bad = ~np.isfinite(pts).all(axis=1)
        if bad.any():
            rows = np.flatnonzero(bad)
            raise ValueError(
                f"xyz: expected finite positions, found {rows.size} row(s) with NaN/inf "
                f"(first at index {int(rows[0])}: {pts[rows[0]].tolist()})"
            )
        c = n if capacity is None else int(capacity)
        if c < max(n, 1):
            raise ValueError(f"capacity: expected an integer >= max(N, 1) = {max(n, 1)}, found {capacity}")
        if not 0.0 < float(confidence) < 1.0:
            raise ValueError(f"confidence: expected a value in (0, 1), found {confidence}")

        if feature is not None:
            feat = np.asarray(feature)
            if feat.ndim != 2 or feat.shape[0] != n:
                raise ValueError(f"feature: expected shape [N={n}, F], found shape {feat.shape}")
            if not np.isfinite(feat).all():
                raise ValueError("feature: expected finite values, found NaN/inf")
            feature_dim = feat.shape[1]
        elif int(feature_dim) < 1:
            raise ValueError(f"feature_dim: expected an integer >= 1, found {feature_dim}")
        if normal is not None:
            nrm = np.asarray(normal)
            if nrm.shape != (n, 3):
                raise ValueError(f"normal: expected shape [N={n}, 3], found shape {nrm.shape}")
            if not np.isfinite(nrm).all():
                raise ValueError("normal: expected finite values, found NaN/inf")

        np_dtype = np.dtype(dtype)
        xyz_c = np.zeros((c, 3), np_dtype)
        xyz_c[:n] = pts
        alive = np.zeros((c,), bool)
        alive[:n] = True
        feat_c = np.zeros((c, int(feature_dim)), np_dtype)
        if feature is not None:
            feat_c[:n] = feat
        elif key is not None:
            feat_c[:n] = 0.1 * np.asarray(jax.random.normal(key, (n, int(feature_dim)), dtype))
        nrm_c = np.zeros((c, 3), np_dtype)
        if normal is not None:
            nrm_c[:n] = nrm
        logit = float(np.log(confidence) - np.log1p(-confidence))
        conf_c = np.where(alive, logit, 0.0).astype(np_dtype)
        ist_c = np.broadcast_to(np.eye(3, dtype=np_dtype), (c, 3, 3)).copy()
        return cls(
            xyz=jnp.asarray(xyz_c),
            alive=jnp.asarray(alive),
            feature=jnp.asarray(feat_c),
            conf_logit=jnp.asarray(conf_c),
            normal=jnp.asarray(nrm_c),
            ist=jnp.asarray(ist_c),
        )

    def delete(self, index) -> PointState:
        """Mark the points at ``index`` (an index array or a ``[C]`` mask) dead; shapes unchanged."""
        return self.replace(alive=self.alive.at[index].set(False))

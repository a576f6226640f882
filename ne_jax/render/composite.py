"""Front-to-back compositing of per-segment density and colour (data flow step 7 of docs/design.md).

``tau_i = sigma_i * len_i`` (optical thickness of slot ``i``), ``alpha_i = 1 - exp(-tau_i)`` computed
as ``-expm1(-tau_i)`` (exact for thin segments), transmittance ``T_i = exp(-sum_{j<i} tau_j)`` from an
exclusive cumulative sum in log space, weights ``w_i = T_i alpha_i``, and
``rgb = sum_i w_i c_i + T_final * background`` with ``T_final = exp(-sum_i tau_i)``.

float32 accuracy (the released code summed in float64): every quantity is a product of
relative-accurate factors — ``exp`` of a float32 sum (relative error ``~|sum| * eps``), ``expm1`` —
never a difference of transmittances ``T_i - T_{i+1}``, so weights of thin and deep segments keep
their relative precision; ``opacity = -expm1(-sum tau)`` likewise. ``tau`` is clamped at ``TAU_MAX``
(``exp(-TAU_MAX)`` underflows in float64 already), so huge densities give exact zeros and finite
gradients instead of ``inf * 0``.

Contract of the slots (what ``composite`` does *not* do):

* slots are in ray order (sorted by entry distance, as ``intersect`` emits them) and each valid slot
  contributes exactly once, independently of the others; invalid slots contribute nothing and their
  (possibly garbage, even NaN) inputs never reach values or gradients;
* overlapping segments are not detected: two slots covering the same stretch both attenuate. K-D
  boxes of one level are disjoint up to the padding margin, so the geometry step guarantees
  disjointness up to that margin; where padded boxes do overlap, ``clip_overlaps`` trims every
  segment to the part not already covered by earlier ones so that no stretch of the ray is counted
  twice (lengths of contained segments become 0);
* a ray with no valid slot is pure background (opacity 0, depth 0).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct
from jax import lax

TAU_MAX = 1.0e3
"""Clamp of the per-slot optical thickness (``exp(-1000) == 0`` in float32 and float64)."""


@struct.dataclass
class Composited:
    """Per-ray compositing results.

    Attributes:
        rgb: ``[R, 3]`` colour including the background.
        opacity: ``[R]`` ``1 - T_final`` (accumulated alpha).
        depth: ``[R]`` expected distance ``sum w t_mid / opacity`` (0 where the opacity is 0).
        weights: ``[R, M]`` ``T_i alpha_i`` (0 in invalid slots).
        transmittance: ``[R]`` ``T_final``, the background's share.
        normal: ``[R, 3]`` ``sum w n`` (not renormalised; length ~ opacity), or ``None``.
    """

    rgb: jax.Array
    opacity: jax.Array
    depth: jax.Array
    weights: jax.Array
    transmittance: jax.Array
    normal: jax.Array | None = None


def composite(sigma: jax.Array, rgb: jax.Array, lengths: jax.Array, valid: jax.Array,
              t_mid: jax.Array, background: jax.Array, normals: jax.Array | None = None
              ) -> Composited:
    """Composite ``M`` slots per ray.

    Args:
        sigma: ``[R, M]`` density (>= 0). rgb: ``[R, M, 3]``. lengths: ``[R, M]`` segment lengths in the
            unit ``sigma`` is per (docs/design.md: point spacings). valid: ``[R, M]`` bool. t_mid: ``[R, M]``
            distance reported for each slot in the depth map (e.g. the segment midpoint).
            background: ``[R, 3]`` or ``[3]``. normals: optional ``[R, M, 3]`` for a normal map.
    """
    dtype = jnp.result_type(sigma, lengths, rgb)
    valid = jnp.asarray(valid, bool)
    sig = jnp.where(valid, sigma, 0.0).astype(dtype)
    length = jnp.where(valid, lengths, 0.0).astype(dtype)
    tau = jnp.minimum(sig * length, TAU_MAX)
    total = jnp.sum(tau, axis=-1)
    # Exclusive sum_{j<i} tau_j by shifting, not as cumsum - tau: the difference carries the rounding
    # of the inclusive sum, ~ulp(tau_i) — up to 6e-5 for a clamped tau of 1e3 in float32 — into the
    # weight of exactly the slot where an opaque surface stops the ray.
    log_trans = jnp.concatenate([jnp.zeros_like(tau[..., :1]), jnp.cumsum(tau[..., :-1], axis=-1)], axis=-1)
    alpha = -jnp.expm1(-tau)
    weights = jnp.where(valid, jnp.exp(-log_trans) * alpha, 0.0)
    trans_final = jnp.exp(-total)
    opacity = -jnp.expm1(-total)
    color = jnp.where(valid[..., None], rgb, 0.0).astype(dtype)
    background = jnp.broadcast_to(jnp.asarray(background, dtype), (*sigma.shape[:-1], 3))
    out_rgb = jnp.sum(weights[..., None] * color, axis=-2) + trans_final[..., None] * background
    t = jnp.where(valid, t_mid, 0.0).astype(dtype)
    # Depth = sum(w t) / opacity, 0 where the ray is (numerically) empty. The guard is sqrt(tiny), not
    # 0: the gradient -num / opacity^2 overflows to -inf once opacity^2 underflows (opacity < ~1e-19).
    seen = opacity > jnp.sqrt(jnp.finfo(dtype).tiny)
    depth = jnp.where(seen, jnp.sum(weights * t, axis=-1) / jnp.where(seen, opacity, 1.0), 0.0)
    normal = None
    if normals is not None:
        nrm = jnp.where(valid[..., None], normals, 0.0).astype(dtype)
        normal = jnp.sum(weights[..., None] * nrm, axis=-2)
    return Composited(rgb=out_rgb, opacity=opacity, depth=depth, weights=weights,
                      transmittance=trans_final, normal=normal)


def clip_overlaps(t_lo: jax.Array, t_hi: jax.Array, valid: jax.Array
                  ) -> tuple[jax.Array, jax.Array]:
    """Trim sorted segments ``[R, M]`` so no stretch of a ray is covered twice.

    Each valid segment starts at ``max(t_lo, furthest t_hi of the earlier valid segments)`` and is
    empty (``t_lo' == t_hi``, length 0) when an earlier one already covers it. Invalid slots are
    returned unchanged and do not trim others. Returns ``(t_lo', t_hi)``; ``t_hi' - t_lo' >= 0``."""
    neg = jnp.asarray(-jnp.inf, t_hi.dtype)
    reach = lax.cummax(jnp.where(valid, t_hi, neg), axis=t_hi.ndim - 1)
    prev = jnp.concatenate([jnp.full_like(reach[..., :1], neg), reach[..., :-1]], axis=-1)
    lo = jnp.minimum(jnp.maximum(t_lo, prev), t_hi)
    return jnp.where(valid, lo, t_lo), t_hi

"""Training losses (docs/design.md facts: "Losses"), each a pure function with finite values and
gradients at the hard inputs (rays with zero opacity, confidences near 0 and 1).

Notation: ``R`` rays, ``M`` segment slots per ray, ``w_i`` the compositing weights ``T_i alpha_i``,
``p_i`` the colour model's unit predicted normal of segment ``i``, ``d`` the unit ray direction
(camera towards the scene), ``c`` point confidences ``sigmoid(conf_logit)``.

* ``photometric``: ``mean_{r, ch} (rgb - target)^2`` (the paper's MSE on RGB composited on the
  chosen background).
* ``orientation`` (Ref-NeRF): ``mean_r sum_i w_i max(0, p_i . d)^2`` -- a predicted normal
  facing away from the camera (``p . v < 0`` with ``v = -d``) is penalised, weighted by how much the
  segment is seen. Ref-NeRF applies it to the normals it shades with; here the predicted normal is
  the one the colour model owns (the point normals are fixed geometry), as the paper's appendix says
  ("the modeled normal vectors are trained with ... the regularization losses introduced in RefNeRF").
* ``normal``: predicted vs point normal, weighted by confidence (paper appendix, "Phong Reflection
  Color Modeling"): ``mean_r sum_i w_i sum_k omega_k c_k |n_k|^2 (1 - (p_i . n_k)^2)``, the inner
  sum integrated over the segment's samples and their ``K`` neighbours (KNN weights ``omega``),
  computed from the integrated moment ``A_i`` of :class:`~ne_jax.render.renderer.SegmentAux` as
  ``trace(A_i) - p_i^T A_i p_i``. ``1 - (p . n)^2`` (sine squared) instead of Ref-NeRF's
  ``1 - p . n``: Open3D normals are unoriented, so the loss must not depend on their sign (the
  orientation loss fixes the sign of ``p``). Each point's mismatch is multiplied by its own
  confidence, so points whose normals the predicted field cannot fit (outliers) are pushed towards
  confidence 0 -- the mechanism the paper names. Points without a normal (zero vector) contribute 0.
* ``confidence``: ``mean_{alive} [log c' + log(1 - c') - log(eps (1 - eps))]`` with
  ``c' = clip(c, eps, 1 - eps)`` -- PointNeRF's "zero-one" regulariser (the ``log c + log(1-c)``
  family of docs/design.md), shifted to be 0 at the clip bounds and ``log(1 / (4 eps (1-eps)))`` at
  ``c = 0.5``. It pushes confidences away from 0.5; the clip (done on the logit) stops the push at
  ``eps`` / ``1 - eps`` so logits do not drift without bound and gradients stay finite.
* ``sparsity``: Cauchy penalty on the optical thickness of every rendered segment,
  ``mean_r sum_i log(1 + tau_i^2 / s)``, ``tau_i = sigma_i len_i`` (a SNeRG-style Cauchy sparsity loss; small
  weight): empty space is pushed to zero density, opaque surfaces cost little more than thin ones.

The weights are static (:class:`LossConfig`); a term with weight 0 is not computed (absent from
the compiled graph, so it cannot poison the gradient with ``0 * NaN``).
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp

from ne_jax.geometry.points import PointState
from ne_jax.render.renderer import RenderOut, SegmentAux

TERMS = ("photometric", "orientation", "normal", "confidence", "sparsity", "ist_orthogonality")
"""Names of the loss terms, in the order they are reported."""


CONFIDENCE_EPS = 1e-3
"""Clip of the confidence regulariser: no push beyond ``[eps, 1 - eps]``."""
SPARSITY_SCALE = 0.5
"""``s`` of the Cauchy sparsity term ``log(1 + tau^2 / s)``."""


@dataclasses.dataclass(frozen=True)
class LossConfig:
    """Static loss weights and shapes (hashable). Weights are our choices where docs/design.md and the
    paper give none; 0 removes a term from the compiled step."""

    photometric: float = 1.0
    """Weight of the RGB MSE."""
    orientation: float = 0.1
    """Weight of the Ref-NeRF orientation loss (Ref-NeRF's ``orientation_loss_mult``)."""
    normal: float = 1e-2
    """Weight of the confidence-weighted predicted-vs-point normal loss. Larger than Ref-NeRF's
    ``3e-4`` for its predicted-normal loss: here it is also the signal that lowers the confidence of
    points whose normals disagree with the learned normal field."""
    confidence: float = 1e-4
    """Weight of the confidence regulariser (a small push away from 0.5, as PointNeRF's zero-one loss)."""
    sparsity: float = 1e-4
    """Weight of the Cauchy density sparsity term."""
    ist_orthogonality: float = 0.0
    """Weight of ``mean_alive |IST^T IST - I|_F^2``, which keeps trainable ISTs rotations (fine-tuning
    with ``TrainConfig.train_ist``; 0 otherwise: the term is then not computed)."""
    def __post_init__(self):
        for name in TERMS:
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"LossConfig.{name}: expected a weight >= 0, found {getattr(self, name)}")

    def weights(self) -> dict[str, float]:
        """``{term: weight}`` of the enabled (non-zero weight) terms, in :data:`TERMS` order."""
        return {name: float(getattr(self, name)) for name in TERMS if getattr(self, name) != 0.0}

    def replace(self, **changes) -> LossConfig:
        return dataclasses.replace(self, **changes)


def photometric_loss(rgb: jax.Array, target: jax.Array) -> jax.Array:
    """``mean (rgb - target)^2`` over ``[R, 3]``."""
    return jnp.mean(jnp.square(rgb - target))


def orientation_loss(aux: SegmentAux) -> jax.Array:
    """``mean_r sum_i w_i max(0, p_i . d)^2`` (``aux`` fields ``[R, M, ...]``)."""
    n_dot_d = jnp.sum(aux.pred_normal * aux.view_dir, axis=-1)
    per_seg = jnp.square(jnp.maximum(n_dot_d, 0.0))
    return jnp.mean(jnp.sum(jnp.where(aux.valid, aux.weights * per_seg, 0.0), axis=-1))


def normal_mismatch(aux: SegmentAux) -> jax.Array:
    """``[R, M]`` ``trace(A) - p^T A p = sum_k omega_k c_k |n_k|^2 (1 - (p . n_k)^2)`` (>= 0 up to
    rounding; clamped at 0)."""
    a = aux.normal_moment
    p = aux.pred_normal
    trace = a[..., 0, 0] + a[..., 1, 1] + a[..., 2, 2]
    quad = jnp.einsum("...i,...ij,...j->...", p, a, p)
    return jnp.maximum(trace - quad, 0.0)


def normal_loss(aux: SegmentAux) -> jax.Array:
    """Confidence-weighted predicted-vs-point normal loss ``mean_r sum_i w_i mismatch_i``."""
    return jnp.mean(jnp.sum(jnp.where(aux.valid, aux.weights * normal_mismatch(aux), 0.0), axis=-1))


def confidence_loss(conf_logit: jax.Array, alive: jax.Array, eps: float = CONFIDENCE_EPS) -> jax.Array:
    """``mean_alive [log c' + log(1 - c') - log(eps (1 - eps))]``, ``c' = clip(c, eps, 1 - eps)``,
    computed on the logit (``conf_logit``, ``alive`` ``[C]``); 0 when nothing is alive."""
    bound = math.log((1.0 - eps) / eps)
    logit = jnp.clip(conf_logit, -bound, bound)
    floor = math.log(eps) + math.log1p(-eps)
    per_point = jax.nn.log_sigmoid(logit) + jax.nn.log_sigmoid(-logit) - floor
    per_point = jnp.where(alive, per_point, 0.0)
    return jnp.sum(per_point) / jnp.maximum(jnp.sum(alive), 1).astype(per_point.dtype)


def sparsity_loss(aux: SegmentAux, scale: float = SPARSITY_SCALE) -> jax.Array:
    """``mean_r sum_i log(1 + tau_i^2 / scale)`` over rendered segments, ``tau = sigma * len``."""
    tau = jnp.where(aux.valid, aux.sigma * aux.lengths, 0.0)
    return jnp.mean(jnp.sum(jnp.log1p(jnp.square(tau) / scale), axis=-1))


def ist_orthogonality_loss(ist: jax.Array, alive: jax.Array) -> jax.Array:
    """``mean_alive |IST^T IST - I|_F^2`` over ``ist [C, 3, 3]``, ``alive [C]``."""
    gram = jnp.einsum("cji,cjk->cik", ist, ist) - jnp.eye(3, dtype=ist.dtype)
    per_point = jnp.where(alive, jnp.sum(jnp.square(gram), axis=(-2, -1)), 0.0)
    return jnp.sum(per_point) / jnp.maximum(jnp.sum(alive), 1).astype(per_point.dtype)


def loss_terms(cfg: LossConfig, out: RenderOut, aux: SegmentAux, target: jax.Array,
               points: PointState) -> dict[str, jax.Array]:
    """The enabled terms (unweighted scalars), keyed as :meth:`LossConfig.weights`.

    ``out``/``aux``: :func:`~ne_jax.render.renderer.render_rays_with_aux` of the batch; ``target``
    ``[R, 3]`` RGB on the background; ``points``: the rendered cloud (confidence regulariser)."""
    enabled = cfg.weights()
    terms = {}
    if "photometric" in enabled:
        terms["photometric"] = photometric_loss(out.rgb, target)
    if "orientation" in enabled:
        terms["orientation"] = orientation_loss(aux)
    if "normal" in enabled:
        terms["normal"] = normal_loss(aux)
    if "confidence" in enabled:
        terms["confidence"] = confidence_loss(points.conf_logit, points.alive)
    if "sparsity" in enabled:
        terms["sparsity"] = sparsity_loss(aux)
    if "ist_orthogonality" in enabled:
        terms["ist_orthogonality"] = ist_orthogonality_loss(points.ist, points.alive)
    return terms


def total_loss(cfg: LossConfig, terms: dict[str, jax.Array]) -> jax.Array:
    """``sum_k weight_k * term_k`` over the enabled terms."""
    weights = cfg.weights()
    return sum(jnp.asarray(weights[k], terms[k].dtype) * terms[k] for k in weights)


__all__ = [
    "TERMS",
    "LossConfig",
    "confidence_loss",
    "ist_orthogonality_loss",
    "loss_terms",
    "normal_loss",
    "normal_mismatch",
    "orientation_loss",
    "photometric_loss",
    "sparsity_loss",
    "total_loss",
]

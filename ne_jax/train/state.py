"""Training configuration and state.

:class:`TrainConfig` holds the static settings of the step (loss weights, optimiser schedule);
:class:`TrainState` is the frozen pytree the step maps to a new one. What is trained: the colour
model's parameters and the per-point ``feature`` and ``conf_logit`` arrays (the paper: "point
features and confidences are parameters"), and the ISTs when ``TrainConfig.train_ist``
(fine-tuning an edited model). Point positions, normals, ``alive`` and the K-D tree are fixed
during a step; they live in the :class:`~ne_jax.render.renderer.PointScene` passed to the step
(whose own ``feature``/``conf_logit`` are replaced by the state's).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from ne_jax.geometry.points import PointState
from ne_jax.render.renderer import PointScene, RenderConfig
from ne_jax.render.shading import init_color_model
from ne_jax.train.losses import LossConfig

LR_FINAL_FRACTION = 0.01
"""Floor of the cosine decay as a fraction of ``TrainConfig.lr`` (``alpha`` of
``optax.cosine_decay_schedule``; our choice, docs/design.md says only "cosine decay")."""


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Static training-step settings (hashable). The length of the learning-rate schedule is not
    one: it is the run's (:attr:`~ne_jax.train.run.RunConfig.total_steps`), passed to
    :meth:`schedule` / :meth:`optimizer`."""

    loss: LossConfig = LossConfig()
    """Loss weights and shapes."""
    lr: float = 2e-3
    """Adam's peak learning rate (docs/design.md facts: 2e-3)."""
    confidence_lr: float = 1.0
    """Multiplier of the learning rate of the confidence logits (Adam's steps of ``conf_logit`` are
    scaled by it). With a density gate (``KDTreeConfig.density_falloff``) the confidences move the
    density, and a larger rate lets them reach the pruning threshold within a short schedule; 1:
    every trainable alike (and Adam's state is the plain ``optax.adam`` one)."""
    train_ist: bool = False
    """Fine-tuning an edited model: the per-point ISTs are trainable too (paper Sec. 4); pair it
    with ``loss.ist_orthogonality > 0`` to keep them rotations. Off: the ISTs are fixed inputs."""

    def __post_init__(self):
        if not self.lr > 0:
            raise ValueError(f"TrainConfig.lr: expected > 0, found {self.lr}")
        if not self.confidence_lr > 0:
            raise ValueError(f"TrainConfig.confidence_lr: expected > 0, found {self.confidence_lr}")

    def schedule(self, total_steps: int) -> optax.Schedule:
        """Learning rate by step: cosine decay from ``lr`` to ``lr * LR_FINAL_FRACTION`` over
        ``total_steps`` (a run's :attr:`~ne_jax.train.run.RunConfig.total_steps`: the decay spans the
        run), the floor afterwards."""
        if int(total_steps) < 1:
            raise ValueError(f"TrainConfig.schedule: expected total_steps an integer >= 1, found {total_steps}")
        return optax.cosine_decay_schedule(self.lr, int(total_steps), alpha=LR_FINAL_FRACTION)

    def optimizer(self, total_steps: int) -> optax.GradientTransformation:
        """Adam with :meth:`schedule` over ``total_steps`` on ``{"params": ..., "points": ...}``, the
        confidence logits' steps scaled by :attr:`confidence_lr`."""
        adam = optax.adam(self.schedule(total_steps))  # optax's b1 0.9, b2 0.999, eps 1e-8
        if self.confidence_lr == 1.0:
            return adam
        k = self.confidence_lr

        def scale(updates, state, params=None):
            pts = updates["points"]
            return {**updates, "points": {**pts, "conf_logit": pts["conf_logit"] * k}}, state

        return optax.chain(adam, optax.GradientTransformation(lambda params: optax.EmptyState(), scale))

    def replace(self, **changes) -> TrainConfig:
        return dataclasses.replace(self, **changes)


@struct.dataclass
class TrainState:
    """What one training step reads and writes.

    Attributes:
        params: colour-model parameters (``init_color_model``'s tree).
        points: ``{"feature": [C, F], "conf_logit": [C]}`` the trainable per-point arrays (and
            ``"ist": [C, 3, 3]`` when ``TrainConfig.train_ist``).
        opt_state: optax state of :meth:`TrainConfig.optimizer` over ``trainables``.
        step: ``[]`` int32 steps applied (skipped steps do not count).
        key: PRNG key (split each step; used by the stochastic integration rule).
        skipped: ``[]`` int32 steps refused because something was non-finite.
    """

    params: dict
    points: dict
    opt_state: optax.OptState
    step: jax.Array
    key: jax.Array
    skipped: jax.Array

    @property
    def trainables(self) -> dict:
        """``{"params": ..., "points": ...}``: the tree the optimiser updates."""
        return {"params": self.params, "points": self.points}

    def point_state(self, base: PointState) -> PointState:
        """``base`` with the trained ``feature`` and ``conf_logit`` (and ``ist`` when trained)."""
        return base.replace(**self.points)

    def scene(self, base: PointScene) -> PointScene:
        """``base`` (tree and fixed point arrays) with the trained per-point arrays."""
        return base.replace(points=self.point_state(base.points))

    def with_points(self, points: PointState, reset) -> TrainState:
        """The state after the cloud changed between epochs: trainable per-point arrays taken from
        ``points`` (capacity ``C'`` >= the current ``C``), Adam's per-point moments padded with zeros
        to ``C'`` and zeroed at ``reset`` (``[C']`` bool or indices: slots that hold new points).
        The colour model, its moments, ``step`` and ``key`` are unchanged."""
        c_new = points.capacity
        reset = jnp.zeros((c_new,), bool).at[jnp.asarray(reset, jnp.int32).reshape(-1)].set(True) \
            if np.asarray(reset).dtype != bool else jnp.asarray(reset)

        def fit(path, a):
            if not any(getattr(k, "key", None) == "points" for k in path) or getattr(a, "ndim", 0) == 0:
                return a
            grown = jnp.concatenate([a, jnp.zeros((c_new - a.shape[0],) + a.shape[1:], a.dtype)])
            return jnp.where(reset.reshape((-1,) + (1,) * (a.ndim - 1)), 0, grown)

        pts = _trainable_points(points, "ist" in self.points)
        return self.replace(points=pts, opt_state=jax.tree_util.tree_map_with_path(fit, self.opt_state))


def _trainable_points(points: PointState, ist: bool) -> dict:
    pts = {"feature": jnp.asarray(points.feature, jnp.float32),
           "conf_logit": jnp.asarray(points.conf_logit, jnp.float32)}
    if ist:
        pts["ist"] = jnp.asarray(points.ist, jnp.float32)
    return pts


def init_train_state(cfg: TrainConfig, render_cfg: RenderConfig, points: PointState,
                     key: jax.Array, *, total_steps: int) -> TrainState:
    """A fresh state: random colour model (``render_cfg.shading``), the cloud's features and
    confidence logits as trainables, Adam's zero moments (of :meth:`TrainConfig.optimizer` over
    ``total_steps``, the run's length), step 0."""
    if points.feature_dim != render_cfg.shading.feature_dim:
        raise ValueError(f"points.feature: width {points.feature_dim} != render_cfg.shading.feature_dim "
                         f"{render_cfg.shading.feature_dim}")
    k_model, k_state = jax.random.split(key)
    params = init_color_model(render_cfg.shading, k_model)
    pts = _trainable_points(points, cfg.train_ist)
    opt_state = cfg.optimizer(total_steps).init({"params": params, "points": pts})
    return TrainState(params=params, points=pts, opt_state=opt_state, step=jnp.zeros((), jnp.int32),
                      key=k_state, skipped=jnp.zeros((), jnp.int32))


__all__ = ["TrainConfig", "TrainState", "init_train_state"]

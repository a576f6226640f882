"""The point cloud the renderer tests share: 3000 surface samples of the procedural ``glossy`` scene
(detail 0.5) with their normals, random features N(0, 0.5) and confidence logits 2; and a random
colour model over it."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ne_jax.benchmark import scenes as S
from ne_jax.geometry.points import PointState
from ne_jax.render.renderer import PointScene, RenderConfig
from ne_jax.render.shading import init_color_model

from tests.mini_presets import tiny_caps


def glossy_points() -> PointState:
    smp = S.surface_samples(S.get_scene("glossy", 0.5), 3000, seed=0)
    rng = np.random.default_rng(0)
    points = PointState.from_numpy(smp["xyz"].astype(np.float32), capacity=3200, feature_dim=32,
                                   normal=smp["normal"].astype(np.float32))
    return points.replace(feature=jnp.asarray(rng.normal(0, 0.5, points.feature.shape), jnp.float32),
                          conf_logit=jnp.full(points.conf_logit.shape, 2.0))


def glossy_model(cfg: RenderConfig) -> tuple[dict, PointScene]:
    """Random colour-model parameters for ``cfg`` (key 0) and the scene of :func:`glossy_points`
    (tree built with ``cfg``, small capacities)."""
    return init_color_model(cfg.shading, jax.random.key(0)), PointScene.build(glossy_points(), cfg, tiny_caps())

"""Scene morphing (data flow: two trained models -> K-D matching -> intermediate clouds -> blended
rendering): :mod:`~ne_jax.morph.matching` pairs two clouds, :mod:`~ne_jax.morph.path` makes or
indexes the intermediate clouds, :mod:`~ne_jax.morph.blend` renders both models through one cloud,
:mod:`~ne_jax.morph.render` runs a whole morph to frames, a video and smoothness figures."""

from ne_jax.morph.blend import (
    BlendedShading,
    MorphPair,
    blended_render_config,
    morph_contexts,
    morph_scene,
    morph_scene_with_report,
    pair_models,
)
from ne_jax.morph.matching import equal_size, index_path, kd_match
from ne_jax.morph.path import linear_path, morph_ratios, path_from_clouds
from ne_jax.morph.render import MorphSettings, morph_models, render_morph, smoothness, strip

__all__ = [
    "BlendedShading",
    "MorphPair",
    "MorphSettings",
    "blended_render_config",
    "equal_size",
    "index_path",
    "kd_match",
    "linear_path",
    "morph_contexts",
    "morph_models",
    "morph_ratios",
    "morph_scene",
    "morph_scene_with_report",
    "pair_models",
    "path_from_clouds",
    "render_morph",
    "smoothness",
    "strip",
]

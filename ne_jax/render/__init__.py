"""Rendering pieces that need no K-D tree: quadrature (steps 3 and 5 of docs/design.md), the integrated
directional encoding, the colour model with declared effects (step 6) and compositing (step 7)."""

from ne_jax.render.composite import TAU_MAX, Composited, clip_overlaps, composite
from ne_jax.render.ide import ide_dim, ide_orders, integrated_dir_enc, positional_encoding
from ne_jax.render.quadrature import (
    RULES,
    QuadratureConfig,
    integrate,
    level_samples,
    level_table,
    quadrature_weights,
    sample_fractions,
    sample_positions,
)
from ne_jax.render.shading import (
    Effects,
    ShadeOut,
    ShadingConfig,
    background_color,
    init_color_model,
    num_params,
    shade,
)

__all__ = [
    "RULES",
    "TAU_MAX",
    "Composited",
    "Effects",
    "QuadratureConfig",
    "ShadeOut",
    "ShadingConfig",
    "background_color",
    "clip_overlaps",
    "composite",
    "ide_dim",
    "ide_orders",
    "init_color_model",
    "integrate",
    "integrated_dir_enc",
    "level_samples",
    "level_table",
    "num_params",
    "positional_encoding",
    "quadrature_weights",
    "sample_fractions",
    "sample_positions",
    "shade",
]

"""Variants for the deformation benchmark, as config switches of one code path (paper Table 1 and the
appendix's ablation table).

A :class:`Variant` says how its model is trained (``train_changes``: a change of the full model's
:class:`~ne_jax.train.run.RunConfig`, or ``None`` to reuse the full model), whether the edited
model declares the IST effect, and which image renderer scores it:

==========================  ==================================================  =====  ========
variant                     model                                               IST    renderer
==========================  ==================================================  =====  ========
``full``                    the full model                                      yes    rays
``no_ist``                  the full model ("Ours w/o IST")                     no     rays
``naive_plotting``          the full model, points plotted (paper baseline 1)   no     naive
``pointnerf_like``          stochastic sampling, traditional colour head, no    no     rays
                            normals (PointNeRF's ingredients on our point
                            cloud pipeline; not PointNeRF itself)
``traditional_sampling``    per-sample shading instead of segment integration   yes    rays
``stochastic_integration``  the stochastic quadrature rule                      yes    rays
``no_normals``              reflect about the predicted normal                  yes    rays
``traditional_color``       the traditional colour head (no Phong/Ref-NeRF)     yes    rays
``half_points``             half the initial points                             yes    rays
``no_ist_kept_normals``     the full model; the edit keeps every point's        no     rays
                            original normal (analysis: what re-estimating the
                            normals on the edited cloud contributes)
``rebuilt_tree``            the full model; the edited cloud gets a new K-D     yes    rays
                            tree (the paper) instead of the trained tree
                            carried through the edit (:mod:`ne_jax.geometry.carry`)
==========================  ==================================================  =====  ========

Every variant but ``rebuilt_tree`` carries the trained tree through the edit (``EditConfig.rebuild_tree`` off).

Fine-tuning Naive Plotting fine-tunes the full model without IST through the ray renderer and then
plots it (training through the plot is not implemented).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

from ne_jax.edit.apply import EditConfig
from ne_jax.render.naive import naive_plot_image
from ne_jax.render.quadrature import QuadratureConfig
from ne_jax.train.run import RunConfig


@dataclasses.dataclass(frozen=True)
class Variant:
    """One row of the benchmark table."""

    name: str
    label: str
    train_changes: Callable[[RunConfig], RunConfig] | None
    """``None``: the full model; else how this variant's model is trained from the full config."""
    ist: bool
    """Whether the edited model declares the IST effect."""
    naive: bool = False
    """Score by Naive Plotting instead of the ray renderer."""
    edit: EditConfig = EditConfig()
    """How the edit is applied to this variant's model."""

    @property
    def own_model(self) -> bool:
        return self.train_changes is not None

    def image_fn(self):
        """The ``image_fn`` for :func:`~ne_jax.eval.views.evaluate_split` (``None``: the ray renderer)."""
        if not self.naive:
            return None
        return lambda cfg, params, scene, camera, background, near, far: naive_plot_image(
            cfg, params, scene, camera, background, near, far)


def _effects(**changes) -> Callable[[RunConfig], RunConfig]:
    return lambda run: run.replace(render=run.render.with_effects(**changes))


def _rule(rule: str) -> Callable[[RunConfig], RunConfig]:
    def change(run: RunConfig) -> RunConfig:
        q = run.render.quadrature
        quadrature = QuadratureConfig(rule=rule, samples_per_level=q.samples_per_level)
        return run.replace(render=run.render.replace(quadrature=quadrature))
    return change


def _half_points(run: RunConfig) -> RunConfig:
    carve = dataclasses.replace(run.init.carve, num_points=run.init.carve.num_points // 2)
    return run.replace(init=dataclasses.replace(run.init, carve=carve))


def _pointnerf_like(run: RunConfig) -> RunConfig:
    run = _rule("stochastic")(run)
    return _effects(color_head="traditional", specular=False, point_normals=False)(run)


def _samples(run: RunConfig) -> RunConfig:
    return run.replace(render=run.render.replace(integration="samples"))


VARIANTS: dict[str, Variant] = {v.name: v for v in (
    Variant("full", "Ours (full)", None, ist=True),
    Variant("no_ist", "Ours w/o IST", None, ist=False),
    Variant("naive_plotting", "Naive Plotting", None, ist=False, naive=True),
    Variant("pointnerf_like", "PointNeRF-like", _pointnerf_like, ist=False),
    Variant("traditional_sampling", "- integration + traditional sampling", _samples, ist=True),
    Variant("stochastic_integration", "- deterministic + stochastic integration", _rule("stochastic"), ist=True),
    Variant("no_normals", "- normal vectors", _effects(point_normals=False), ist=True),
    Variant("traditional_color", "- Phong + traditional colour", _effects(color_head="traditional", specular=False),
            ist=True),
    Variant("half_points", "- 50% points", _half_points, ist=True),
    Variant("no_ist_kept_normals", "w/o IST, normals not re-estimated", None, ist=False,
            edit=EditConfig(reestimate_normals=False)),
    Variant("rebuilt_tree", "Ours, tree rebuilt (paper)", None, ist=True, edit=EditConfig(rebuild_tree=True)),
)}
"""Every variant by name (Table 1's rows first, then the ablation rows)."""

MAIN_VARIANTS = ("full", "rebuilt_tree", "no_ist", "naive_plotting", "pointnerf_like")
"""The rows of the paper's Table 1 (with PointNeRF replaced by the PointNeRF-like variant), and the
full model edited with the paper's rebuilt tree."""


def get_variant(name: str) -> Variant:
    if name not in VARIANTS:
        raise KeyError(f"unknown variant {name!r}; expected one of {sorted(VARIANTS)}")
    return VARIANTS[name]


def variant_run(full: RunConfig, variant: Variant) -> RunConfig:
    """The training config of ``variant``'s model (the full one for variants that reuse it)."""
    if not variant.own_model:
        return full
    return variant.train_changes(full).replace(name=f"{full.name}-{variant.name}")


__all__ = ["MAIN_VARIANTS", "VARIANTS", "Variant", "get_variant", "variant_run"]

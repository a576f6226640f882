"""Rendering two trained models through one intermediate cloud, blended by the morph ratio.

Both models see the same moving points (so one K-D tree, one set of segments and samples, one KNN
per sample) but each through its own eyes: its own features, its own normals oriented and its own
IST computed by :func:`~ne_jax.edit.apply.apply_edit` from its own cloud to the intermediate one.
Per segment, each model's colour model shades its own integrated features; the density and colour
are blended, ``sigma = (1 - r) sigma_A + r sigma_B`` and ``c = (1 - r) c_A + r c_B``, then composited
as usual (docs/design.md: "rendering blends the two scenes' density and colour terms with the morph ratio").

How it plugs into the renderer without a second code path: the morph scene's
:class:`~ne_jax.geometry.points.PointState` carries both models' per-point arrays side by side —
``feature [C, F_A + F_B]``, ``normal [C, 2, 3]``, ``ist [C, 2, 3, 3]`` (KNN interpolation and the
quadrature are linear and act per channel) — and :class:`BlendedShading` stands in for the render
config's :class:`~ne_jax.render.shading.ShadingConfig`: it splits the integrated arrays and shades
each half with its model's parameters, ``params = {"a": ..., "b": ..., "ratio": r}`` (the ratio is
data, so a whole morph compiles once).

The morph cloud lives in scene A's slots: point ``i`` of the matching is A's slot ``slots_a[i]`` and
B's slot ``slots_b[i]``. At ratio 0 on A's own cloud (equal sizes) the render is A's up to float
rounding (same tree; ``1 * x + 0 * y``; the interpolated identity IST is ``(sum_k w_k) I``, not exactly
``I``), at ratio 1 on B's cloud B's up to float rounding as well (B's points sit in A's slot order,
so sums run in another order). Tested to 1e-5.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from ne_jax.edit.apply import EditConfig, EditContext, apply_edit_with_report, edit_context
from ne_jax.geometry.points import PointState
from ne_jax.morph.matching import equal_size, kd_match
from ne_jax.numerics import safe_normalize
from ne_jax.render.quadrature import at_test_time
from ne_jax.render.renderer import PointScene, RenderConfig
from ne_jax.render.shading import Effects, ShadeOut, ShadingConfig, background_color, shade
from ne_jax.train.model import TrainedModel


@dataclasses.dataclass(frozen=True)
class BlendedEffects:
    """What the renderer asks of a blended scene: the union of the two models' inputs."""

    a: Effects
    b: Effects

    @property
    def uses_point_normals(self) -> bool:
        return self.a.uses_point_normals or self.b.uses_point_normals

    @property
    def uses_ist(self) -> bool:
        return self.a.uses_ist or self.b.uses_ist

    @property
    def uses_view_dir(self) -> bool:
        return self.a.uses_view_dir or self.b.uses_view_dir


@dataclasses.dataclass(frozen=True)
class BlendedShading:
    """Stands in for ``RenderConfig.shading``: model A's and model B's colour models, blended by
    ``params["ratio"]`` (module docstring). Hashable and static like a ``ShadingConfig``."""

    a: ShadingConfig
    b: ShadingConfig

    @property
    def effects(self) -> BlendedEffects:
        return BlendedEffects(self.a.effects, self.b.effects)

    @property
    def feature_dim(self) -> int:
        return self.a.feature_dim + self.b.feature_dim

    def shade(self, params: dict, feature, normal, view_dir, ist=None, pred_normal_mix=None) -> ShadeOut:
        """``feature [..., F_A + F_B]``, ``normal [..., 2, 3]``, ``ist [..., 2, 3, 3]`` (A's, then B's)."""
        r = jnp.asarray(params["ratio"], feature.dtype)
        outs = []
        for i, (cfg, p, f) in enumerate(((self.a, params["a"], feature[..., :self.a.feature_dim]),
                                         (self.b, params["b"], feature[..., self.a.feature_dim:]))):
            fx = cfg.effects
            n = normal[..., i, :] if fx.uses_point_normals else None
            m = ist[..., i, :, :] if fx.uses_ist else None
            outs.append(shade(cfg, p, f, n, view_dir, m, pred_normal_mix))
        a, b = outs

        def mix(x, y):
            return (1.0 - r) * x + r * y

        normals = [o.shading_normal for o in outs if o.shading_normal is not None]
        shading_normal = None
        if len(normals) == 2:
            shading_normal = safe_normalize(mix(*normals))
        elif normals:
            shading_normal = normals[0]
        return ShadeOut(sigma=mix(a.sigma, b.sigma), rgb=mix(a.rgb, b.rgb),
                        pred_normal=safe_normalize(mix(a.pred_normal, b.pred_normal)),
                        shading_normal=shading_normal)

    def background_color(self, params: dict, origin, direction, constant=None):
        r = jnp.asarray(params["ratio"], direction.dtype)
        bg_a = background_color(self.a, params["a"], origin, direction, constant)
        bg_b = background_color(self.b, params["b"], origin, direction, constant)
        return (1.0 - r) * bg_a + r * bg_b


_GEOMETRY_FIELDS = ("kdtree", "quadrature", "integration", "exact_knn")


def blended_render_config(render_a: RenderConfig, render_b: RenderConfig) -> RenderConfig:
    """A's render config with :class:`BlendedShading` of both colour models (each with the IST
    effect declared) and the test-time quadrature. Raises ``ValueError`` naming the settings in
    which the two models' traversal or integration differ (they must render the same samples)."""
    differ = [f for f in _GEOMETRY_FIELDS if getattr(render_a, f) != getattr(render_b, f)]
    if differ:
        raise ValueError("morph: expected two models rendered with the same traversal and integration, found "
                         "different " + ", ".join(f"{f} ({getattr(render_a, f)} vs {getattr(render_b, f)})"
                                                  for f in differ))
    shading = BlendedShading(a=render_a.with_effects(ist=True).shading, b=render_b.with_effects(ist=True).shading)
    return render_a.replace(shading=shading, quadrature=at_test_time(render_a.quadrature))


@dataclasses.dataclass(frozen=True)
class MorphPair:
    """Two trained models paired for morphing (host side, fixed along the morph).

    ``slots_a [N]`` / ``slots_b [N]``: A's and B's slots of matched point ``i`` (all alive points of the
    smaller cloud, the most confident ones of the larger, :func:`~ne_jax.morph.matching.equal_size`),
    paired by :func:`~ne_jax.morph.matching.kd_match`. ``render``: the blended render config."""

    a: TrainedModel
    b: TrainedModel
    points_a: PointState
    points_b: PointState
    slots_a: np.ndarray
    slots_b: np.ndarray
    render: RenderConfig

    @property
    def cloud_a(self) -> np.ndarray:
        """``[N, 3]`` A's matched points, in matching order."""
        return np.asarray(self.points_a.xyz, np.float64)[self.slots_a]

    @property
    def cloud_b(self) -> np.ndarray:
        """``[N, 3]`` B's points paired with :attr:`cloud_a` row by row."""
        return np.asarray(self.points_b.xyz, np.float64)[self.slots_b]

    def params(self, ratio) -> dict:
        """The blended colour-model parameters at morph ratio ``ratio`` (a traced scalar)."""
        return {"a": self.a.state.params, "b": self.b.state.params, "ratio": jnp.asarray(ratio, jnp.float32)}


def pair_models(a: TrainedModel, b: TrainedModel, seed: int = 0) -> MorphPair:
    """Match the alive points of two trained models; the larger cloud keeps its most confident
    points (:func:`~ne_jax.morph.matching.equal_size`)."""
    render = blended_render_config(a.run.render, b.run.render)
    pa, pb = a.state.point_state(a.scene.points), b.state.point_state(b.scene.points)
    alive_a, alive_b = np.flatnonzero(np.asarray(pa.alive)), np.flatnonzero(np.asarray(pb.alive))
    keep_a, keep_b = equal_size(alive_a.size, alive_b.size, seed, np.asarray(pa.confidence)[alive_a],
                                np.asarray(pb.confidence)[alive_b])
    slots_a, slots_b = alive_a[keep_a], alive_b[keep_b]
    perm = kd_match(np.asarray(pa.xyz)[slots_a], np.asarray(pb.xyz)[slots_b])
    return MorphPair(a=a, b=b, points_a=pa, points_b=pb, slots_a=slots_a, slots_b=slots_b[perm], render=render)


def _only(points: PointState, slots: np.ndarray) -> np.ndarray:
    """``[C]`` bool: ``slots`` of ``points``, the points alive after :func:`_moved`."""
    alive = np.zeros(points.capacity, bool)
    alive[slots] = True
    return alive & np.asarray(points.alive)


def _moved(points: PointState, slots: np.ndarray, cloud: np.ndarray, cfg: EditConfig,
           context: EditContext | None) -> tuple[PointState, dict]:
    """``points`` edited: ``slots`` moved to ``cloud``, every other alive point deleted (NaN rows);
    ``(points, report)`` (:func:`~ne_jax.edit.apply.apply_edit_with_report`)."""
    rows = np.full((points.capacity, 3), np.nan)
    rows[slots] = cloud
    return apply_edit_with_report(points, rows, cfg, context)


def morph_contexts(pair: MorphPair, cfg: EditConfig = EditConfig()) -> tuple[EditContext, EditContext]:
    """A's and B's :class:`~ne_jax.edit.apply.EditContext` for every :func:`morph_scene` of ``pair``
    with ``cfg`` (each cloud's IST neighbour table among its matched points): made once for a
    whole morph."""
    return (edit_context(cfg, pair.points_a, alive=_only(pair.points_a, pair.slots_a)),
            edit_context(cfg, pair.points_b, alive=_only(pair.points_b, pair.slots_b)))


def morph_scene(pair: MorphPair, cloud, cfg: EditConfig = EditConfig(),
                contexts: tuple[EditContext, EditContext] | None = None) -> PointScene:
    """The scene of intermediate ``cloud [N, 3]``: :func:`morph_scene_with_report` without its report."""
    return morph_scene_with_report(pair, cloud, cfg, contexts)[0]


def morph_scene_with_report(pair: MorphPair, cloud, cfg: EditConfig = EditConfig(),
                            contexts: tuple[EditContext, EditContext] | None = None) -> tuple[PointScene, dict]:
    """The scene of intermediate ``cloud [N, 3]`` (row ``i``: matched point ``i``) for
    :attr:`MorphPair.render`: both models edited onto the cloud (normals, ISTs), their per-point
    arrays side by side in A's slots, the K-D tree built. ``contexts``: :func:`morph_contexts` of
    ``pair`` and ``cfg``, held for a whole morph (made on the spot when ``None``).

    Returns ``(scene, report)``; ``report``: ``{"a": ..., "b": ...}``, each edit's report
    (:func:`~ne_jax.edit.apply.apply_edit_with_report`)."""
    cloud = np.asarray(cloud, np.float64)
    if cloud.shape != (pair.slots_a.size, 3):
        raise ValueError(f"morph_scene: expected a cloud of shape ({pair.slots_a.size}, 3) (the matched points), "
                         f"found {cloud.shape}")
    ctx_a, ctx_b = (None, None) if contexts is None else contexts
    ea, rep_a = _moved(pair.points_a, pair.slots_a, cloud, cfg, ctx_a)
    eb, rep_b = _moved(pair.points_b, pair.slots_b, cloud, cfg, ctx_b)
    c = pair.points_a.capacity
    dtype = ea.feature.dtype

    def in_a_slots(x_b, fill):  # B's per-point array, moved into A's slots
        out = jnp.broadcast_to(jnp.asarray(fill, dtype), (c,) + x_b.shape[1:])
        return out.at[pair.slots_a].set(x_b[pair.slots_b])

    points = PointState(
        xyz=ea.xyz, alive=ea.alive,
        feature=jnp.concatenate([ea.feature, in_a_slots(eb.feature, 0.0)], axis=-1),
        conf_logit=ea.conf_logit,
        normal=jnp.stack([ea.normal, in_a_slots(eb.normal, 0.0)], axis=1),
        ist=jnp.stack([ea.ist, in_a_slots(eb.ist, jnp.eye(3, dtype=dtype))], axis=1),
    )
    return PointScene.build(points, pair.render), {"a": rep_a, "b": rep_b}


__all__ = ["BlendedEffects", "BlendedShading", "MorphPair", "blended_render_config", "morph_contexts", "morph_scene",
           "morph_scene_with_report", "pair_models"]

"""The colour model (data flow step 6 of docs/design.md): per-segment density and colour from the
segment's mean feature, mean point normal, view direction and mean IST.

Flax flavour: ``linen``. Parameters are a plain nested dict created by ``init_color_model`` and
passed explicitly (``shade(cfg, params, ...)``), so the model is a pure function of
``(config, params, inputs)``, the param tree is inspectable as data and ``jax.grad`` / optax apply
unchanged; nnx's mutable module objects would need split/merge at every jit boundary for nothing.

Architecture (the released code's sizes, docs/design.md facts; ELU everywhere):

* trunk: ``Dense(F -> 48)``, residual block ``h + Dense(elu(Dense(elu(h))))``, ``elu``;
* heads on the trunk: density ``softplus(Dense_1 + 0.5)``, predicted normal
  ``normalize(Dense(48->16->3))``, diffuse ``Dense(48->16->3)``, tint ``sigmoid(Dense_3)``, roughness
  ``softplus(Dense_1 - 1)``, bottleneck ``elu(Dense_128)``;
* specular MLP on ``[bottleneck, IDE(reflected dir, roughness), n.d] -> 48 -> 16 -> 3``;
* colour ``c = sigmoid(0.5 diffuse + tint * specular)`` — the **released code's** formula (the paper
  only says "the Phong formula" following Ref-NeRF, which adds linear diffuse and tinted specular and
  tone-maps); like the released code (and multinerf) the sigmoid is widened by ``rgb_padding``:
  ``c (1 + 2p) - p``.

View redirection (IST): the IST maps the edited scene's frame to the original one (docs/design.md), and
the MLPs were trained in the original frame, so the view direction is mapped before reflection:
``d' = normalize(IST @ d)``. The reflection normal must live in the same frame: the *predicted* normal
is a function of the (original) features, so it is used as is; the *point* normal is re-estimated on
the edited cloud, so it is mapped too: ``n' = normalize(IST @ n)``. For a rotation IST this equals the
released code (reflect in the edited frame, then map the reflected direction); ``n'.d' = n.d``. With an
identity IST, ``IST @ v`` is computed elementwise (``v_i * 1 + 0 + 0``, exact), so the result is
bit-for-bit the one of a scene without the IST effect (tested).

Which normal reflects: the paper's colour model is "Phong reflection with point cloud normal
vectors" — the integrated *point* normal ``n_i`` shades, the predicted normal is only regularised
towards it (appendix "Phong Reflection Color Modeling"); the released code does the same after a
warm-up in which it reflects about ``normalize(mix * predicted + (1 - mix) * point)`` with ``mix``
decaying from 1 to 0 (pass ``pred_normal_mix`` for that). So ``Effects.point_normals=True`` reflects
about the point normal (the ``normal`` input is read); ``False`` is the paper's "- normal vectors"
ablation: Ref-NeRF style, reflection about the predicted normal, the ``normal`` input is never read
(the integrator need not interpolate normals at all). The predicted normal always exists: the
orientation and predicted-vs-point losses need it. Point normals from Open3D are unoriented: the
reflection is invariant to the normal's sign, ``n.d`` is not (orientation is the geometry's job).

Declared effects are static: a disabled effect's parameters do not exist and its ops are not traced.

Extension point: ``shade`` and ``background_color`` accept, in place of a ``ShadingConfig``, any
hashable object with ``effects`` (``uses_point_normals``, ``uses_ist``), ``shade(params, ...)`` and
``background_color(params, ...)`` methods; scene morphing's
:class:`~ne_jax.morph.blend.BlendedShading` blends two colour models this way.
"""

from __future__ import annotations

import dataclasses
from typing import Literal

import flax.linen as nn
import jax
import jax.numpy as jnp
from flax import struct

from ne_jax.numerics import safe_normalize, safe_sqrt
from ne_jax.render.ide import integrated_dir_enc, positional_encoding


@dataclasses.dataclass(frozen=True)
class Effects:
    """Effects a scene declares (static; hashable). Undeclared effects are not computed at all."""

    specular: bool = True
    """Ref-NeRF head only: tint, roughness, bottleneck, IDE and specular MLP. Off:
    ``c = sigmoid(0.5 diffuse)``, no view dependence (view direction, IST and normal unused)."""
    ist: bool = False
    """Redirect view directions (and point normals) by the segment's mean IST. Off: the ``ist``
    input is ignored (pass ``None``). Unedited scenes leave it off; it adds no parameters."""
    point_normals: bool = True
    """Reflect about the integrated point-cloud normal (paper); off: about the predicted normal."""
    background_model: Literal["constant", "sphere"] = "constant"
    """``"constant"``: a colour given at run time; ``"sphere"``: a learned background sphere."""
    color_head: Literal["refnerf", "traditional"] = "refnerf"
    """``"refnerf"``: diffuse + tint * specular (paper); ``"traditional"``: an MLP of the trunk feature
    and the positional encoding of the view direction (the paper's ablation baseline)."""

    def __post_init__(self):
        if self.background_model not in ("constant", "sphere"):
            raise ValueError(f"background_model must be 'constant' or 'sphere', got {self.background_model!r}")
        if self.color_head not in ("refnerf", "traditional"):
            raise ValueError(f"color_head must be 'refnerf' or 'traditional', got {self.color_head!r}")
        if self.color_head == "traditional" and self.specular:
            raise ValueError("specular belongs to the refnerf head; use specular=False with 'traditional'")

    @property
    def uses_view_dir(self) -> bool:
        """Whether the colour depends on the view direction at all."""
        return self.color_head == "traditional" or self.specular

    @property
    def uses_point_normals(self) -> bool:
        """Whether ``shade`` reads its ``normal`` input."""
        return self.color_head == "refnerf" and self.specular and self.point_normals

    @property
    def uses_ist(self) -> bool:
        """Whether ``shade`` reads its ``ist`` input."""
        return self.ist and self.uses_view_dir


DENSITY_BIAS = 0.5
"""``sigma = softplus(x + DENSITY_BIAS)``."""
ROUGHNESS_BIAS = -1.0
"""``roughness = softplus(x + ROUGHNESS_BIAS)``."""
DIFFUSE_SCALE = 0.5
"""``c = sigmoid(DIFFUSE_SCALE * diffuse + tint * specular)``."""
RGB_PADDING = 0.001
"""Colour range widening: ``c (1 + 2 p) - p`` (released code)."""
VIEW_PE_FREQS = 4
"""Frequencies of the view-direction encoding of the traditional head."""
BACKGROUND_PE_FREQS = 4
"""Frequencies of the encoding of the background-sphere point."""


@dataclasses.dataclass(frozen=True)
class ShadingConfig:
    """Static colour-model settings (docs/design.md facts by default)."""

    feature_dim: int = 32
    """Width of the integrated point feature."""
    trunk_width: int = 48
    """Width of the trunk and of the first hidden layer of the specular MLP."""
    head_width: int = 16
    """Hidden width of the two-layer heads (predicted normal, diffuse)."""
    bottleneck_dim: int = 128
    """Bottleneck feature fed to the specular MLP."""
    ide_degree: int = 5
    """IDE degree (5 -> 72 dims)."""
    specular_widths: tuple[int, ...] = (48, 16)
    """Hidden widths of the specular MLP (output 3)."""
    traditional_widths: tuple[int, ...] = (48, 16)
    """Hidden widths of the traditional colour MLP."""
    background_radius: float = 4.0
    """Radius of the background sphere centred at the origin (released code: 4)."""
    background_widths: tuple[int, ...] = (64, 32)
    """Hidden widths of the background-sphere MLP."""
    effects: Effects = Effects()
    """The scene's declared effects."""


@struct.dataclass
class ShadeOut:
    """Per-segment outputs of ``shade`` (``[...]`` = the batch shape of the inputs).

    Attributes:
        sigma: ``[...]`` density (per unit length; multiply by the segment length to composite).
        rgb: ``[..., 3]`` colour in ``[-p, 1 + p]``.
        pred_normal: ``[..., 3]`` unit predicted normal (for the orientation / normal losses).
        shading_normal: ``[..., 3]`` the unit normal the view direction was reflected about, in the
            IST-redirected frame; ``None`` without specular.
        roughness: ``[...]``; ``None`` without specular.
        tint: ``[..., 3]``; ``None`` without specular.
    """

    sigma: jax.Array
    rgb: jax.Array
    pred_normal: jax.Array
    shading_normal: jax.Array | None = None
    roughness: jax.Array | None = None
    tint: jax.Array | None = None


class MLP(nn.Module):
    """``Dense -> elu`` per hidden width, then a linear ``Dense(out_dim)``."""

    widths: tuple[int, ...]
    out_dim: int

    @nn.compact
    def __call__(self, x):
        for i, w in enumerate(self.widths):
            x = nn.elu(nn.Dense(w, name=f"hidden_{i}")(x))
        return nn.Dense(self.out_dim, name="out")(x)


class Trunk(nn.Module):
    """``h = Dense(x); elu(h + Dense(elu(Dense(elu(h)))))`` (the released ``feed_fea``)."""

    width: int

    @nn.compact
    def __call__(self, x):
        h = nn.Dense(self.width, name="in")(x)
        r = nn.Dense(self.width, name="res_0")(nn.elu(h))
        r = nn.Dense(self.width, name="res_1")(nn.elu(r))
        return nn.elu(h + r)


def redirect(ist: jax.Array, v: jax.Array) -> jax.Array:
    """``IST @ v`` for ``ist [..., 3, 3]``, ``v [..., 3]``, elementwise (exact for the identity)."""
    return jnp.sum(ist * v[..., None, :], axis=-1)


def reflect(d: jax.Array, n: jax.Array) -> jax.Array:
    """Mirror of the incoming direction ``d`` about unit ``n``: ``d - 2 (d.n) n`` (= Ref-NeRF's
    ``reflect(-d, n)``, the outgoing ray towards the reflected environment)."""
    return d - 2.0 * jnp.sum(d * n, axis=-1, keepdims=True) * n


def _pad_sigmoid(x: jax.Array, pad: float) -> jax.Array:
    return jax.nn.sigmoid(x) * (1.0 + 2.0 * pad) - pad


class SegmentShader(nn.Module):
    """Trunk, heads and colour branch selected by ``cfg.effects`` (see the module docstring)."""

    cfg: ShadingConfig

    @nn.compact
    def __call__(self, feature, normal, view_dir, ist, pred_normal_mix=None) -> ShadeOut:
        cfg, fx = self.cfg, self.cfg.effects
        h = Trunk(cfg.trunk_width, name="trunk")(feature)
        sigma = jax.nn.softplus(nn.Dense(1, name="density")(h)[..., 0] + DENSITY_BIAS)
        pred_normal = safe_normalize(MLP((cfg.head_width,), 3, name="normal")(h))

        d = None
        if fx.uses_view_dir:
            d = safe_normalize(redirect(ist, view_dir) if fx.ist else view_dir)

        if fx.color_head == "traditional":
            x = jnp.concatenate([h, positional_encoding(d, VIEW_PE_FREQS)], axis=-1)
            rgb = _pad_sigmoid(MLP(cfg.traditional_widths, 3, name="traditional")(x), RGB_PADDING)
            return ShadeOut(sigma=sigma, rgb=rgb, pred_normal=pred_normal)

        linear = DIFFUSE_SCALE * MLP((cfg.head_width,), 3, name="diffuse")(h)
        if not fx.specular:
            return ShadeOut(sigma=sigma, rgb=_pad_sigmoid(linear, RGB_PADDING),
                            pred_normal=pred_normal)

        tint = jax.nn.sigmoid(nn.Dense(3, name="tint")(h))
        roughness = jax.nn.softplus(nn.Dense(1, name="roughness")(h)[..., 0] + ROUGHNESS_BIAS)
        bottleneck = nn.elu(nn.Dense(cfg.bottleneck_dim, name="bottleneck")(h))
        if fx.point_normals:
            n = safe_normalize(redirect(ist, normal) if fx.ist else normal)
            if pred_normal_mix is not None:
                mix = jnp.asarray(pred_normal_mix, n.dtype)
                n = safe_normalize(mix * pred_normal + (1.0 - mix) * n)
        else:
            n = pred_normal
        enc = integrated_dir_enc(reflect(d, n), roughness, cfg.ide_degree)
        n_dot_d = jnp.sum(n * d, axis=-1, keepdims=True)
        specular = MLP(cfg.specular_widths, 3, name="specular")(
            jnp.concatenate([bottleneck, enc, n_dot_d], axis=-1))
        rgb = _pad_sigmoid(linear + tint * specular, RGB_PADDING)
        return ShadeOut(sigma=sigma, rgb=rgb, pred_normal=pred_normal, shading_normal=n,
                        roughness=roughness, tint=tint)


def sphere_exit_point(origin: jax.Array, direction: jax.Array, radius: float) -> jax.Array:
    """Unit vector to the far intersection of the ray with the sphere ``|x| = radius`` centred at
    the world origin, ``[..., 3]``; rays that miss the sphere fall back to their direction."""
    b = jnp.sum(origin * direction, axis=-1, keepdims=True)
    closest = origin - b * direction
    disc = radius * radius - jnp.sum(closest * closest, axis=-1, keepdims=True)
    point = closest + safe_sqrt(disc) * direction
    return jnp.where(disc > 0, safe_normalize(point, fallback=direction), direction)


class BackgroundSphere(nn.Module):
    """Colour of the background sphere where the ray leaves it: ``sigmoid(MLP(PE(point)))``.

    The paper's background sphere (appendix, Tanks and Temples) lets a scene whose background is not
    masked out model it without growing points there. The released code also learns a background
    opacity that blends with the constant colour; here the sphere is opaque (simpler, one head)."""

    cfg: ShadingConfig

    @nn.compact
    def __call__(self, origin, direction):
        u = sphere_exit_point(origin, safe_normalize(direction), self.cfg.background_radius)
        x = positional_encoding(u, BACKGROUND_PE_FREQS)
        raw = MLP(self.cfg.background_widths, 3, name="mlp")(x)
        return _pad_sigmoid(raw, RGB_PADDING)


def init_color_model(cfg: ShadingConfig, key: jax.Array) -> dict:
    """Random parameters: ``{"shader": ..., "background": ...}`` (``background`` only for the sphere).
    Branches of undeclared effects are absent from the tree."""
    k_shader, k_bg = jax.random.split(key)
    f = jnp.zeros((1, cfg.feature_dim))
    v = jnp.zeros((1, 3)).at[:, 2].set(1.0)
    ist = jnp.eye(3)[None]
    params = {"shader": SegmentShader(cfg).init(k_shader, f, v, v, ist)["params"]}
    if cfg.effects.background_model == "sphere":
        params["background"] = BackgroundSphere(cfg).init(k_bg, jnp.zeros((1, 3)), v)["params"]
    return params


def shade(cfg: ShadingConfig, params: dict, feature: jax.Array, normal: jax.Array | None,
          view_dir: jax.Array, ist: jax.Array | None = None,
          pred_normal_mix: jax.Array | float | None = None) -> ShadeOut:
    """Density and colour of segments.

    Args:
        feature: ``[..., F]`` mean feature. normal: ``[..., 3]`` mean point normal (read only when
            ``cfg.effects.uses_point_normals``; may be ``None`` otherwise). view_dir: ``[..., 3]`` ray
            direction (normalised here). ist: ``[..., 3, 3]`` mean IST (read only when
            ``cfg.effects.uses_ist``). pred_normal_mix: optional scalar in ``[0, 1]``, warm-up blend of
            the predicted normal into the reflection normal (point normals only).
    """
    if not isinstance(cfg, ShadingConfig):  # a stand-in with its own shade, e.g. morphing's BlendedShading
        return cfg.shade(params, feature, normal, view_dir, ist, pred_normal_mix)
    fx = cfg.effects
    if fx.uses_point_normals and normal is None:
        raise ValueError("this scene reflects about point normals: pass `normal`")
    if fx.uses_ist and ist is None:
        raise ValueError("this scene declares the IST effect: pass `ist`")
    if feature.shape[-1] != cfg.feature_dim:
        raise ValueError(f"feature width {feature.shape[-1]} != cfg.feature_dim {cfg.feature_dim}")
    return SegmentShader(cfg).apply({"params": params["shader"]}, feature, normal, view_dir, ist,
                                    pred_normal_mix)


def background_color(cfg: ShadingConfig, params: dict, origin: jax.Array, direction: jax.Array,
                     constant: jax.Array | None = None) -> jax.Array:
    """Background colour per ray ``[..., 3]``: the learned sphere (``origin, direction [..., 3]``;
    ``constant`` unused) or ``constant [3]`` broadcast (required for ``"constant"``)."""
    if not isinstance(cfg, ShadingConfig):  # a stand-in, e.g. morphing's BlendedShading
        return cfg.background_color(params, origin, direction, constant)
    if cfg.effects.background_model == "sphere":
        return BackgroundSphere(cfg).apply({"params": params["background"]}, origin, direction)
    if constant is None:
        raise ValueError("a 'constant' background needs its colour: pass `constant`")
    constant = jnp.asarray(constant, direction.dtype)
    return jnp.broadcast_to(constant, (*direction.shape[:-1], 3))


def num_params(params) -> int:
    """Total number of scalars in a parameter tree."""
    return sum(int(x.size) for x in jax.tree_util.tree_leaves(params))


__all__ = [
    "MLP",
    "BackgroundSphere",
    "Effects",
    "SegmentShader",
    "ShadeOut",
    "ShadingConfig",
    "Trunk",
    "background_color",
    "init_color_model",
    "num_params",
    "redirect",
    "reflect",
    "shade",
    "sphere_exit_point",
]

"""Which effects a run models: declared by the scene folder, given on the command line, or decided
from the training images (``auto``). An effect a run does not declare has no parameters and no ops
(:class:`~ne_jax.render.shading.Effects`).

Declarable effects and their values (:data:`DECLARABLE`):

* ``specular``: ``on`` (view-dependent colour: the Ref-NeRF head's tint, roughness, IDE and specular
  MLP) or ``off`` (colour from the diffuse head alone);
* ``background_model``: ``constant`` (a colour given at run time: images with an alpha mask) or ``sphere``
  (a learned background: images that hold their background).

A scene folder states them in its ``scene.json`` as ``"effects": {"specular": true,
"background_model": "constant"}`` (the benchmark writes it from what its ground-truth renderer does). A spec string (the
CLI's ``--effects``) is ``scene`` (the folder's declaration, else the preset's), ``auto`` (decided
from the training split, :func:`auto_effects`), ``all`` (every effect on: ``specular=on,
background_model=sphere``) or ``name=value`` pairs separated by commas, applied over the preset's.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ne_jax.render.renderer import RenderConfig

DECLARABLE: dict[str, tuple] = {"specular": ("on", "off"), "background_model": ("constant", "sphere")}
"""Effects a scene or the command line may declare, with their values."""

ALL_ON = {"specular": "on", "background_model": "sphere"}
"""``--effects all``: every declarable effect on."""

class EffectsError(ValueError):
    """A bad effects declaration: names where it came from, what was expected and what was found."""


def _value(name: str, value, where: str) -> str:
    if name not in DECLARABLE:
        raise EffectsError(f"{where}: unknown effect {name!r}; expected one of {sorted(DECLARABLE)}")
    if isinstance(value, bool) and name == "specular":
        value = "on" if value else "off"
    text = str(value).strip().lower()
    text = {"true": "on", "false": "off", "1": "on", "0": "off"}.get(text, text)
    if text not in DECLARABLE[name]:
        raise EffectsError(f"{where}: effect {name!r} expected one of {list(DECLARABLE[name])}, found {value!r}")
    return text


def parse_effects(spec: str, where: str = "--effects") -> dict[str, str]:
    """``"specular=off,background_model=sphere"`` -> ``{"specular": "off", "background_model": "sphere"}``."""
    out = {}
    for part in (p.strip() for p in spec.split(",")):
        if not part:
            continue
        name, sep, value = part.partition("=")
        if not sep:
            pairs = ", ".join(f"{k}={'|'.join(v)}" for k, v in DECLARABLE.items())
            raise EffectsError(f"{where}: expected name=value pairs ({pairs}), or scene, auto or all; found {part!r}")
        out[name.strip()] = _value(name.strip(), value, where)
    return out


def scene_effects(scene_dir) -> dict[str, str] | None:
    """The effects ``scene_dir/scene.json`` declares (``None`` when it declares none)."""
    path = Path(scene_dir) / "scene.json"
    if not path.is_file():
        return None
    declared = json.loads(path.read_text(encoding="utf-8")).get("effects")
    if declared is None:
        return None
    if not isinstance(declared, dict):
        raise EffectsError(f"{path}: expected \"effects\" to be an object of name: value, found {declared!r}")
    return {name: _value(name, value, str(path)) for name, value in declared.items()}


def effects_of(render: RenderConfig) -> dict[str, str]:
    """The declarable effects of a render config, as declared values."""
    e = render.shading.effects
    return {"specular": "on" if e.specular else "off", "background_model": e.background_model}


def with_declared(render: RenderConfig, effects: dict[str, str]) -> RenderConfig:
    """``render`` with the declared ``effects`` (a subset of :data:`DECLARABLE`) set."""
    changes = {}
    if "specular" in effects:
        changes["specular"] = effects["specular"] == "on"
    if "background_model" in effects:
        changes["background_model"] = effects["background_model"]
    return render.with_effects(**changes)


def auto_effects(split, cloud_xyz: np.ndarray | None, *, opaque_share: float = 0.98, spread: float = 0.05,
                 share: float = 0.01, window: int = 5, max_points: int = 6000, seed: int = 0
                 ) -> tuple[dict[str, str], dict]:
    """Decide the effects from a training ``split`` and a cloud near its surface (the carved
    initial cloud; ``None`` where there is none: specular then stays on). Returns ``(effects, evidence)``.

    * ``background_model``: ``sphere`` when more than ``opaque_share`` of all pixels are opaque (alpha >=
      0.99: the images hold their background, or the masks leave it in the foreground), else
      ``constant``.
    * ``specular``: per point (at most ``max_points``) and view that sees it (z-buffered,
      :func:`~ne_jax.pointcloud.init.visibility`), the luminance range of the ``window x window``
      pixels around its projection. A diffuse point's colour lies in every view's range, however far
      the cloud is from the surface; a highlight or reflection that moves with the view leaves a gap
      (the 90th percentile of the ranges' lower ends above the 10th of their upper ends). ``on``
      when more than ``share`` of the points have a gap above ``spread``. Measured on the
      benchmark at ``tiny``: ray-cast glossy 5.7%, cup 6.2%, stool 2.2% of the points, the matte
      blocks 0.2% (all four right); path-traced glossy 6.7%, stool 3.0%, blocks 0.35%, and the
      glazed cup 0.28% (missed). The cloud's distance from the surface and occlusion between parts
      also leave gaps: a matte glossy scene at 64 px and mesh detail 0.4 scores 4.0% (on).
    """
    from ne_jax.pointcloud.init import Views, visibility
    from ne_jax.pointcloud.normals import mean_spacing

    alpha = split.images[..., 3]
    opaque = float((alpha >= 0.99).mean())
    evidence = {"opaque_pixels": round(opaque, 4), "opaque_share": opaque_share}
    effects = {"background_model": "sphere" if opaque > opaque_share else "constant"}

    if cloud_xyz is None or len(cloud_xyz) == 0:
        effects["specular"] = "on"
        evidence["note"] = "no cloud near the surface to decide from (carving needs alpha masks): specular kept on"
        return effects, evidence
    xyz = np.asarray(cloud_xyz, np.float64)
    if len(xyz) > max_points:
        xyz = xyz[np.random.default_rng(seed).choice(len(xyz), max_points, replace=False)]
    views = Views.from_split(split)
    seen = visibility(views, xyz, mean_spacing(xyz))
    lum_img = split.images[..., :3] @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    h, w = lum_img.shape[1:]
    lo = np.full(seen.shape, np.nan)  # per view and point: the luminance range around its projection
    hi = np.full(seen.shape, np.nan)
    r = int(window) // 2
    for k in range(views.num_views):
        idx = np.flatnonzero(seen[k])
        u, v, _ = views.project(k, xyz[idx])
        iu, iv = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
        ok = (iu >= 0) & (iu < w) & (iv >= 0) & (iv < h)
        idx, iu, iv = idx[ok], iu[ok], iv[ok]
        ok = alpha[k, iv, iu] >= 0.5  # on the object in this view
        idx, iu, iv = idx[ok], iu[ok], iv[ok]
        win = np.stack([lum_img[k, np.clip(iv + dv, 0, h - 1), np.clip(iu + du, 0, w - 1)]
                        for dv in range(-r, r + 1) for du in range(-r, r + 1)])
        lo[k, idx], hi[k, idx] = win.min(0), win.max(0)
    counted = np.sum(~np.isnan(lo), axis=0) >= 3
    if counted.sum() == 0:
        effects["specular"] = "on"
        evidence.update(specular_points=0, note="no point seen by 3 views: specular kept on")
        return effects, evidence
    # a diffuse point's colour lies in every view's window (whatever the cloud's distance from the
    # surface shifts); a highlight that moves with the view leaves no value common to the windows
    gap = np.nanpercentile(lo[:, counted], 90, axis=0) - np.nanpercentile(hi[:, counted], 10, axis=0)
    moving = float((gap > spread).mean())
    effects["specular"] = "on" if moving > share else "off"
    evidence.update(specular_points=int(counted.sum()), view_dependent_share=round(moving, 4),
                    spread=spread, share=share)
    return effects, evidence


def declare_effects(render: RenderConfig, spec: str, scene_dir, split=None, cloud_xyz=None
                    ) -> tuple[RenderConfig, dict]:
    """The render config a run trains with under the effects ``spec`` (module docstring), and a
    record of the decision for the run's metrics: ``{"spec", "source", "effects", "evidence"?}``.
    ``auto`` needs the training ``split`` and a cloud near the surface (``cloud_xyz``, or ``None``)."""
    spec = spec.strip()
    if spec == "scene":
        declared = scene_effects(scene_dir)
        source = "scene.json" if declared is not None else "preset"
        declared = declared or {}
        evidence = None
    elif spec == "all":
        declared, source, evidence = dict(ALL_ON), "all", None
    elif spec == "auto":
        if split is None:
            raise EffectsError("--effects auto: expected the training split to decide from")
        declared, evidence = auto_effects(split, cloud_xyz)
        source = "auto"
    else:
        declared, source, evidence = parse_effects(spec), "command line", None
    render = with_declared(render, declared)
    record = {"spec": spec, "source": source, "effects": effects_of(render)}
    if evidence is not None:
        record["evidence"] = evidence
    return render, record


__all__ = ["ALL_ON", "DECLARABLE", "EffectsError", "auto_effects", "declare_effects", "effects_of", "parse_effects",
           "scene_effects", "with_declared"]

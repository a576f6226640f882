"""A morph from end to end (host side): pair two trained models, walk the path of intermediate
clouds, render every frame blended by its ratio, measure how smoothly the frames change, and write
PNG frames, a video, a strip of frames and a JSON report (``ne-jax morph A B --steps T``).

Smoothness (the paper judged morphs by eye only): for frames ``F_0..F_{T-1}`` of one camera,

* ``step_change[t] = mean |F_{t+1} - F_t|`` (per pixel and channel, in [0, 1]) — what a viewer sees
  jump between frames; its ``mean`` and ``max`` are reported;
* ``path_ratio = sum_t step_change[t] / mean |F_{T-1} - F_0|`` — 1 when every pixel moves
  monotonically from its start to its end colour (a clean cross-fade), larger when frames flicker or
  detour (colour that appears and disappears again).
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Sequence
from pathlib import Path

import jax
import numpy as np
from tqdm.auto import tqdm

from ne_jax.atomic import atomic_directory, atomic_write_text
from ne_jax.data.nerf_synthetic import parse_background
from ne_jax.data.png import write_image
from ne_jax.data.rays import Camera
from ne_jax.edit.apply import EditConfig
from ne_jax.eval.views import save_images, write_video
from ne_jax.morph.blend import MorphPair, morph_contexts, morph_scene_with_report, pair_models
from ne_jax.morph.path import linear_path, morph_ratios, path_from_clouds
from ne_jax.render.driver import render_image
from ne_jax.train.model import TrainedModel


def smoothness(frames) -> dict:
    """Frame-to-frame change of ``frames [T, H, W, 3]`` (module docstring): ``step_change [T-1]``,
    its ``mean`` and ``max``, the ``end_change`` ``mean |F_{T-1} - F_0|`` and the ``path_ratio``."""
    frames = np.asarray(frames, np.float64)
    if frames.ndim != 4 or frames.shape[0] < 2:
        raise ValueError(f"smoothness: expected frames [T, H, W, C] with T >= 2, found shape {frames.shape}")
    steps = np.abs(np.diff(frames, axis=0)).mean(axis=(1, 2, 3))
    end = float(np.abs(frames[-1] - frames[0]).mean())
    return {"step_change": [round(float(s), 6) for s in steps], "mean": float(steps.mean()),
            "max": float(steps.max()), "end_change": end,
            "path_ratio": float(steps.sum() / end) if end > 0 else float("nan")}


def render_morph(pair: MorphPair, path: Sequence[np.ndarray], camera: Camera | Sequence[Camera], background,
                 near: float, far: float, edit: EditConfig = EditConfig(), progress: bool = True,
                 ratios: Sequence[float] | None = None) -> tuple[np.ndarray, list[dict]]:
    """Render ``path`` (``T`` indexed clouds ``[N, 3]``) from ``camera`` (one, or one per frame) at
    ``ratios`` (default evenly spaced 0..1) -> frames ``[T, H, W, 3]`` and one report per frame
    (ratio, seconds, segments lost, IST counts of both edits). Every frame has the same array shapes,
    so the renderer compiles once for the whole morph."""
    ratios = morph_ratios(len(path)) if ratios is None else np.asarray(ratios, np.float64)
    cameras = list(camera) if isinstance(camera, (list, tuple)) else [camera] * len(path)
    if len(cameras) != len(path) or len(ratios) != len(path):
        raise ValueError(f"render_morph: expected one camera (or {len(path)}) and {len(path)} ratios, found "
                         f"{len(cameras)} cameras and {len(ratios)} ratios")
    bg = parse_background(background)
    contexts = morph_contexts(pair, edit)  # every frame edits the same two clouds onto the same matched points
    frames, reports = [], []
    for cloud, r, cam in tqdm(list(zip(path, ratios, cameras)), desc="morph", unit="frame", disable=not progress):
        t0 = time.perf_counter()
        scene, edits = morph_scene_with_report(pair, cloud, edit, contexts)
        out = render_image(pair.render, pair.params(r), scene, cam, bg, near, far, progress=False)
        rgb, lost = jax.device_get((out.rgb, out.lost.count.sum()))
        frames.append(np.asarray(rgb, np.float32))
        reports.append({"ratio": round(float(r), 6), "seconds": round(time.perf_counter() - t0, 3),
                        "lost_segments": int(lost),
                        **{f"ist_{k}_{m}": edits[m].get(k) for m in ("a", "b") for k in ("good", "filled")}})
    return np.stack(frames), reports


def strip(frames: np.ndarray, count: int = 6, pad: int = 2) -> np.ndarray:
    """``count`` evenly spaced frames side by side (white gaps of ``pad`` pixels) ``[H, W', 3]``."""
    idx = np.unique(np.round(np.linspace(0, len(frames) - 1, min(count, len(frames)))).astype(int))
    h, w = frames.shape[1:3]
    out = np.ones((h, len(idx) * (w + pad) - pad, 3), np.float32)
    for j, i in enumerate(idx):
        out[:, j * (w + pad):j * (w + pad) + w] = np.clip(frames[i], 0.0, 1.0)
    return out


@dataclasses.dataclass(frozen=True)
class MorphSettings:
    """How :func:`morph_models` runs: ``steps`` frames (``T``; ignored with intermediate clouds,
    which give ``T = len + 2``), the ``seed`` of :func:`~ne_jax.morph.matching.equal_size`,
    ``video`` file name (``.mp4`` or ``.gif``) and ``fps``."""

    steps: int = 24
    seed: int = 0
    video: str = "morph.mp4"
    fps: float = 12.0
    edit: EditConfig = EditConfig()


def morph_models(a: TrainedModel, b: TrainedModel, out_dir: str | Path, camera: Camera | Sequence[Camera],
                 settings: MorphSettings = MorphSettings(), intermediate: Sequence | None = None,
                 background=None, progress: bool = True, labels: tuple[str, str] = ("A", "B")
                 ) -> tuple[dict, np.ndarray]:
    """Morph model ``a`` into model ``b`` and write ``out_dir`` atomically: ``frames/frame_###.png``,
    the video, ``strip.png`` and ``morph.json`` (settings, matching, per-frame reports, smoothness).

    ``intermediate``: clouds from another generator (arrays or ``.npy``/``.ply`` files, unindexed,
    ordered from A to B, each of the matched size); default the straight-line stand-in
    (:func:`~ne_jax.morph.path.linear_path`). ``background``: default model A's. Returns the report
    and the frames ``[T, H, W, 3]``."""
    t0 = time.perf_counter()
    pair = pair_models(a, b, settings.seed)
    given = f"{len(intermediate or ())} intermediate clouds given, chained by the K-D matching"
    path = (linear_path(pair.cloud_a, pair.cloud_b, settings.steps) if intermediate is None
            else path_from_clouds(pair.cloud_a, pair.cloud_b, intermediate))
    background = a.run.background if background is None else background
    frames, per_frame = render_morph(pair, path, camera, background, a.run.sampler.near, a.run.sampler.far,
                                     settings.edit, progress)
    report = {
        "what": f"morph of {labels[0]} into {labels[1]}: both models rendered through each intermediate cloud, "
                "density and colour blended by the morph ratio",
        "path": "straight lines along the K-D matching (stand-in for the paper's diffusion-model clouds)"
                if intermediate is None else given,
        "frames": len(path), "points": {"a_alive": int(np.asarray(pair.points_a.alive).sum()),
                                        "b_alive": int(np.asarray(pair.points_b.alive).sum()),
                                        "matched": int(pair.slots_a.size)},
        "background": str(background), "smoothness": smoothness(frames), "per_frame": per_frame,
        "seconds": round(time.perf_counter() - t0, 1),
    }
    with atomic_directory(out_dir) as tmp:
        save_images(frames, tmp / "frames", [f"frame_{i:03d}" for i in range(len(frames))])
        write_video(frames, tmp / settings.video, fps=settings.fps)
        write_image(tmp / "strip.png", strip(frames))
        atomic_write_text(tmp / "morph.json", json.dumps(report, indent=2) + "\n")
    return report, frames


__all__ = ["MorphSettings", "morph_models", "render_morph", "smoothness", "strip"]

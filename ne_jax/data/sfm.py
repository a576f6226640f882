"""Structure from motion: a folder of photos -> a COLMAP scene folder (poses, intrinsics, sparse points).

:func:`process_images` runs COLMAP through pycolmap on the CPU: SIFT features, exhaustive (or
sequential) matching with geometric verification, and incremental mapping. It writes the standard
COLMAP layout that :func:`ne_jax.data.formats.colmap.read_colmap` (and nerfstudio, gsplat, COLMAP
itself) read::

    <out>/images/<photo>            the photos, hard-linked (copied across file systems)
    <out>/sparse/0/cameras.bin      the largest reconstructed model, COLMAP binary
    <out>/sparse/0/images.bin       world-to-camera poses, OpenCV camera axes
    <out>/sparse/0/points3D.bin     the sparse points (pycolmap 4 adds rigs.bin, frames.bin)
    <out>/database.db               COLMAP's database (features, matches), to re-run a stage
    <out>/sfm.json                  the report :func:`process_images` returns, with its settings

Nothing is written half: everything is built in a temporary sibling of ``out`` and renamed into
place when every stage has succeeded (:func:`ne_jax.atomic.atomic_directory`).

:func:`similarity_align` (Umeyama) aligns recovered camera centres to known ones, to measure a
reconstruction's pose error where the true poses are known (a synthetic capture).
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import shutil
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from ne_jax.atomic import atomic_directory, atomic_write_json
from ne_jax.data.formats._common import IMAGE_SUFFIXES
from ne_jax.data.formats.colmap import SUPPORTED_MODELS
from ne_jax.data.png import DataError, fail

MIN_IMAGES = 3
"""Fewest photos, and fewest registered images, a reconstruction is accepted with."""
MATCHERS = ("exhaustive", "sequential")
"""``exhaustive``: every pair of photos (quadratic; a few hundred photos); ``sequential``: each photo
with the ``sequential_overlap`` next ones in name order (a video or a walk around)."""
CAMERA_MODELS = SUPPORTED_MODELS
"""COLMAP camera models :func:`process_images` accepts: those the COLMAP reader takes."""

_SUGGESTIONS = ("photos that overlap more (each part of the scene in several photos taken 10-20 degrees "
                "apart), more texture in view (plain walls, sky and reflections give no features), sharper "
                "photos")


def list_photos(photos: str | os.PathLike) -> list[str]:
    """The names of the photos directly inside ``photos`` (:data:`IMAGE_SUFFIXES`, any case; hidden
    files and sub-folders are skipped), sorted. Raises :class:`DataError` where ``photos`` is not a
    folder or holds fewer than :data:`MIN_IMAGES` photos."""
    photos = Path(photos)
    if not photos.exists():
        raise fail(photos, None, "expected a folder of photos, found nothing at this path")
    if not photos.is_dir():
        raise fail(photos, None, "expected a folder of photos, found a file")
    names = sorted(p.name for p in photos.iterdir()
                   if p.is_file() and not p.name.startswith(".") and p.suffix.lower() in IMAGE_SUFFIXES)
    if len(names) < MIN_IMAGES:
        others = sum(1 for p in photos.iterdir() if p.name not in names)
        raise fail(photos, None, f"expected at least {MIN_IMAGES} photos ({'/'.join(IMAGE_SUFFIXES)}, any case), "
                                 f"found {len(names)} (and {others} other entries)")
    return names


@contextlib.contextmanager
def _colmap_log(verbose: bool) -> Iterator[None]:
    """COLMAP's own log (glog, on stderr) from INFO up with ``verbose``, else its errors only (its
    warnings are per-attempt notes such as discarded partial models); the previous level is restored
    afterwards."""
    import pycolmap

    before = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 0 if verbose else 2
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = before


def _link_or_copy(src: Path, dst: Path) -> str:
    """Hard-link ``src`` to ``dst``, or copy it where a link cannot be made; returns which."""
    try:
        os.link(src, dst)
        return "linked"
    except OSError:
        shutil.copy2(src, dst)
        return "copied"


def _stats(values: list[int]) -> dict:
    return {"min": int(min(values)), "mean": float(np.mean(values)), "max": int(max(values))} if values else {}


def process_images(photos: str | os.PathLike, out: str | os.PathLike, *, matcher: str = "exhaustive",
                   camera_model: str = "SIMPLE_RADIAL", single_camera: bool = True,
                   max_image_size: int = 3200, max_num_features: int = 8192, guided_matching: bool = False,
                   sequential_overlap: int = 10, num_threads: int = 1, seed: int = 0,
                   overwrite: bool = False, verbose: bool = False,
                   progress: Callable[[str], object] | None = print) -> dict:
    """Reconstruct the cameras of the photos in ``photos`` and write a COLMAP scene folder ``out``.

    ``photos``: a folder of ``.png``/``.jpg``/``.jpeg`` files (not searched recursively);
    ``out``: the scene folder to make (module docstring: layout); an existing non-empty ``out`` is
    replaced only with ``overwrite``, and only once everything succeeded.

    ``matcher``: ``"exhaustive"`` or ``"sequential"`` (:data:`MATCHERS`; ``sequential_overlap``
    next photos in name order); ``camera_model``: a COLMAP model of :data:`CAMERA_MODELS`
    (``SIMPLE_RADIAL``, the default: one focal length, the principal point and one radial term;
    ``PINHOLE``'s two free focal lengths can converge to a wrong solution on small images, see
    :func:`camera_warnings`); ``single_camera``: every photo shares one camera
    (one set of intrinsics), else COLMAP's ``AUTO`` mode (one camera per image size and EXIF
    model); ``max_image_size``: features are found on photos downscaled to this longest side
    (cameras keep the photos' full resolution); ``max_num_features``: per photo;
    ``guided_matching``: a second matching pass guided by each verified pair's geometry (more
    inlier matches for more matching time; off, as in COLMAP);
    ``num_threads``: COLMAP's threads in every stage; with 1 (the default) a run is repeatable bit
    for bit (the same photos and ``seed`` give the same model files); with more, the features are
    the same but geometric verification draws its RANSAC samples in whatever order the threads take
    the pairs, so the model can differ slightly from run to run; ``seed``: COLMAP's random choices
    (its global generator, RANSAC, the mapper); ``verbose``: COLMAP's own INFO log on stderr (else
    its errors only); ``progress``: called with one line per stage (``None``: silent).

    Returns the report (also written to ``out/sfm.json``): ``images`` (photos found), ``features``
    (keypoints: ``total`` and per image ``min/mean/max``), ``pairs`` (``candidates`` matched,
    ``verified``: with a verified two-view geometry, ``inlier_matches``), ``registered``,
    ``unregistered`` (names), ``points``, ``mean_reprojection_error`` (pixels), ``mean_track_length``,
    ``models`` (how many were reconstructed), ``other_models`` (``[registered images, points]`` of
    each model not kept, largest first), ``cameras`` (model and parameters), ``warnings``
    (:func:`camera_warnings`: intrinsics that look wrong; also printed), ``seconds`` per stage
    (``copy``, ``extract``, ``match``, ``map``, ``total``) and ``settings``.

    Raises :class:`DataError` (naming the folder, what was expected and what was found) where
    ``photos`` is missing, not a folder or holds fewer than :data:`MIN_IMAGES` photos, where fewer
    than that can be read, where ``out`` is a file, ``photos`` itself or not empty (without
    ``overwrite``), and where fewer than :data:`MIN_IMAGES` images register; ``ValueError`` for an
    unknown ``matcher`` or ``camera_model``."""
    import pycolmap

    if matcher not in MATCHERS:
        raise ValueError(f"matcher: expected one of {MATCHERS}, found {matcher!r}")
    if camera_model not in CAMERA_MODELS:
        raise ValueError(f"camera_model: expected one of {CAMERA_MODELS}, found {camera_model!r}")
    if num_threads < 1:
        raise ValueError(f"num_threads: expected a positive count, found {num_threads}")
    say = progress or (lambda line: None)
    photos, out = Path(photos), Path(out)
    t_start = time.perf_counter()
    names = list_photos(photos)
    if out.exists() and not out.is_dir():
        raise fail(out, None, "expected a folder (or nothing) to write the scene to, found a file")
    if out.resolve() == photos.resolve():
        raise fail(out, None, "expected a new folder for the scene, found the photos folder itself")
    if out.is_dir() and any(out.iterdir()) and not overwrite:
        raise fail(out, None, f"expected a new or empty folder, found {sum(1 for _ in out.iterdir())} entries "
                              "(pass overwrite=True to replace it)")
    settings = {"matcher": matcher, "camera_model": camera_model, "single_camera": single_camera,
                "max_image_size": max_image_size, "max_num_features": max_num_features,
                "guided_matching": guided_matching, "sequential_overlap": sequential_overlap,
                "num_threads": num_threads, "seed": seed, "device": "cpu",
                "pycolmap": pycolmap.__version__, "colmap": pycolmap.COLMAP_version}
    seconds: dict[str, float] = {}
    say(f"process_images: {len(names)} photos in {photos}")

    with _colmap_log(verbose), atomic_directory(out, fsync=True) as tmp:
        t = time.perf_counter()
        images_dir = tmp / "images"
        images_dir.mkdir()
        how = [_link_or_copy(photos / name, images_dir / name) for name in names]
        seconds["copy"] = time.perf_counter() - t
        say(f"  images: {how.count('linked')} linked, {how.count('copied')} copied to {out / 'images'} "
            f"({seconds['copy']:.1f} s)")

        pycolmap.set_random_seed(seed)
        database = tmp / "database.db"
        t = time.perf_counter()
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = camera_model
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.use_gpu = False
        extraction.num_threads = num_threads
        extraction.max_image_size = max_image_size
        extraction.sift.max_num_features = max_num_features
        pycolmap.extract_features(database, images_dir, image_names=names,
                                  camera_mode=pycolmap.CameraMode.SINGLE if single_camera else pycolmap.CameraMode.AUTO,
                                  reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
        with pycolmap.Database.open(database) as db:
            read = {image.name: db.num_keypoints_for_image(image.image_id) for image in db.read_all_images()}
        seconds["extract"] = time.perf_counter() - t
        unreadable = [n for n in names if n not in read]
        if len(read) < MIN_IMAGES:
            raise fail(photos, None, f"expected at least {MIN_IMAGES} readable photos, COLMAP read {len(read)} of "
                                     f"{len(names)} (unreadable: {', '.join(unreadable[:5])}"
                                     f"{', ...' if len(unreadable) > 5 else ''})")
        counts = [read[n] for n in names if n in read]
        say(f"  features: {sum(counts):,} SIFT keypoints in {len(read)} images (per image min {min(counts):,}, "
            f"mean {np.mean(counts):,.0f}, max {max(counts):,})"
            + (f"; {len(unreadable)} unreadable: {', '.join(unreadable[:5])}" if unreadable else "")
            + f" ({seconds['extract']:.1f} s)")

        t = time.perf_counter()
        matching = pycolmap.FeatureMatchingOptions()
        matching.use_gpu = False
        matching.num_threads = num_threads
        matching.guided_matching = guided_matching
        verification = pycolmap.TwoViewGeometryOptions()
        verification.ransac.random_seed = seed
        if matcher == "exhaustive":
            pycolmap.match_exhaustive(database, matching_options=matching, verification_options=verification,
                                      device=pycolmap.Device.cpu)
        else:
            pairing = pycolmap.SequentialPairingOptions()
            pairing.overlap = sequential_overlap
            pairing.num_threads = num_threads
            pycolmap.match_sequential(database, matching_options=matching, pairing_options=pairing,
                                      verification_options=verification, device=pycolmap.Device.cpu)
        with pycolmap.Database.open(database) as db:
            candidates = db.num_matched_image_pairs()
            _pair_ids, geometries = db.read_two_view_geometries()
        inliers = [len(g.inlier_matches) for g in geometries]
        verified = [n for n in inliers if n >= verification.min_num_inliers]
        seconds["match"] = time.perf_counter() - t
        say(f"  matching ({matcher}{', guided' if guided_matching else ''}): {candidates:,} pairs matched, "
            f"{len(verified):,} verified with {sum(verified):,} inlier matches ({seconds['match']:.1f} s)")

        t = time.perf_counter()
        options = pycolmap.IncrementalPipelineOptions()
        options.num_threads = num_threads
        options.random_seed = seed
        scratch = tmp / ".mapper"
        scratch.mkdir()
        models = pycolmap.incremental_mapping(database, images_dir, scratch, options=options)
        ranked = sorted(models.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()), reverse=True)
        seconds["map"] = time.perf_counter() - t
        best = ranked[0] if ranked else None
        registered = best.num_reg_images() if best is not None else 0
        if registered < MIN_IMAGES:
            other_matcher = ("matcher='exhaustive' or a larger sequential_overlap" if matcher == "sequential"
                             else "matcher='sequential' for the frames of a video")
            raise fail(photos, None,
                       f"expected at least {MIN_IMAGES} photos registered in one model, found {registered} of "
                       f"{len(names)} ({len(models)} models; {len(verified)} of {candidates} photo pairs verified, "
                       f"{sum(counts):,} features). Try {_SUGGESTIONS}, or {other_matcher}")
        other = [[r.num_reg_images(), r.num_points3D()] for r in ranked[1:]]
        say(f"  mapping: {registered} of {len(names)} images registered, {best.num_points3D():,} points, "
            f"mean reprojection error {best.compute_mean_reprojection_error():.2f} px, {len(models)} model"
            f"{'s' if len(models) != 1 else ''}"
            + (f" (kept the largest; others [images, points]: {other})" if other else "")
            + f" ({seconds['map']:.1f} s)")
        reg_names = {best.images[i].name for i in best.reg_image_ids()}
        unregistered = [n for n in names if n not in reg_names]
        warnings = camera_warnings(best)
        if unregistered:
            say(f"  not registered: {', '.join(unregistered[:10])}{', ...' if len(unregistered) > 10 else ''}")
        for warning in warnings:
            say(f"  warning: {warning}")
        sparse = tmp / "sparse" / "0"
        sparse.mkdir(parents=True)
        best.write(sparse)
        shutil.rmtree(scratch)

        seconds["total"] = time.perf_counter() - t_start
        report = {
            "photos": str(photos), "out": str(out), "images": len(names),
            "features": {"total": int(sum(counts)), **_stats(counts)},
            "unreadable": unreadable,
            "pairs": {"candidates": int(candidates), "verified": len(verified), "inlier_matches": int(sum(verified))},
            "registered": int(registered),
            "unregistered": unregistered,
            "points": int(best.num_points3D()),
            "mean_reprojection_error": float(best.compute_mean_reprojection_error()),
            "mean_track_length": float(best.compute_mean_track_length()),
            "models": len(models), "other_models": other,
            "cameras": [{"model": c.model_name, "width": int(c.width), "height": int(c.height),
                         "params": [float(p) for p in c.params]} for _, c in sorted(best.cameras.items())],
            "warnings": warnings,
            "seconds": {k: round(v, 3) for k, v in seconds.items()},
            "settings": settings,
        }
        atomic_write_json(tmp / "sfm.json", report)
    say(f"  wrote {out} (images/, sparse/0/, database.db, sfm.json) in {time.perf_counter() - t_start:.1f} s")
    return report


MAX_ASPECT_MISMATCH = 0.05
"""Largest relative difference of a camera's ``fx`` and ``fy`` that :func:`camera_warnings` lets pass."""


def camera_warnings(reconstruction) -> list[str]:
    """Signs that a pycolmap reconstruction's intrinsics are wrong: a camera with separate focal
    lengths (``PINHOLE``, ``OPENCV``, ...) whose ``fx`` and ``fy`` differ by more than
    :data:`MAX_ASPECT_MISMATCH` (photos have square pixels). Such a model can register every photo
    with small reprojection errors and still be far off: on the test's 320 px renders ``PINHOLE``
    converged to ``fx`` 214, ``fy`` 160 px (true: 445) with every pose wrong."""
    out = []
    for camera_id, camera in sorted(reconstruction.cameras.items()):
        fx, fy = float(camera.focal_length_x), float(camera.focal_length_y)
        if abs(fx - fy) > MAX_ASPECT_MISMATCH * max(fx, fy):
            out.append(f"camera {camera_id} ({camera.model_name}): focal lengths fx {fx:.1f} and fy {fy:.1f} px differ "
                       f"by {100 * abs(fx - fy) / max(fx, fy):.0f}%; photos have square pixels, so the intrinsics "
                       "and poses are likely wrong: try camera_model='SIMPLE_RADIAL'")
    return out


@dataclasses.dataclass(frozen=True)
class Similarity:
    """``x -> scale * R @ x + t``: ``scale`` > 0, ``R`` ``[3, 3]`` a rotation, ``t`` ``[3]``."""

    scale: float
    R: np.ndarray
    t: np.ndarray

    def __iter__(self):  # (scale, R, t) = similarity_align(...)
        return iter((self.scale, self.R, self.t))

    def apply(self, x: np.ndarray) -> np.ndarray:
        """The points ``x`` ``[..., 3]`` mapped."""
        return self.scale * np.asarray(x, np.float64) @ self.R.T + self.t


def similarity_align(src: np.ndarray, dst: np.ndarray) -> Similarity:
    """The similarity ``(scale, R, t)`` taking points ``src`` ``[n, 3]`` closest to ``dst`` ``[n, 3]`` in
    least squares (Umeyama 1991; ``n >= 3`` points not all on a line), e.g. recovered camera centres
    to known ones. A proper rotation (``det R = +1``), never a reflection."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ValueError(f"similarity_align: expected two [n, 3] arrays with n >= 3, found {src.shape} and {dst.shape}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    var = float((xs**2).sum()) / len(src)
    if not var > 0:
        raise ValueError("similarity_align: the source points all coincide")
    u, d, vt = np.linalg.svd(xd.T @ xs / len(src))
    sign = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        sign[2] = -1.0
    R = (u * sign) @ vt
    scale = float((d * sign).sum()) / var
    return Similarity(scale, R, mu_d - scale * R @ mu_s)


def rotation_angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The angle in degrees ``[...]`` of the rotation between rotations ``a`` and ``b`` ``[..., 3, 3]``."""
    cos = (np.einsum("...ij,...ij->...", np.asarray(a, np.float64), np.asarray(b, np.float64)) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


__all__ = ["CAMERA_MODELS", "DataError", "IMAGE_SUFFIXES", "MATCHERS", "MAX_ASPECT_MISMATCH", "MIN_IMAGES",
           "Similarity", "camera_warnings", "list_photos", "process_images", "rotation_angle_deg", "similarity_align"]

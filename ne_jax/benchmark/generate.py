"""Writing the procedural editing benchmark to disk, in the NeRF Synthetic layout.

Layout of ``<root>`` for one preset::

    <root>/<scene>/transforms_{train,val,test}.json, {train,val,test}/r_<i>.png
    <root>/<scene>/points.ply          surface samples: x y z nx ny nz red green blue material
    <root>/<scene>/scene.json          what was made, how, and the edits' descriptions
    <root>/<scene>/edits/<edit>/       the edited scene as ground truth: transforms_{train,test}.json,
                                       images from the *same* cameras, points.ply with an ``index``
                                       property (the original sample each edited point came from);
                                       a whole-scene turn's scene.json adds ``rigid`` (its 4x4 motion)
                                       and ``moves_environment``

Everything is deterministic for a seed (same seed, same bytes; a path-traced preset's scene.json adds
its generation time, the one field that differs), and each scene directory appears only when
complete (written to a temporary sibling, then renamed). A long generation can be resumed
(``resume=True``): finished scenes are kept and each image is saved as it is rendered, under
``<root>/.<scene>.partial/``, until its scene is complete.

The ground truth is rendered by the preset's ``renderer`` (:data:`RENDERERS`): the ray caster
(``tiny``, ``default``) or Mitsuba 3's path tracer (``tiny_pt``, ``default_pt``; needs ``mitsuba``).
The capture presets (``tiny_capture``, ``default_capture``) write another layout: a COLMAP model
and a nerfstudio copy of each scene, opaque images with the environment and a ground
(:mod:`ne_jax.benchmark.capture`).
"""

from __future__ import annotations

import dataclasses
import io
import json
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from ne_jax.atomic import atomic_directory, atomic_write_bytes, atomic_write_json
from ne_jax.benchmark import raycaster
from ne_jax.benchmark import scenes as S
from ne_jax.data import cameras
from ne_jax.data.nerf_synthetic import load_split, write_split
from ne_jax.data.ply import read_ply, write_ply

RENDERERS = {
    "raycast": "the Open3D ray caster (ne_jax.benchmark.raycaster): Blinn-Phong, noise-free",
    "pathtrace": "Mitsuba 3's path tracer (ne_jax.benchmark.pathtracer): environment map, PBR materials, noisy",
}
"""The ground-truth renderers a preset can name, with what they are."""


@dataclass(frozen=True)
class BenchmarkPreset:
    """Sizes of one benchmark preset."""

    name: str
    resolution: int
    """Image width and height in pixels."""
    train_views: int
    val_views: int
    test_views: int
    """Test views lie on an orbit at 25 degrees elevation; train/val views are random."""
    supersample: int
    """``ss``: each pixel averages an ``ss x ss`` grid of ray samples (anti-aliasing, alpha); the ray
    caster's only (the path tracer spreads its ``spp`` samples over each pixel)."""
    detail: float
    """Mesh resolution factor (1.0: ~0.05 edge length, 96 segments around)."""
    surface_samples: int
    """Points in each ``points.ply``."""
    renderer: str = "raycast"
    """The ground-truth renderer, a key of :data:`RENDERERS`."""
    spp: int = 0
    """Samples per pixel of the path tracer (``renderer="pathtrace"``; unused by the ray caster)."""
    matte: bool = False
    """Every surface without highlights and reflections (a variant that needs no view-dependent colour)."""
    alpha: bool = True
    """False: images composited on white and saved without alpha (a variant that needs a background model)."""
    capture: bool = False
    """The capture variant (:mod:`ne_jax.benchmark.capture`): the path tracer with the environment
    visible and a ground, written as a COLMAP model and a nerfstudio copy; no validation split, and
    ``train_views`` such that every 8th image held out gives the ``test_views``."""
    edit_train_views: int | None = None
    """A capture preset's training views of each edit's ground truth: the first ones of the
    capture's (``None``: all of them)."""

    def __post_init__(self):
        if self.renderer not in RENDERERS:
            raise ValueError(f"BenchmarkPreset.renderer: unknown renderer {self.renderer!r}; expected one of "
                             f"{sorted(RENDERERS)}")
        if self.renderer == "pathtrace" and self.spp < 1:
            raise ValueError(f"BenchmarkPreset.spp: the path tracer needs a positive sample count, found {self.spp}")
        if self.capture:
            if self.renderer != "pathtrace" or self.val_views or self.alpha:
                raise ValueError("BenchmarkPreset.capture: expected the path tracer, no validation views and "
                                 f"alpha=False, found {self.renderer!r}, {self.val_views} and {self.alpha}")
            from ne_jax.benchmark.capture import view_order

            view_order(self.train_views, self.test_views)  # raises unless every 8th image is a test view
        if self.edit_train_views is not None and not (self.capture and 0 < self.edit_train_views <= self.train_views):
            raise ValueError(f"BenchmarkPreset.edit_train_views: expected a capture preset and 1..{self.train_views} "
                             f"views, found {self.edit_train_views} (capture={self.capture})")

    def record(self) -> dict:
        """The preset as scene.json and timings.json record it (a ray-cast preset without the path
        tracer's fields, so its files keep their bytes)."""
        out = asdict(self)
        if self.renderer == "raycast":
            del out["renderer"], out["spp"]
        for name, default in (("matte", False), ("alpha", True), ("capture", False), ("edit_train_views", None)):
            if out[name] == default:
                del out[name]
        return out

    def effects(self, scene: S.Scene) -> dict:
        """The effects a model of ``scene`` rendered by this preset needs (``scene.json``'s
        ``effects``, :mod:`ne_jax.train.effects`): view-dependent colour where a surface has a
        highlight or a reflection, a learned background where the images have no alpha."""
        if self.renderer == "raycast":
            shiny = any(m.ks > 0 or m.reflect > 0 for m in scene.materials)
        else:
            from ne_jax.benchmark import pathtracer

            shiny = any(s.kind != "diffuse" for s in pathtracer.scene_surfaces(scene.name, scene.materials))
        return {"specular": bool(shiny and not self.matte), "background_model": "constant" if self.alpha else "sphere"}


PRESETS = {
    "tiny": BenchmarkPreset("tiny", 64, 24, 4, 8, 2, 0.75, 20_000),
    "default": BenchmarkPreset("default", 200, 100, 10, 20, 3, 1.0, 200_000),
    # The path-traced variants: the same scenes, views and edits, rendered by Mitsuba 3 at 256 spp
    # (seed-to-seed PSNR >= 40 dB on every scene, docs/decisions.md, "The path tracer's noise floor").
    "tiny_pt": BenchmarkPreset("tiny_pt", 64, 24, 4, 8, 1, 0.75, 20_000, renderer="pathtrace", spp=256),
    "default_pt": BenchmarkPreset("default_pt", 200, 100, 10, 20, 1, 1.0, 200_000, renderer="pathtrace", spp=256),
    # The capture variants: the path-traced scenes and edits with the environment visible and a ground,
    # as a COLMAP model and a nerfstudio copy (ne_jax.benchmark.capture). The test views are the *_pt
    # presets'; 7 training views per test view, so that every 8th image held out is a test view. The
    # edits' ground truth has the *_pt presets' training views (the first of the capture's).
    "tiny_capture": BenchmarkPreset("tiny_capture", 64, 56, 0, 8, 1, 0.75, 20_000, renderer="pathtrace", spp=256,
                                    alpha=False, capture=True, edit_train_views=24),
    "default_capture": BenchmarkPreset("default_capture", 200, 140, 0, 20, 1, 1.0, 200_000, renderer="pathtrace",
                                       spp=256, alpha=False, capture=True, edit_train_views=100),
}


def get_preset(name: str) -> BenchmarkPreset:
    if name not in PRESETS:
        raise KeyError(f"unknown benchmark preset {name!r}; expected one of {sorted(PRESETS)}")
    return PRESETS[name]


def _rng(seed: int, scene_name: str, stream: str) -> np.random.Generator:
    """Independent, reproducible random streams per (seed, scene, purpose)."""
    key = [seed] + list(scene_name.encode()) + [0] + list(stream.encode())
    return np.random.default_rng(key)


def _render_split(render, c2ws: np.ndarray, seeds: np.ndarray, resolution: int, desc: str,
                  cache: Path | None = None) -> tuple[np.ndarray, float]:
    """``([n, H, W, 4] images render(c2ws[i], seeds[i]) of every camera, seconds spent rendering)``.

    With ``cache`` (a folder), each image is saved there as soon as it is rendered (``r_<i>.npz``: the
    float image and its render seconds, written atomically) and read back instead of rendered again,
    so an interrupted generation continues where it stopped, with the same bytes; the seconds then
    include those of the cached images."""
    images = np.empty((len(c2ws), resolution, resolution, 4), np.float32)
    seconds = 0.0
    for i in tqdm(range(len(c2ws)), desc=desc, leave=False, unit="img"):
        path = None if cache is None else cache / f"r_{i}.npz"
        if path is not None and path.is_file():
            with np.load(path) as done:
                images[i], seconds = done["image"], seconds + float(done["seconds"])
            continue
        t0 = time.perf_counter()
        images[i] = render(c2ws[i], int(seeds[i]))
        took = time.perf_counter() - t0
        seconds += took
        if path is not None:
            buffer = io.BytesIO()
            np.savez(buffer, image=images[i], seconds=np.float64(took))
            atomic_write_bytes(path, buffer.getvalue())
    return images, seconds


def _renderer(scene: S.Scene, edit, preset: BenchmarkPreset):
    """``(render(c2w, seed) -> [H, W, 4], description)``: the ground truth of ``edit`` (or the
    original) in ``preset``'s renderer (the ray caster ignores the seed)."""
    mesh, res, angle = S.truth_mesh(scene.mesh, edit), preset.resolution, cameras.CAMERA_ANGLE_X
    if preset.renderer == "raycast":
        caster = raycaster.RayCaster(mesh, scene.materials)
        description = "open3d RaycastingScene, two-sided Blinn-Phong, 2 shadowed directional lights, sky reflection"
        return (lambda c2w, seed: caster.render(c2w, res, res, angle, preset.supersample)), description
    from ne_jax.benchmark import pathtracer  # imports Mitsuba: only for a path-traced preset

    surfaces = (tuple(pathtracer.Surface("diffuse") for _ in scene.materials) if preset.matte
                else pathtracer.scene_surfaces(scene.name, scene.materials))
    tracer = pathtracer.PathTracer(mesh, scene.materials, surfaces,
                                   max_edge=pathtracer.pixel_footprint(res, angle), spp=preset.spp)
    description = (f"mitsuba {tracer.mi.__version__} {pathtracer.VARIANT} path tracer, {preset.spp} spp, "
                   f"max depth {pathtracer.MAX_DEPTH}, procedural environment map (sky and sun spots), "
                   "diffuse/plastic/conductor materials")
    return (lambda c2w, seed: tracer.render(c2w, res, res, angle, seed=seed)), description


def _write_points(path: Path, samples: dict[str, np.ndarray]) -> None:
    props = {f"{a}": samples["xyz"][:, i].astype(np.float32) for i, a in enumerate("xyz")}
    props.update({f"n{a}": samples["normal"][:, i].astype(np.float32) for i, a in enumerate("xyz")})
    rgb = np.round(np.clip(samples["color"], 0, 1) * 255).astype(np.uint8)
    props.update(red=rgb[:, 0], green=rgb[:, 1], blue=rgb[:, 2], material=samples["material"].astype(np.uint8))
    if "index" in samples:
        props["index"] = samples["index"].astype(np.int32)
    write_ply(path, props)


def _kept(scene_dir: Path, preset: BenchmarkPreset, seed: int, edits: list[str]) -> dict[str, float] | None:
    """The timings a finished scene in ``scene_dir`` recorded (its variants' generation seconds, where
    the renderer records them) if it was made with ``preset``, ``seed`` and exactly ``edits``; else None."""
    meta_path = scene_dir / "scene.json"
    if not meta_path.is_file():
        return None
    meta = json.loads(meta_path.read_text())
    if meta.get("preset") != preset.record() or meta.get("seed") != seed or list(meta.get("edits", {})) != edits:
        return None
    timings = {}
    for name, directory in [("original", scene_dir)] + [(e, scene_dir / "edits" / e) for e in edits]:
        generation = json.loads((directory / "scene.json").read_text()).get("generation")
        if generation is not None:
            timings[name] = float(generation["seconds"])
    timings["total"] = sum(timings.values())
    return timings


def generate_scene(scene_name: str, preset: BenchmarkPreset, root: Path, seed: int = 0, edits=None,
                   resume: bool = False) -> dict[str, float]:
    """Render one scene and its edits into ``root/<scene_name>``; returns timings in seconds.

    ``edits``: the names of the edits to make (``()``: only the original; default: all of the scene's);
    ``scene.json`` lists the ones made. With ``resume``, a finished scene already there with the same
    preset, seed and edits is kept (returning the timings it recorded), and every image is also saved
    under ``root/.<scene_name>.partial/`` as soon as it is rendered, so a generation stopped part way
    continues from its last image with the same bytes; that folder goes when the scene is complete.
    A capture preset (``preset.capture``) writes the capture layouts instead
    (:func:`ne_jax.benchmark.capture.generate_scene`)."""
    if preset.capture:
        from ne_jax.benchmark import capture

        return capture.generate_scene(scene_name, preset, root, seed, edits, resume)
    t0 = time.perf_counter()
    scene = S.get_scene(scene_name, preset.detail)
    names = list(scene.edits) if edits is None else list(edits)
    unknown = [e for e in names if e not in scene.edits]
    if unknown:
        raise KeyError(f"scene {scene_name!r} has no edit {unknown[0]!r}; expected some of {list(scene.edits)}")
    if resume and (kept := _kept(Path(root) / scene_name, preset, seed, names)) is not None:
        return kept
    partial = None
    if resume:
        partial = Path(root) / f".{scene_name}.partial"
        key = {"scene": scene_name, "preset": preset.record(), "seed": seed}
        if (partial / "key.json").is_file() and json.loads((partial / "key.json").read_text()) != key:
            shutil.rmtree(partial)  # images of another preset or seed
        atomic_write_json(partial / "key.json", key)
    if preset.matte:
        scene = dataclasses.replace(scene, materials=tuple(dataclasses.replace(m, ks=0.0, reflect=0.0)
                                                           for m in scene.materials))
    cams = {
        "train": cameras.random_cameras(preset.train_views, _rng(seed, scene_name, "train")),
        "val": cameras.random_cameras(preset.val_views, _rng(seed, scene_name, "val")),
        "test": cameras.orbit_cameras(preset.test_views),
    }
    samples = S.surface_samples(scene, preset.surface_samples, seed)
    timings = {"build": time.perf_counter() - t0}
    earlier = 0.0  # seconds of the images rendered in earlier sittings (resume)
    variants = [(None, None)] + [(n, scene.edits[n]) for n in names]
    with atomic_directory(Path(root) / scene_name) as out:
        for edit_name, edit in variants:
            t1 = time.perf_counter()
            target = out if edit is None else out / "edits" / edit_name
            target.mkdir(parents=True, exist_ok=True)
            render, description = _renderer(scene, edit, preset)
            splits = ("train", "val", "test") if edit is None else ("train", "test")
            images, cached_seconds = 0, 0.0
            for split in splits:
                # one renderer seed per image (the path tracer's noise), independent across variants and splits
                seeds = _rng(seed, scene_name, f"render/{edit_name or 'original'}/{split}").integers(
                    0, 2**31, len(cams[split]))
                t2 = time.perf_counter()
                rendered, seconds = _render_split(
                    render, S.truth_cameras(edit, cams[split]), seeds, preset.resolution,
                    f"{scene_name}/{edit_name or 'original'}/{split}",
                    None if partial is None else partial / (edit_name or "original") / split)
                cached_seconds += max(0.0, seconds - (time.perf_counter() - t2))  # earlier sittings' images
                if not preset.alpha:  # on white, opaque
                    a = rendered[..., 3:]
                    rendered = np.concatenate([rendered[..., :3] * a + (1.0 - a), np.ones_like(a)], axis=-1)
                write_split(target, split, rendered, cams[split], cameras.CAMERA_ANGLE_X)
                images += len(rendered)
            _write_points(target / "points.ply", samples if edit is None else S.edit_samples(samples, edit))
            meta = {
                "scene": scene_name,
                "difficulty": scene.difficulty,
                "edit": edit_name,
                "edit_description": None if edit is None else edit.description,
                "preset": preset.record(),
                "seed": seed,
                "near": cameras.NEAR,
                "far": cameras.FAR,
                "renderer": description,
                "effects": preset.effects(scene),
            }
            seconds = time.perf_counter() - t1 + cached_seconds
            earlier += cached_seconds
            if preset.renderer != "raycast":  # the one field that is not the same bytes for a seed
                meta["generation"] = {"images": images, "seconds": round(seconds, 2)}
            if edit is not None and edit.rigid is not None:
                meta["rigid"] = [list(row) for row in edit.rigid]
                meta["moves_environment"] = edit.moves_environment
            if edit is None:
                meta["edits"] = {n: {"kind": e.kind, "description": e.description} for n, e in variants[1:]}
            atomic_write_json(target / "scene.json", meta)
            timings[edit_name or "original"] = seconds
    if partial is not None:
        shutil.rmtree(partial, ignore_errors=True)
    timings["total"] = time.perf_counter() - t0 + earlier
    return timings


def generate_benchmark(root, preset: str | BenchmarkPreset = "tiny", scenes=None, seed: int = 0, edits=None,
                       resume: bool = False) -> dict:
    """Generate ``scenes`` (names of scenes or of sets of them, :func:`ne_jax.benchmark.scenes.scene_names`;
    default: the four tuning scenes) of ``preset`` under ``root``, each with ``edits`` (default: all;
    ``()``: only the originals; see :func:`generate_scene`, also for ``resume``); returns and saves
    timings (``root/timings.json``)."""
    preset = get_preset(preset) if isinstance(preset, str) else preset
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    names = S.scene_names(scenes)
    t0 = time.perf_counter()
    per_scene = {}
    for name in tqdm(names, desc=f"benchmark[{preset.name}]", unit="scene"):
        per_scene[name] = generate_scene(name, preset, root, seed, edits, resume)
    seconds = time.perf_counter() - t0
    if resume:  # the scenes' own records, earlier sittings included
        seconds = sum(t["total"] for t in per_scene.values())
    report = {"preset": preset.record(), "seed": seed, "seconds": seconds, "scenes": per_scene}
    atomic_write_json(root / "timings.json", report)
    return report


def list_variants(root) -> list[tuple[str, str | None, Path]]:
    """``(scene, edit or None, directory)`` for every scene and edit found under ``root``, each
    directory in the NeRF Synthetic layout: a capture scene's original is its ``unedited/`` folder,
    and its nerfstudio copy (``<scene>_ns``) is not listed again."""
    out = []
    for scene_dir in sorted(p for p in Path(root).iterdir() if (p / "scene.json").is_file()):
        meta = json.loads((scene_dir / "scene.json").read_text())
        if "copy_of" in meta:
            continue
        out.append((scene_dir.name, None, scene_dir / "unedited" if meta.get("layout") == "colmap" else scene_dir))
        for edit in meta.get("edits", {}):
            out.append((scene_dir.name, edit, scene_dir / "edits" / edit))
    return out


def seen_surface_samples(scene_dir, split: str = "train", tolerance: float = 1e-3) -> np.ndarray:
    """Which ground-truth surface samples (``scene_dir/points.ply``) a camera of ``split`` sees: inside
    its image and the first surface along the ray from the camera (within ``tolerance`` world units).

    Returns ``[G]`` bool. A surface no camera sees (an underside, a hidden contact) cannot be
    reconstructed from the images, so a cloud's completeness is fairer measured on the seen samples.
    Works for a scene or one of its edits (the mesh is rebuilt from ``scene.json``)."""
    scene_dir = Path(scene_dir)
    meta_path = scene_dir / "scene.json"
    if not meta_path.is_file():
        raise FileNotFoundError(f"{meta_path}: expected the scene.json of a benchmark scene (made by "
                                "ne_jax.benchmark.generate); not found")
    meta = json.loads(meta_path.read_text())
    scene = S.get_scene(meta["scene"], meta["preset"]["detail"])
    edit = None if meta.get("edit") is None else scene.edits[meta["edit"]]
    caster = raycaster.RayCaster(S.apply_to_mesh(scene.mesh, edit), scene.materials)
    xyz = np.stack([np.asarray(read_ply(scene_dir / "points.ply")[a], np.float64) for a in "xyz"], axis=1)
    cams = load_split(scene_dir, split)
    half_x, half_y = cams.cx / cams.fx, cams.cy / cams.fy  # tangents of the half fields of view
    seen = np.zeros(len(xyz), bool)
    for c2w in np.asarray(cams.c2w, np.float64):
        todo = np.nonzero(~seen)[0]
        if len(todo) == 0:
            break
        v = xyz[todo] - c2w[:3, 3]
        local = v @ c2w[:3, :3]  # camera axes (OpenGL: looking down -z)
        depth = -local[:, 2]
        inside = (depth > 0) & (np.abs(local[:, 0]) <= half_x * depth) & (np.abs(local[:, 1]) <= half_y * depth)
        todo, v = todo[inside], v[inside]
        dist = np.linalg.norm(v, axis=1)
        t_hit = caster.hit_distance(np.broadcast_to(c2w[:3, 3], v.shape), v / dist[:, None])
        seen[todo[t_hit >= dist - tolerance]] = True
    return seen

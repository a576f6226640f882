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
complete (written to a temporary sibling, then renamed).

The ground truth is rendered by the preset's ``renderer`` (:data:`RENDERERS`): the ray caster
(``tiny``, ``default``) or Mitsuba 3's path tracer (``tiny_pt``, ``default_pt``; needs ``mitsuba``).
"""

from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from ne_jax.atomic import atomic_directory, atomic_write_json
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

    def __post_init__(self):
        if self.renderer not in RENDERERS:
            raise ValueError(f"BenchmarkPreset.renderer: unknown renderer {self.renderer!r}; expected one of "
                             f"{sorted(RENDERERS)}")
        if self.renderer == "pathtrace" and self.spp < 1:
            raise ValueError(f"BenchmarkPreset.spp: the path tracer needs a positive sample count, found {self.spp}")

    def record(self) -> dict:
        """The preset as scene.json and timings.json record it (a ray-cast preset without the path
        tracer's fields, so its files keep their bytes)."""
        out = asdict(self)
        if self.renderer == "raycast":
            del out["renderer"], out["spp"]
        for name, default in (("matte", False), ("alpha", True)):  # variants only
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
    # (seed-to-seed PSNR >= 40 dB on every scene, experiments/pathtraced_noise.py).
    "tiny_pt": BenchmarkPreset("tiny_pt", 64, 24, 4, 8, 1, 0.75, 20_000, renderer="pathtrace", spp=256),
    "default_pt": BenchmarkPreset("default_pt", 200, 100, 10, 20, 1, 1.0, 200_000, renderer="pathtrace", spp=256),
}


def get_preset(name: str) -> BenchmarkPreset:
    if name not in PRESETS:
        raise KeyError(f"unknown benchmark preset {name!r}; expected one of {sorted(PRESETS)}")
    return PRESETS[name]


def _rng(seed: int, scene_name: str, stream: str) -> np.random.Generator:
    """Independent, reproducible random streams per (seed, scene, purpose)."""
    key = [seed] + list(scene_name.encode()) + [0] + list(stream.encode())
    return np.random.default_rng(key)


def _render_split(render, c2ws: np.ndarray, seeds: np.ndarray, resolution: int, desc: str) -> np.ndarray:
    """``[n, H, W, 4]`` images ``render(c2ws[i], seeds[i])`` of every camera."""
    images = np.empty((len(c2ws), resolution, resolution, 4), np.float32)
    for i in tqdm(range(len(c2ws)), desc=desc, leave=False, unit="img"):
        images[i] = render(c2ws[i], int(seeds[i]))
    return images


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


def generate_scene(scene_name: str, preset: BenchmarkPreset, root: Path, seed: int = 0) -> dict[str, float]:
    """Render one scene and all its edits into ``root/<scene_name>``; returns timings in seconds."""
    t0 = time.perf_counter()
    scene = S.get_scene(scene_name, preset.detail)
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
    variants = [(None, None)] + list(scene.edits.items())
    with atomic_directory(Path(root) / scene_name) as out:
        for edit_name, edit in variants:
            t1 = time.perf_counter()
            target = out if edit is None else out / "edits" / edit_name
            target.mkdir(parents=True, exist_ok=True)
            render, description = _renderer(scene, edit, preset)
            splits = ("train", "val", "test") if edit is None else ("train", "test")
            images = 0
            for split in splits:
                # one renderer seed per image (the path tracer's noise), independent across variants and splits
                seeds = _rng(seed, scene_name, f"render/{edit_name or 'original'}/{split}").integers(
                    0, 2**31, len(cams[split]))
                rendered = _render_split(render, S.truth_cameras(edit, cams[split]), seeds, preset.resolution,
                                         f"{scene_name}/{edit_name or 'original'}/{split}")
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
            if preset.renderer != "raycast":  # the one field that is not the same bytes for a seed
                meta["generation"] = {"images": images, "seconds": round(time.perf_counter() - t1, 2)}
            if edit is not None and edit.rigid is not None:
                meta["rigid"] = [list(row) for row in edit.rigid]
                meta["moves_environment"] = edit.moves_environment
            if edit is None:
                meta["edits"] = {n: {"kind": e.kind, "description": e.description} for n, e in scene.edits.items()}
            atomic_write_json(target / "scene.json", meta)
            timings[edit_name or "original"] = time.perf_counter() - t1
    timings["total"] = time.perf_counter() - t0
    return timings


def generate_benchmark(root, preset: str | BenchmarkPreset = "tiny", scenes=None, seed: int = 0) -> dict:
    """Generate ``scenes`` (default: all) of ``preset`` under ``root``; returns and saves timings
    (``root/timings.json``)."""
    preset = get_preset(preset) if isinstance(preset, str) else preset
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    names = list(S.SCENES) if scenes is None else list(scenes)
    for n in names:
        if n not in S.SCENES:
            raise KeyError(f"unknown scene {n!r}; expected one of {sorted(S.SCENES)}")
    t0 = time.perf_counter()
    per_scene = {}
    for name in tqdm(names, desc=f"benchmark[{preset.name}]", unit="scene"):
        per_scene[name] = generate_scene(name, preset, root, seed)
    report = {"preset": preset.record(), "seed": seed, "seconds": time.perf_counter() - t0, "scenes": per_scene}
    atomic_write_json(root / "timings.json", report)
    return report


def list_variants(root) -> list[tuple[str, str | None, Path]]:
    """``(scene, edit or None, directory)`` for every scene and edit found under ``root``."""
    out = []
    for scene_dir in sorted(p for p in Path(root).iterdir() if (p / "scene.json").is_file()):
        meta = json.loads((scene_dir / "scene.json").read_text())
        out.append((scene_dir.name, None, scene_dir))
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

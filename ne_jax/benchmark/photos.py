"""Photos with known cameras, to try structure from motion on (``ne-jax make-photos``, and the
test of ``ne-jax process-images``): the benchmark's ``blocks`` scene, path-traced
(:mod:`ne_jax.benchmark.pathtracer`), standing on a textured ground plate.

The benchmark scenes alone give SIFT too little to match: the checker of ``blocks`` repeats (its
corners all look alike, so the ratio test drops them), the drum's stripes and the ball's paint are
smooth, and the background is empty. At 192 px and 24 views 30 degrees apart no initial pair
verifies. A real capture has a table or a floor in view; here it is a square plate of value noise
(three octaves, one colour channel each) under the scene, which SIFT matches well. The plate's mesh
is a grid fine enough that the path tracer does not split it (its texture is resolved by its own
vertices), so it costs no build time beyond its triangles.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ne_jax.data import cameras as C
from ne_jax.data.png import write_image

GROUND_HALF = 2.2
"""Half the side of the ground plate (world units, centred under the origin)."""
GROUND_Z = -0.86
"""Height of the plate: 1 cm under the block's bottom (z = -0.85)."""
ELEVATIONS = (20.0, 45.0)
"""Elevations (degrees) of the two rings of cameras; the second ring is offset by half a step."""
BACKGROUND = 0.5
"""Grey the renders are composited on (the path tracer's background is transparent)."""


def _value_noise(xy: np.ndarray, per_unit: float, rng: np.random.Generator) -> np.ndarray:
    """Smooth value noise ``[n]`` in ``[0, 1]`` at ``xy`` ``[n, 2]`` inside the plate, on a lattice of
    ``per_unit`` cells a world unit."""
    cells = math.ceil(2 * GROUND_HALF * per_unit)
    lattice = rng.random((cells + 2, cells + 2))
    g = (xy + GROUND_HALF) / (2 * GROUND_HALF) * cells
    i = np.clip(np.floor(g).astype(np.int64), 0, cells)
    f = g - i
    f = f * f * (3 - 2 * f)
    fx, fy = f[:, 0], f[:, 1]
    ix, iy = i[:, 0], i[:, 1]
    bottom = lattice[ix, iy] * (1 - fx) + lattice[ix + 1, iy] * fx
    top = lattice[ix, iy + 1] * (1 - fx) + lattice[ix + 1, iy + 1] * fx
    return bottom * (1 - fy) + top * fy


def ground_albedo(xy: np.ndarray, seed: int = 0) -> np.ndarray:
    """sRGB albedo ``[n, 3]`` of the plate at ``xy`` ``[n, 2]``: per channel, three octaves of value
    noise (4, 9 and 20 cells a unit: about 28, 12 and 6 pixels a cell at 320 px), contrast-stretched."""
    rng = np.random.default_rng(seed)
    rgb = np.stack([0.5 * _value_noise(xy, 4, rng) + 0.3 * _value_noise(xy, 9, rng) + 0.2 * _value_noise(xy, 20, rng)
                    for _ in range(3)], axis=1)
    return np.clip(0.5 + 1.2 * (rgb - 0.5), 0.0, 1.0)


def ground_mesh(max_edge: float) -> tuple[np.ndarray, np.ndarray]:
    """``(vertices [V, 3], faces [F, 3])`` of the plate: a grid whose triangles' longest edges (the
    cell diagonals) are at most ``max_edge``, facing up."""
    n = math.ceil(2 * GROUND_HALF * math.sqrt(2) / max_edge)
    u = np.linspace(-GROUND_HALF, GROUND_HALF, n + 1)
    x, y = np.meshgrid(u, u, indexing="ij")
    vertices = np.stack([x.ravel(), y.ravel(), np.full(x.size, GROUND_Z)], axis=1)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return vertices, faces


def ring_cameras(per_ring: int, radius: float = C.CAMERA_RADIUS) -> np.ndarray:
    """``[2 * per_ring, 4, 4]`` OpenGL camera-to-world matrices on two rings (:data:`ELEVATIONS`)
    ``radius`` from the origin, looking at it, neighbours ``360 / per_ring`` degrees apart."""
    eyes = []
    for ring, elevation in enumerate(ELEVATIONS):
        el = math.radians(elevation)
        for k in range(per_ring):
            az = 2 * math.pi * (k + 0.5 * ring) / per_ring
            eyes.append(radius * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)]))
    return np.stack([C.look_at(e) for e in eyes])


def render_photos(folder: Path, resolution: int = 256, spp: int = 16, per_ring: int = 12,
                  detail: float = 0.5) -> tuple[list[str], np.ndarray]:
    """Render the views of :func:`ring_cameras` into ``folder`` as opaque 8-bit PNGs
    ``view_<i>.png``; returns ``(names, c2w [n, 4, 4])`` (OpenGL, the benchmark's world)."""
    from ne_jax.benchmark import meshes as M
    from ne_jax.benchmark import pathtracer as P
    from ne_jax.benchmark import scenes as S

    scene = S.get_scene("blocks", detail)
    max_edge = P.pixel_footprint(resolution, C.CAMERA_ANGLE_X)
    vertices, faces = ground_mesh(max_edge)
    ground = M.TriMesh(vertices, faces, np.zeros(len(faces), np.int32)).with_material(len(scene.materials))
    mesh = M.concatenate([scene.mesh, ground])
    materials = (*scene.materials, S.Material(lambda p: ground_albedo(p[:, :2])))
    surfaces = (*P.scene_surfaces(scene.name, scene.materials), P.Surface("diffuse"))
    tracer = P.PathTracer(S.truth_mesh(mesh, None), materials, surfaces, max_edge=max_edge, spp=spp)
    c2ws = ring_cameras(per_ring)
    folder.mkdir(parents=True, exist_ok=True)
    names = []
    for i, c2w in enumerate(c2ws):
        rgba = tracer.render(c2w, resolution, resolution, C.CAMERA_ANGLE_X, seed=i)
        alpha = rgba[..., 3:]
        names.append(f"view_{i:03d}.png")
        write_image(folder / names[-1], rgba[..., :3] * alpha + BACKGROUND * (1 - alpha))
    return names, c2ws


def write_photos(folder: Path, resolution: int = 320, spp: int = 16, per_ring: int = 12) -> dict:
    """:func:`render_photos` into ``folder`` plus ``folder/cameras.json`` with the true cameras
    (``{name: c2w}``, OpenGL, the benchmark's world) to compare a reconstruction with. Returns
    ``{"photos", "seconds"}``."""
    import json
    import time

    t0 = time.perf_counter()
    folder = Path(folder)
    names, c2ws = render_photos(folder / "photos_tmp", resolution, spp, per_ring)
    for name in names:
        (folder / "photos_tmp" / name).replace(folder / name)
    (folder / "photos_tmp").rmdir()
    (folder / "cameras.json").write_text(json.dumps({n: m.tolist() for n, m in zip(names, c2ws)}, indent=1) + "\n")
    return {"photos": len(names), "seconds": round(time.perf_counter() - t0, 1)}

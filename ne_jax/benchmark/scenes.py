"""The procedural benchmark's scenes and their edits.

The paper's benchmark (NeRF Synthetic scenes deformed in Blender) cannot be downloaded, so ne_jax
makes its own the same way: build a scene, render it from many views, apply each edit to the scene's
mesh, render the edited scene again as ground truth. The edits are functions of 3-D points
(:mod:`ne_jax.edit.deformations`), so exactly the same edit is later applied to a model's points.

The ground truth is rendered by :mod:`ne_jax.benchmark.raycaster` (noise-free and bit-for-bit
repeatable; highlights move with the view, which is the view-dependent colour the IST exists for).

Textures are functions of the *rest* (unedited) position, so a texture moves with the surface when
the scene is edited.

Every scene ends with two whole-scene turns (:func:`scene_turns`), 40 degrees about the unit axis
``normalize(1, 1, 2)`` through the origin (the cameras' target): ``turn_with_light`` moves the lights
and the sky with the scene, so its ground truth is exactly the original scene seen from the cameras
``T^-1 @ c2w`` (:func:`truth_cameras`) and reflections and highlights stay attached to the surface —
the case the IST exists for; ``turn_scene`` keeps lights and sky fixed in the world and renders the
turned mesh, so highlights and reflections slide over the surface as in every other edit.

Scenes (all inside ``[-1, 1]^3``, z up, as in Blender):

========  ================================================================================
stool     thin structures: a seat on four thin legs joined by a thin ring
cup       concavities: a mug with a handle and a ball inside
blocks    textured diffuse surfaces: a checkered block, a striped drum, a painted ball
glossy    specular parts: a glossy sphere, a gold ring around it, a glossy cube on top
========  ================================================================================
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ne_jax.benchmark import meshes as M
from ne_jax.edit import deformations as D

# --------------------------------------------------------------------------------- materials


Texture = Callable[[np.ndarray], np.ndarray]
"""Albedo as a function of rest positions ``[n, 3]`` -> sRGB ``[n, 3]`` in ``[0, 1]``."""


def solid(rgb) -> Texture:
    return lambda p: np.broadcast_to(np.asarray(rgb, np.float64), p.shape).copy()


def checker(rgb_a, rgb_b, cells_per_unit: float) -> Texture:
    def tex(p):
        parity = np.sum(np.floor(p * cells_per_unit + 1e-6), axis=1) % 2
        return np.where(parity[:, None] > 0, np.asarray(rgb_a, float), np.asarray(rgb_b, float))
    return tex


def stripes(rgb_a, rgb_b, axis: int, per_unit: float, angular: bool = False) -> Texture:
    """Stripes across ``axis`` (or around the z axis when ``angular``)."""
    def tex(p):
        coord = np.arctan2(p[:, 1], p[:, 0]) / (2 * np.pi) if angular else p[:, axis]
        t = 0.5 + 0.5 * np.sin(2 * np.pi * per_unit * coord)
        t = np.clip((t - 0.3) / 0.4, 0.0, 1.0)  # soft-edged bands
        return (1 - t)[:, None] * np.asarray(rgb_a, float) + t[:, None] * np.asarray(rgb_b, float)
    return tex


def wood(rgb_light, rgb_dark, rings_per_unit: float) -> Texture:
    def tex(p):
        r = np.hypot(p[:, 0], p[:, 1]) + 0.04 * np.sin(7 * p[:, 0]) * np.cos(5 * p[:, 1])
        t = 0.5 + 0.5 * np.sin(2 * np.pi * rings_per_unit * r)
        return (1 - t)[:, None] * np.asarray(rgb_light, float) + t[:, None] * np.asarray(rgb_dark, float)
    return tex


def painted(freq: float) -> Texture:
    """A smooth multi-coloured pattern (sums of sines), for a textured surface with no symmetry."""
    def tex(p):
        x, y, z = p[:, 0], p[:, 1], p[:, 2]
        r = 0.5 + 0.45 * np.sin(freq * (1.3 * x + 0.7 * z) + 0.5)
        g = 0.5 + 0.45 * np.sin(freq * (1.1 * y - 0.9 * z) + 2.0)
        b = 0.5 + 0.45 * np.sin(freq * (0.8 * x + 1.2 * y) + 4.0)
        return np.stack([r, g, b], axis=1)
    return tex


def by_radius(inner: Texture, outer: Texture, radius: float) -> Texture:
    """``inner`` closer than ``radius`` to the z axis, ``outer`` beyond."""
    def tex(p):
        return np.where((np.hypot(p[:, 0], p[:, 1]) < radius)[:, None], inner(p), outer(p))
    return tex


@dataclass(frozen=True)
class Material:
    """Blinn-Phong material: ``albedo`` texture, specular weight ``ks`` and exponent ``shininess``,
    and the weight of the mirror-reflected sky (``reflect``)."""

    albedo: Texture
    ks: float = 0.0
    shininess: float = 32.0
    reflect: float = 0.0


# ------------------------------------------------------------------------------------ scenes


@dataclass(frozen=True)
class Scene:
    """A benchmark scene: parts as one mesh (``mesh.material`` indexes ``materials``), its edits,
    and the difficulty it stands for."""

    name: str
    difficulty: str
    mesh: M.TriMesh
    materials: tuple[Material, ...]
    edits: dict[str, D.Edit] = field(default_factory=dict)


def _parts(parts: list[tuple[M.TriMesh, Material]]):
    meshes, materials = [], []
    for mesh, material in parts:
        meshes.append(mesh.with_material(len(materials)))
        materials.append(material)
    return M.concatenate(meshes), tuple(materials)


TURN_AXIS = (1.0, 1.0, 2.0)
"""Axis of the whole-scene turns (normalised by the edit)."""
TURN_DEGREES = 40.0
TURN_PIVOT = (0.0, 0.0, 0.0)
"""The turns' pivot: the point every camera looks at."""


def scene_turns() -> tuple[D.Edit, D.Edit]:
    """The two whole-scene turns every scene ends with (same names, same motion ``T`` in every
    scene): ``turn_with_light`` (lights and sky turn with the scene: ``moves_environment``) and
    ``turn_scene`` (lights and sky stay)."""
    return (D.rigid_scene("turn_with_light", TURN_AXIS, TURN_DEGREES, TURN_PIVOT, moves_environment=True),
            D.rigid_scene("turn_scene", TURN_AXIS, TURN_DEGREES, TURN_PIVOT))


def _edits(*edits: D.Edit) -> dict[str, D.Edit]:
    """The scene's edits by name: its own, then the whole-scene turns (:func:`scene_turns`)."""
    return {e.name: e for e in (*edits, *scene_turns())}


def make_stool(detail: float) -> Scene:
    """Thin structures: a round seat on four thin legs (pre-cut at z = -0.2) joined by a thin ring."""
    seg, h = int(96 * detail), 0.05 / detail
    cut_z, legs = -0.2, [(sx * 0.42, sy * 0.42) for sx in (-1, 1) for sy in (-1, 1)]
    seat = M.cylinder(0.65, 0.45, 0.57, seg, h)
    leg_meshes = M.concatenate([M.cylinder(0.045, -0.9, 0.45, max(12, seg // 6), h, cut_z, xy) for xy in legs])
    ring = M.torus(0.42 * math.sqrt(2), 0.022, seg, 12, center=(0, 0, -0.45))
    mesh, materials = _parts([
        (seat, Material(wood((0.78, 0.58, 0.36), (0.55, 0.36, 0.2), 9.0), ks=0.15, shininess=20)),
        (leg_meshes, Material(solid((0.25, 0.25, 0.28)), ks=0.5, shininess=40, reflect=0.1)),
        (ring, Material(solid((0.7, 0.15, 0.12)), ks=0.3, shininess=30)),
    ])
    edits = _edits(
        D.twist("twist", (0, 0, 0), (0, 0, 1), 60.0),
        D.rigid_part("tilt_seat", D.halfspace((0, 0, 1), 0.44), (1, 0, 0), 25.0, (0, 0, 0.45)),
        D.cut("cut", (0, 0, cut_z), (0, 0, 1), 0.3),
        D.delete_part("delete_leg", D.vertical_cylinder(legs[3], 0.1, z_hi=0.44)),
    )
    return Scene("stool", "thin structures", mesh, materials, edits)


def make_cup(detail: float) -> Scene:
    """Concavities: a mug (pre-cut at z = -0.2) with a handle, and a ball inside."""
    seg, h = int(96 * detail), 0.05 / detail
    cut_z, ro, ri, zb, zi, zt = -0.2, 0.55, 0.48, -0.6, -0.5, 0.6
    loop = [
        M.Piece(np.array([[0.0, zb], [ro, zb]])),
        M.Piece(np.array([[ro, zb], [ro, zt]])),
        M.Piece(np.array([[ro, zt], [ri, zt]])),
        M.Piece(np.array([[ri, zt], [ri, zi]])),
        M.Piece(np.array([[ri, zi], [0.0, zi]])),
        M.Piece(np.array([[0.0, zi], [0.0, zb]]), virtual=True),
    ]
    mug = M.lathe(loop, seg, h, cut_z)
    t = np.linspace(-np.pi / 2, np.pi / 2, int(32 * detail))
    handle_path = np.stack([0.553 + 0.24 * np.cos(t), np.zeros_like(t), 0.25 + 0.22 * np.sin(t)], axis=1)
    handle = M.tube(handle_path, 0.04, 16, closed=False)
    ball = M.sphere(0.13, seg // 2, h, center=(0.0, 0.0, -0.36))
    mug_tex = by_radius(solid((0.92, 0.9, 0.85)), stripes((0.15, 0.35, 0.7), (0.93, 0.92, 0.88), 2, 3.0), 0.515)
    mesh, materials = _parts([
        (mug, Material(mug_tex, ks=0.25, shininess=50)),
        (handle, Material(solid((0.15, 0.35, 0.7)), ks=0.25, shininess=50)),
        (ball, Material(solid((0.95, 0.6, 0.1)), ks=0.2, shininess=30)),
    ])
    # The handle without the 3 cm next to the wall (radius 0.55): a trained cloud's wall points spread
    # a few spacings off the surface, and a region that reached them would edit the mug's wall too.
    handle_region = D.intersection(D.beyond_radius(0.58), D.axis_box((0.5, -0.1, -0.04), (0.9, 0.1, 0.54)))
    edits = _edits(
        D.bend("bend", (0, 0, -0.6), (0, 0, 1), (1, 0, 0), 50.0, 1.2),
        D.rigid_part("turn_handle", handle_region, (0, 0, 1), 90.0, (0, 0, 0), part="the handle"),
        D.cut("cut", (0, 0, cut_z), (0, 0, 1), 0.35),
        D.delete_part("delete_handle", handle_region, part="the handle"),
    )
    return Scene("cup", "concavities", mesh, materials, edits)


def make_blocks(detail: float) -> Scene:
    """Textured diffuse surfaces: a checkered block (pre-cut at z = -0.35), a striped drum, a ball."""
    seg, h = int(96 * detail), 0.05 / detail
    cut_z, ball_c, ball_r = -0.35, (0.0, 0.0, 0.755), 0.3  # ball floats 5 mm above the drum
    block = M.box((-0.55, -0.55, -0.85), (0.55, 0.55, 0.1), h, cut_z)
    drum = M.cylinder(0.35, 0.1, 0.45, seg, h)
    ball = M.sphere(ball_r, seg, h, center=ball_c)
    mesh, materials = _parts([
        (block, Material(checker((0.9, 0.85, 0.75), (0.2, 0.3, 0.45), 5.0))),
        (drum, Material(stripes((0.8, 0.2, 0.2), (0.95, 0.85, 0.3), 0, 4.0, angular=True))),
        (ball, Material(painted(9.0))),
    ])
    ball_region = D.intersection(D.ball(ball_c, ball_r + 0.01), D.halfspace((0, 0, 1), 0.452))
    edits = _edits(
        D.twist("twist", (0, 0, 0), (0, 0, 1), 70.0),
        D.rigid_part("roll_ball", ball_region, (1, 0, 0), 90.0, ball_c),
        D.cut("cut", (0, 0, cut_z), (0, 0, 1), 0.3),
        D.delete_part("delete_ball", ball_region),
    )
    return Scene("blocks", "textured diffuse surfaces", mesh, materials, edits)


def make_glossy(detail: float) -> Scene:
    """Specular parts: a glossy sphere (pre-cut at z = 0.3), a gold ring around it, a cube on top."""
    seg, h = int(96 * detail), 0.05 / detail
    cut_z = 0.3
    body = M.sphere(0.55, seg, h, cut_z)
    ring = M.torus(0.85, 0.11, seg, 24)
    cube = M.box((-0.15, -0.15, 0.551), (0.15, 0.15, 0.85), h)
    mesh, materials = _parts([
        (body, Material(solid((0.75, 0.1, 0.1)), ks=0.8, shininess=80, reflect=0.25)),
        (ring, Material(solid((0.85, 0.65, 0.2)), ks=0.9, shininess=120, reflect=0.35)),
        (cube, Material(solid((0.15, 0.3, 0.8)), ks=0.7, shininess=60, reflect=0.2)),
    ])
    edits = _edits(
        D.bend("bend", (0, 0, -0.8), (0, 0, 1), (1, 0, 0), 60.0, 1.6),
        D.rigid_part("tilt_ring", D.beyond_radius(0.68), (1, 0, 0), 35.0, (0, 0, 0)),
        D.cut("cut", (0, 0, cut_z), (0, 0, 1), 0.35),
        D.delete_part("delete_cube", D.halfspace((0, 0, 1), 0.5505)),
    )
    return Scene("glossy", "specular parts", mesh, materials, edits)


SCENES: dict[str, Callable[[float], Scene]] = {
    "stool": make_stool,
    "cup": make_cup,
    "blocks": make_blocks,
    "glossy": make_glossy,
}


def get_scene(name: str, detail: float = 1.0) -> Scene:
    """The benchmark scene ``name`` with mesh resolution scaled by ``detail``."""
    if name not in SCENES:
        raise KeyError(f"unknown scene {name!r}; expected one of {sorted(SCENES)}")
    return SCENES[name](detail)


# ------------------------------------------------------------------------------------- edits


@dataclass(frozen=True)
class EditedMesh:
    """A mesh after an edit. ``vertices`` are edited positions, ``rest`` the original ones (for
    textures); ``faces`` keep only triangles with no deleted vertex."""

    vertices: np.ndarray
    rest: np.ndarray
    faces: np.ndarray
    material: np.ndarray


def apply_to_mesh(mesh: M.TriMesh, edit: D.Edit | None) -> EditedMesh:
    """Apply ``edit`` to the mesh vertices; drop every face touching a deleted vertex. (The geometry of
    the edited scene; its ground truth is rendered by :func:`truth_mesh` and :func:`truth_cameras`.)"""
    if edit is None:
        return EditedMesh(mesh.vertices, mesh.vertices, mesh.faces, mesh.material)
    moved, deleted = edit.apply(mesh.vertices)
    moved, deleted = np.asarray(moved, np.float64), np.asarray(deleted)
    keep = ~deleted[mesh.faces].any(axis=1)
    return EditedMesh(moved, mesh.vertices, mesh.faces[keep], mesh.material[keep])


def truth_mesh(mesh: M.TriMesh, edit: D.Edit | None) -> EditedMesh:
    """The mesh the ground truth of ``edit`` is rendered from: the original one for an edit that moves
    the environment with the scene (``edit.moves_environment``; the cameras move instead, see
    :func:`truth_cameras`), otherwise the edited one (:func:`apply_to_mesh`)."""
    return apply_to_mesh(mesh, None if edit is not None and edit.moves_environment else edit)


def truth_cameras(edit: D.Edit | None, c2ws: np.ndarray) -> np.ndarray:
    """The cameras ``[..., 4, 4]`` the ground truth of ``edit`` seen from ``c2ws`` is rendered from:
    ``T^-1 @ c2w`` for an edit whose lights and sky move with the scene by ``T``
    (``edit.moves_environment``, ``edit.matrix``), else ``c2ws`` unchanged. Exact: moving the scene,
    the lights and the environment by ``T`` and looking from ``c2w`` is looking at the original from
    ``T^-1 @ c2w``."""
    c2ws = np.asarray(c2ws, np.float64)
    if edit is None or not edit.moves_environment:
        return c2ws
    if edit.matrix is None:
        raise ValueError(f"edit {edit.name!r}: moves_environment needs a whole-scene rigid motion (edit.rigid), "
                         "found none")
    return np.linalg.inv(edit.matrix) @ c2ws


# ----------------------------------------------------------------------------- surface samples


def surface_samples(scene: Scene, count: int, seed: int) -> dict[str, np.ndarray]:
    """Area-uniform samples of the scene surface: ``xyz``/``normal`` ``[n, 3]``, sRGB ``color``
    ``[n, 3]`` and ``material`` ``[n]``. Deterministic for ``seed``."""
    rng = np.random.default_rng(seed)
    mesh = scene.mesh
    face, bary = M.sample_surface(mesh, count, rng)
    xyz = M.interpolate(mesh.vertices, mesh.faces, face, bary)
    normal, _ = M.face_normals(mesh.vertices, mesh.faces[face])
    mat = mesh.material[face]
    color = np.zeros_like(xyz)
    for i, m in enumerate(scene.materials):
        sel = mat == i
        color[sel] = m.albedo(xyz[sel])
    return {"xyz": xyz, "normal": normal, "color": np.clip(color, 0, 1), "material": mat}


def edit_samples(samples: dict[str, np.ndarray], edit: D.Edit) -> dict[str, np.ndarray]:
    """Apply ``edit`` to surface samples: surviving points moved, normals by the inverse-transpose
    Jacobian, and ``index`` ``[m]`` the original sample index of each survivor."""
    moved, deleted = edit.apply(samples["xyz"])
    keep = ~np.asarray(deleted)
    normal = np.asarray(D.transform_normals(edit, samples["xyz"][keep], samples["normal"][keep]))
    out = {k: v[keep] for k, v in samples.items()}
    out.update(xyz=np.asarray(moved, np.float64)[keep], normal=normal, index=np.nonzero(keep)[0].astype(np.int32))
    return out

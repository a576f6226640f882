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

These four are the tuning scenes (:data:`SCENES`, the default benchmark). :data:`HELDOUT_SCENES`
holds four more, never used to choose a setting (``vase``: a thin foot under a wide body; ``bowl``:
open containers, thin rims, dark insides; ``lamp``: a wide shade seen from below on a thin stem;
``pattern``: fine texture on curved and concave surfaces); :func:`scene_names` expands the set
names of :data:`SCENE_SETS` (``heldout``, ``tuning``).
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


# ---------------------------------------------------------------------------- held-out scenes
#
# Made once and never used to choose a setting: new shapes for what the tuning scenes above do not
# stress. Nothing below changes the tuning scenes (their geometry, materials and draws).


def polar_checker(rgb_a, rgb_b, sectors: int, per_unit: float, center_xy=(0.0, 0.0),
                  by_height: bool = False) -> Texture:
    """A checker of ``sectors`` around the vertical axis through ``center_xy`` and of bands ``1 / per_unit``
    wide along the distance to that axis (or along z when ``by_height``): a fine pattern that follows a
    surface of revolution (a dish, a column) instead of cutting it at odd angles as :func:`checker` does."""
    def tex(p):
        dx, dy = p[:, 0] - center_xy[0], p[:, 1] - center_xy[1]
        sector = np.floor((np.arctan2(dy, dx) / (2 * np.pi) + 0.5) * sectors + 1e-6)
        band = np.floor((p[:, 2] if by_height else np.hypot(dx, dy)) * per_unit + 1e-6)
        parity = (sector + band) % 2
        return np.where(parity[:, None] > 0, np.asarray(rgb_a, float), np.asarray(rgb_b, float))
    return tex


VASE_AXIS = (-0.3, 0.15)
"""Where the vase of the ``vase`` scene stands (its axis, vertical)."""
VASE_FOOT_RADIUS, VASE_STEM_RADIUS, VASE_BODY_RADIUS, VASE_STEM_TOP = 0.09, 0.05, 0.44, -0.44
"""The vase's foot (its widest part under the body), stem, widest body radius (approximately: a
spline's) and the stem's top, where the body starts."""


def make_vase(detail: float) -> Scene:
    """A thin part under a wide one: a vase whose foot and stem are under a quarter of its body's width
    (the part a carving start from the masks misses), beside a checkered ball and a thin metal ring."""
    seg, h = int(96 * detail), 0.05 / detail
    zb, rf, rs, zs = -0.92, VASE_FOOT_RADIUS, VASE_STEM_RADIUS, VASE_STEM_TOP
    body = M.smooth_curve([[rs, zs], [0.15, -0.41], [0.31, -0.31], [0.42, -0.14], [VASE_BODY_RADIUS, 0.02],
                           [0.38, 0.22], [0.24, 0.40], [0.17, 0.52], [0.21, 0.64]])
    inside = M.smooth_curve([[0.18, 0.64], [0.13, 0.53], [0.17, 0.42], [0.12, 0.30], [0.0, 0.26]])
    loop = [
        M.Piece(np.array([[0.0, zb], [rf, zb]])),
        M.Piece(np.array([[rf, zb], [rf, zb + 0.035]])),
        M.Piece(np.array([[rf, zb + 0.035], [rs, zb + 0.06]])),
        M.Piece(np.array([[rs, zb + 0.06], [rs, zs]])),
        M.Piece(body),
        M.Piece(np.array([[0.21, 0.64], [0.18, 0.64]])),
        M.Piece(inside),
        M.Piece(np.array([[0.0, 0.26], [0.0, zb]]), virtual=True),
    ]
    vase = M.lathe(loop, seg, h, axis_xy=VASE_AXIS)
    ball_c, ring_c = (0.45, -0.35, -0.65), (0.5, 0.45, -0.68)
    ball = M.sphere(0.27, seg, h, center=ball_c)
    ring = M.torus(0.22, 0.018, seg, 12).rotated((1, 0, 0), 90.0).rotated((0, 0, 1), 30.0).translated(ring_c)
    mesh, materials = _parts([
        (vase, Material(solid((0.18, 0.42, 0.52)), ks=0.35, shininess=60, reflect=0.1)),
        (ball, Material(checker((0.92, 0.9, 0.84), (0.7, 0.15, 0.12), 7.0))),
        (ring, Material(solid((0.8, 0.8, 0.82)), ks=0.9, shininess=150, reflect=0.45)),
    ])
    edits = _edits(
        D.bend("bend", (*VASE_AXIS, zb), (0, 0, 1), (1, 0, 0), 35.0, 1.4),
        D.delete_part("delete_ring", D.ball(ring_c, 0.27), part="the ring"),
    )
    return Scene("vase", "a thin part under a wide one", mesh, materials, edits)


BOWL_AXIS, BOWL_RADIUS, BOWL_WALL = (-0.35, -0.2), 0.55, 0.02
"""The ``bowl`` scene's bowl: its axis, outer radius (a spherical shell) and wall thickness."""
BOX_CENTER, BOX_HALF, BOX_WALL, BOX_Z = (0.5, 0.45), 0.24, 0.02, (-0.92, -0.3)
"""Its open box: the centre of its square, half its side, its wall thickness and its bottom and top."""


def make_bowl(detail: float) -> Scene:
    """Open containers: a deep bowl and a box open at the top, both with thin walls (a thin rim) and a
    dark inside."""
    seg, h = int(96 * detail), 0.05 / detail
    r, t, zc, rim = BOWL_RADIUS, BOWL_WALL, -0.62 + BOWL_RADIUS, np.deg2rad(5.0)
    count = max(8, int(r * (rim + np.pi / 2) / h))
    outer, inner = M.arc((0.0, zc), r, -np.pi / 2, rim, count), M.arc((0.0, zc), r - t, rim, -np.pi / 2, count)
    outer[0, 0] = inner[-1, 0] = 0.0
    bowl_out = M.lathe([M.Piece(outer), M.Piece(np.stack([outer[-1], inner[0]]))], seg, h, axis_xy=BOWL_AXIS)
    bowl_in = M.lathe([M.Piece(inner)], seg, h, axis_xy=BOWL_AXIS)
    foot = M.cylinder(0.16, -0.92, zc - r + 0.012, seg, h, axis_xy=BOWL_AXIS)
    (x, y), a, w, (z0, z1) = BOX_CENTER, BOX_HALF, BOX_WALL, BOX_Z
    cuts = (-a, -a + w, a - w, a)  # walls as slabs meeting at the corners: no face spans inside and outside
    box = M.concatenate([
        M.box((x + lo_x, y + lo_y, z0), (x + hi_x, y + hi_y, z1 if (i, j) != (1, 1) else z0 + w), h)
        for i, (lo_x, hi_x) in enumerate(zip(cuts[:-1], cuts[1:]))
        for j, (lo_y, hi_y) in enumerate(zip(cuts[:-1], cuts[1:]))])  # the middle one: the floor
    centroid = box.vertices[box.faces].mean(axis=1)
    box_inside = ((np.abs(centroid[:, 0] - x) < a - w / 2) & (np.abs(centroid[:, 1] - y) < a - w / 2)
                  & (centroid[:, 2] > z0 + w / 2) & (centroid[:, 2] < z1 - 1e-6))
    dark = Material(solid((0.06, 0.05, 0.045)))
    mesh, materials = _parts([
        (bowl_out, Material(stripes((0.93, 0.9, 0.82), (0.2, 0.45, 0.4), 2, 6.0), ks=0.3, shininess=50)),
        (bowl_in, dark),
        (foot, Material(solid((0.2, 0.45, 0.4)), ks=0.3, shininess=50)),
        (M.submesh(box, ~box_inside), Material(solid((0.85, 0.5, 0.2)))),
        (M.submesh(box, box_inside), Material(solid((0.05, 0.05, 0.06)))),
    ])
    box_region = D.axis_box((x - a - 0.01, y - a - 0.01, z0 - 0.01), (x + a + 0.01, y + a + 0.01, z1 + 0.01))
    edits = _edits(
        D.bend("bend", (0, 0, -0.92), (0, 0, 1), (1, 1, 0), 30.0, 1.6),
        D.rigid_part("turn_box", box_region, (0, 0, 1), 35.0, (x, y, z0), part="the box"),
    )
    return Scene("bowl", "open containers with a dark inside", mesh, materials, edits)


LAMP_STEM_RADIUS, LAMP_SHADE = 0.035, ((0.72, 0.3), (0.34, 0.85))
"""The ``lamp`` scene's stem radius and its shade's outer line ``((r, z) bottom, (r, z) top)``."""
LAMP_HEAD_Z = 0.27
"""The height above which its ``tilt_head`` edit turns the lamp."""


def make_lamp(detail: float) -> Scene:
    """A concavity seen from below: a lamp with a thin stem, a thin brass plate and ring on it, and a
    wide open shade over a bulb, held by three thin spokes."""
    seg, h = int(96 * detail), 0.05 / detail
    rs, (bottom, top), t = LAMP_STEM_RADIUS, LAMP_SHADE, 0.02
    base = M.lathe([
        M.Piece(np.array([[0.0, -0.92], [0.34, -0.92]])),
        M.Piece(np.array([[0.34, -0.92], [0.34, -0.87]])),
        M.Piece(M.smooth_curve([[0.34, -0.87], [0.27, -0.83], [0.14, -0.805], [0.0, -0.8]])),
        M.Piece(np.array([[0.0, -0.8], [0.0, -0.92]]), virtual=True),
    ], seg, h)
    stem = M.cylinder(rs, -0.81, 0.43, max(12, seg // 4), h)
    plate = M.cylinder(0.2, -0.27, -0.255, seg, h)
    ring = M.torus(0.2, 0.02, seg, 12, center=(0, 0, -0.2625))
    ob, ot = np.asarray(bottom, float), np.asarray(top, float)
    along = (ot - ob) / np.linalg.norm(ot - ob)
    ib, it = ob + t * np.array([-along[1], along[0]]), ot + t * np.array([-along[1], along[0]])  # inward
    shade_out = M.lathe([M.Piece(np.stack([ib, ob])), M.Piece(np.stack([ob, ot])), M.Piece(np.stack([ot, it]))],
                        seg, h)
    shade_in = M.lathe([M.Piece(np.stack([it, ib]))], seg, h)
    bulb = M.sphere(0.1, seg // 2, h, center=(0, 0, 0.5))
    spoke_end = 0.5 * (ot + it)
    spokes = M.concatenate([
        M.tube(np.linspace([0.06 * math.cos(a), 0.06 * math.sin(a), 0.58],
                           [spoke_end[0] * math.cos(a), spoke_end[0] * math.sin(a), spoke_end[1]], 8), 0.012, 8,
               closed=False)
        for a in np.deg2rad([90.0, 210.0, 330.0])])
    mesh, materials = _parts([
        (base, Material(wood((0.5, 0.32, 0.18), (0.32, 0.19, 0.1), 12.0), ks=0.2, shininess=30)),
        (stem, Material(solid((0.75, 0.75, 0.78)), ks=0.7, shininess=80, reflect=0.3)),
        (M.concatenate([plate, ring]), Material(solid((0.85, 0.62, 0.28)), ks=0.8, shininess=90, reflect=0.3)),
        (shade_out, Material(stripes((0.9, 0.84, 0.7), (0.8, 0.7, 0.52), 2, 10.0))),
        (shade_in, Material(solid((0.96, 0.93, 0.85)))),
        (bulb, Material(solid((0.98, 0.97, 0.92)), ks=0.3, shininess=40)),
        (spokes, Material(solid((0.75, 0.75, 0.78)), ks=0.7, shininess=80, reflect=0.3)),
    ])
    edits = _edits(
        D.twist("twist", (0, 0, 0), (0, 0, 1), 60.0),
        D.rigid_part("tilt_head", D.halfspace((0, 0, 1), LAMP_HEAD_Z), (1, 0, 0), 30.0, (0, 0, LAMP_HEAD_Z),
                     part="the lamp's head"),
    )
    return Scene("lamp", "a concavity seen from below, thin parts", mesh, materials, edits)


DISH_AXIS, DISH_CELL = (-0.35, -0.3), 1.0 / 16.0
"""The ``pattern`` scene's dish axis and the size of its fine checker's bands (world units; a pixel
at 200 px is 0.0144 wide at the cameras' target)."""


def make_pattern(detail: float) -> Scene:
    """Fine texture on curved surfaces: a dish (concave) with a fine polar checker inside, a column with a
    fine checker and a ball with fine stripes, each band 3-5 pixels wide at 200 px."""
    seg, h = int(96 * detail), 0.05 / detail
    r, t, zc, open_angle = 0.75, 0.02, -0.78 + 0.75, np.deg2rad(50.0)
    rim = -np.pi / 2 + open_angle
    count = max(8, int(r * open_angle / h))
    outer, inner = M.arc((0.0, zc), r, -np.pi / 2, rim, count), M.arc((0.0, zc), r - t, rim, -np.pi / 2, count)
    outer[0, 0] = inner[-1, 0] = 0.0
    dish_out = M.lathe([M.Piece(outer), M.Piece(np.stack([outer[-1], inner[0]]))], seg, h, axis_xy=DISH_AXIS)
    dish_in = M.lathe([M.Piece(inner)], seg, h, axis_xy=DISH_AXIS)
    foot = M.cylinder(0.15, -0.92, -0.77, seg, h, axis_xy=DISH_AXIS)
    column_xy, ball_c, ball_r = (0.5, -0.45), (0.5, 0.4, -0.62), 0.3
    column = M.cylinder(0.2, -0.92, 0.35, seg, h, axis_xy=column_xy)
    ball = M.sphere(ball_r, seg, h, center=ball_c)
    mesh, materials = _parts([
        (dish_in, Material(polar_checker((0.92, 0.9, 0.85), (0.12, 0.14, 0.2), 48, 1.0 / DISH_CELL, DISH_AXIS))),
        (dish_out, Material(solid((0.55, 0.3, 0.2)), ks=0.2, shininess=30)),
        (foot, Material(solid((0.6, 0.6, 0.62)), ks=0.6, shininess=60, reflect=0.2)),
        (column, Material(polar_checker((0.95, 0.8, 0.25), (0.15, 0.3, 0.65), 20, 1.0 / DISH_CELL, column_xy,
                                        by_height=True))),
        (ball, Material(stripes((0.75, 0.15, 0.15), (0.95, 0.92, 0.85), 2, 10.0), ks=0.35, shininess=60,
                        reflect=0.1)),
    ])
    dish_region = D.vertical_cylinder(DISH_AXIS, 0.6, z_lo=-0.95, z_hi=-0.45)
    edits = _edits(
        D.rigid_part("spin_dish", dish_region, (0, 0, 1), 5.0, (*DISH_AXIS, 0.0), part="the dish"),
        D.rigid_part("roll_ball", D.ball(ball_c, ball_r + 0.01), (1, 0, 0), 90.0, ball_c, part="the ball"),
    )
    return Scene("pattern", "fine texture on curved and concave surfaces", mesh, materials, edits)


HELDOUT_SCENES: dict[str, Callable[[float], Scene]] = {
    "vase": make_vase,
    "bowl": make_bowl,
    "lamp": make_lamp,
    "pattern": make_pattern,
}
"""The held-out scenes: generated once, never used to choose a setting (docs/benchmark.md, "The held-out
scenes"). Not in :data:`SCENES`, so the default benchmark stays the four tuning scenes."""

SCENE_SETS: dict[str, tuple[str, ...]] = {"tuning": tuple(SCENES), "heldout": tuple(HELDOUT_SCENES)}
"""Names that stand for several scenes (:func:`scene_names`): the tuning scenes and the held-out ones."""


def get_scene(name: str, detail: float = 1.0) -> Scene:
    """The benchmark scene ``name`` (of :data:`SCENES` or :data:`HELDOUT_SCENES`) with mesh resolution
    scaled by ``detail``."""
    make = SCENES.get(name) or HELDOUT_SCENES.get(name)
    if make is None:
        raise KeyError(f"unknown scene {name!r}; expected one of {sorted(SCENES) + sorted(HELDOUT_SCENES)}")
    return make(detail)


def scene_names(names=None) -> list[str]:
    """The scenes ``names`` stands for, in order and each once: a scene's name, or a set's of
    :data:`SCENE_SETS` (``heldout``: the four held-out scenes); ``None``: the tuning scenes
    (:data:`SCENES`). A ``KeyError`` names the first unknown one."""
    out = []
    for n in list(SCENES) if names is None else names:
        if n in SCENE_SETS:
            out.extend(SCENE_SETS[n])
        elif n in SCENES or n in HELDOUT_SCENES:
            out.append(n)
        else:
            raise KeyError(f"unknown scene {n!r}; expected one of {sorted(SCENES) + sorted(HELDOUT_SCENES)} or a "
                           f"set of them: {sorted(SCENE_SETS)}")
    return list(dict.fromkeys(out))


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

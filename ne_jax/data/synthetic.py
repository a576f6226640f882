"""The procedural editing benchmark: scenes, their edits, and a ray-casting renderer.

The paper's benchmark (NeRF Synthetic scenes deformed in Blender) cannot be downloaded, so ne_jax
makes its own the same way: build a scene, render it from many views, apply each edit to the scene's
mesh, render the edited scene again as ground truth. The edits are functions of 3-D points
(:mod:`ne_jax.edit.deformations`), so exactly the same edit is later applied to a model's points.

Renderer: Open3D's ``RaycastingScene`` (Embree) with two-sided Blinn-Phong shading, shadow rays for
two directional lights, a sky-gradient environment reflection for glossy materials, and a fixed
``ss x ss`` grid of sub-pixel samples per pixel for anti-aliasing and alpha. It is noise-free and
bit-for-bit repeatable; at 200x200 it is ~3.5x faster than Mitsuba 3 ``scalar_rgb`` at 32 spp and
~12x faster than at the 128 spp that Mitsuba needs for ~32 dB clean ground truth
(``experiments/compare_renderers.py`` measures both). Highlights move with the view, which is the
view-dependent colour that IST exists for. It has no inter-reflections.

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

from ne_jax.data import meshes as M
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


@dataclass(frozen=True)
class Light:
    direction: tuple  # towards the light
    intensity: float
    shadows: bool = True


LIGHTS = (Light((0.6, -0.5, 1.0), 0.95), Light((-0.9, 0.4, 0.5), 0.45), Light((0.1, 0.8, -0.4), 0.2, False))
AMBIENT = 0.18
GAMMA = 2.2


def sky(direction: np.ndarray) -> np.ndarray:
    """Linear-RGB environment seen in direction ``[n, 3]``: warm ground to blue sky, plus a sun."""
    t = np.clip(0.5 + 0.5 * direction[:, 2], 0.0, 1.0)[:, None]
    base = (1 - t) * np.array([0.12, 0.10, 0.08]) + t * np.array([0.45, 0.6, 0.9])
    sun = np.asarray(LIGHTS[0].direction, float)
    sun = sun / np.linalg.norm(sun)
    return base + 2.0 * np.clip(direction @ sun, 0.0, 1.0)[:, None] ** 200


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
    handle_region = D.beyond_radius(0.5515)
    edits = _edits(
        D.bend("bend", (0, 0, -0.6), (0, 0, 1), (1, 0, 0), 50.0, 1.2),
        D.rigid_part("turn_handle", handle_region, (0, 0, 1), 90.0, (0, 0, 0)),
        D.cut("cut", (0, 0, cut_z), (0, 0, 1), 0.35),
        D.delete_part("delete_handle", handle_region),
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


# ---------------------------------------------------------------------------------- cameras

CAMERA_ANGLE_X = 0.6911112070083618  # the NeRF Synthetic value (about 39.6 degrees)
CAMERA_RADIUS = 4.0
NEAR, FAR = 2.0, 6.0


def look_at(eye: np.ndarray, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """OpenGL camera-to-world ``[4, 4]`` at ``eye`` looking at ``target`` (camera -z forward)."""
    eye = np.asarray(eye, np.float64)
    forward = np.asarray(target, np.float64) - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-9:  # looking straight up or down
        right = np.cross(forward, (0.0, 1.0, 0.0))
    right /= np.linalg.norm(right)
    true_up = np.cross(right, forward)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, true_up, -forward, eye
    return c2w


def random_cameras(count: int, rng: np.random.Generator, min_elev=-15.0, max_elev=75.0) -> np.ndarray:
    """``[count, 4, 4]`` cameras on the sphere of radius ``CAMERA_RADIUS``, uniform in area between
    the elevations (degrees)."""
    lo, hi = np.sin(np.deg2rad(min_elev)), np.sin(np.deg2rad(max_elev))
    z = rng.uniform(lo, hi, count)
    az = rng.uniform(0.0, 2 * np.pi, count)
    r = np.sqrt(1 - z**2)
    eyes = CAMERA_RADIUS * np.stack([r * np.cos(az), r * np.sin(az), z], axis=1)
    return np.stack([look_at(e) for e in eyes])


def orbit_cameras(count: int, elevation_deg: float = 25.0) -> np.ndarray:
    """``[count, 4, 4]`` cameras evenly spaced on a circle at ``elevation_deg``."""
    el = np.deg2rad(elevation_deg)
    az = 2 * np.pi * np.arange(count) / count
    eyes = CAMERA_RADIUS * np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.full(count, np.sin(el))], 1)
    return np.stack([look_at(e) for e in eyes])


# --------------------------------------------------------------------------------- renderer


class RayCaster:
    """Blinn-Phong ray caster over one (edited) scene mesh; see the module docstring.

    ``environment``: a rotation ``[3, 3]`` applied to the lights and the sky (light directions ``R l``,
    sky seen in direction ``d`` is ``sky(R^T d)``); ``None`` (the benchmark's setting): as defined by
    ``LIGHTS`` and :func:`sky`."""

    def __init__(self, mesh: EditedMesh, materials: tuple[Material, ...], environment: np.ndarray | None = None):
        import open3d as o3d  # heavy import, only where rendering happens

        self._o3d = o3d
        self.mesh = mesh
        self.materials = materials
        self.environment = None if environment is None else np.asarray(environment, np.float64)
        self.normals = M.vertex_normals(mesh.vertices, mesh.faces)
        self.scene = o3d.t.geometry.RaycastingScene()
        if len(mesh.faces):
            self.scene.add_triangles(
                o3d.core.Tensor(mesh.vertices.astype(np.float32)), o3d.core.Tensor(mesh.faces.astype(np.uint32))
            )

    def _cast(self, origins: np.ndarray, dirs: np.ndarray) -> dict[str, np.ndarray]:
        rays = self._o3d.core.Tensor(np.concatenate([origins, dirs], 1).astype(np.float32))
        out = self.scene.cast_rays(rays)
        return {k: out[k].numpy() for k in ("t_hit", "primitive_ids", "primitive_uvs", "primitive_normals")}

    def hit_distance(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """Distance ``[n]`` along each ray ``(origins, dirs)`` ``[n, 3]`` (unit ``dirs``) to the first
        surface it hits; ``inf`` for a miss."""
        return self._cast(origins, dirs)["t_hit"]

    def _occluded(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        rays = self._o3d.core.Tensor(np.concatenate([origins, dirs], 1).astype(np.float32))
        return self.scene.test_occlusions(rays).numpy().astype(bool)

    def shade(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Linear RGB ``[n, 3]`` and hit mask ``[n]`` for rays ``(origins, dirs)`` ``[n, 3]``."""
        hit_info = self._cast(origins, dirs)
        hit = np.isfinite(hit_info["t_hit"])
        rgb = np.zeros((len(dirs), 3))
        if not hit.any():
            return rgb, hit
        face = hit_info["primitive_ids"][hit].astype(np.int64)
        uv = hit_info["primitive_uvs"][hit].astype(np.float64)
        bary = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], 1)
        d = dirs[hit]
        point = origins[hit] + hit_info["t_hit"][hit, None] * d
        n_geo = hit_info["primitive_normals"][hit].astype(np.float64)
        n = M.interpolate(self.normals, self.mesh.faces, face, bary)
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        facing = np.sign(np.sum(n_geo * -d, axis=1, keepdims=True))  # two-sided shading
        facing[facing == 0] = 1.0
        n_geo, n = n_geo * facing, n * facing
        rest = M.interpolate(self.mesh.rest, self.mesh.faces, face, bary)
        mat_id = self.mesh.material[face]
        albedo = np.zeros_like(point)
        ks, shin, refl = np.zeros(len(point)), np.ones(len(point)), np.zeros(len(point))
        for i, m in enumerate(self.materials):
            sel = mat_id == i
            if sel.any():
                albedo[sel] = m.albedo(rest[sel])
                ks[sel], shin[sel], refl[sel] = m.ks, m.shininess, m.reflect
        albedo = np.clip(albedo, 0.0, 1.0) ** GAMMA
        colour = AMBIENT * albedo
        view = -d
        lift = point + 1e-4 * n_geo
        for light in LIGHTS:
            ldir = np.asarray(light.direction, np.float64)
            ldir = ldir / np.linalg.norm(ldir)
            if self.environment is not None:
                ldir = self.environment @ ldir
            ndotl = np.clip(n @ ldir, 0.0, None)
            lit = ndotl > 0
            if light.shadows:
                lit &= ~self._occluded(lift, np.broadcast_to(ldir, lift.shape))
            half = view + ldir
            half /= np.maximum(np.linalg.norm(half, axis=1, keepdims=True), 1e-12)
            spec = ks * np.clip(np.sum(n * half, 1), 0.0, None) ** shin
            colour += (light.intensity * lit)[:, None] * (albedo * ndotl[:, None] + spec[:, None])
        mirror = d - 2.0 * np.sum(d * n, 1, keepdims=True) * n
        if self.environment is not None:
            mirror = mirror @ self.environment  # R^T d: the direction in the unrotated environment
        colour += refl[:, None] * sky(mirror)
        rgb[hit] = colour
        return rgb, hit

    def render(self, c2w: np.ndarray, width: int, height: int, camera_angle_x: float, ss: int = 2) -> np.ndarray:
        """Straight-alpha RGBA ``[H, W, 4]`` float in ``[0, 1]`` with ``ss x ss`` samples per pixel."""
        focal = 0.5 * width / math.tan(0.5 * camera_angle_x)
        offsets = (np.arange(ss) + 0.5) / ss
        j, i, sj, si = np.meshgrid(np.arange(height), np.arange(width), offsets, offsets, indexing="ij")
        x = (i + si - 0.5 * width) / focal
        y = -(j + sj - 0.5 * height) / focal
        d = np.stack([x, y, -np.ones_like(x)], -1).reshape(-1, 3) @ c2w[:3, :3].T
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        o = np.broadcast_to(c2w[:3, 3], d.shape)
        rgb, hit = self.shade(o, d)
        display = np.clip(rgb, 0.0, 1.0) ** (1.0 / GAMMA)
        display = display.reshape(height, width, ss * ss, 3)
        hit = hit.reshape(height, width, ss * ss)
        alpha = hit.mean(-1)
        colour = (display * hit[..., None]).sum(2) / np.maximum(hit.sum(-1), 1)[..., None]
        return np.concatenate([colour, alpha[..., None]], -1)


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

"""The benchmark's ground-truth renderer: a Blinn-Phong ray caster over Open3D's ``RaycastingScene``
(Embree), with shadow rays for directional lights, a sky-gradient environment reflected by glossy
materials, and a fixed ``ss x ss`` grid of sub-pixel samples per pixel for anti-aliasing and alpha.
Noise-free and bit-for-bit repeatable; no inter-reflections (see :mod:`ne_jax.benchmark.scenes`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ne_jax.benchmark import meshes as M
from ne_jax.benchmark.scenes import EditedMesh, Material


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
        color = AMBIENT * albedo
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
            color += (light.intensity * lit)[:, None] * (albedo * ndotl[:, None] + spec[:, None])
        mirror = d - 2.0 * np.sum(d * n, 1, keepdims=True) * n
        if self.environment is not None:
            mirror = mirror @ self.environment  # R^T d: the direction in the unrotated environment
        color += refl[:, None] * sky(mirror)
        rgb[hit] = color
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
        color = (display * hit[..., None]).sum(2) / np.maximum(hit.sum(-1), 1)[..., None]
        return np.concatenate([color, alpha[..., None]], -1)

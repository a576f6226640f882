"""The path-traced ground-truth renderer: a benchmark scene rendered by Mitsuba 3's path tracer under an
environment map, with physically based materials (a conductor, glossy plastics, rough diffuse surfaces).

It is the alternative to :mod:`ne_jax.benchmark.raycaster` for the ``*_pt`` presets of
:mod:`ne_jax.benchmark.generate`. What it adds over the ray caster is global illumination: light
inter-reflected inside the open cup and between parts, glossy reflections of the whole environment
(not just the sky gradient), soft shadows from area-like sun spots, and a metal whose reflection is
tinted. What it costs is Monte Carlo noise (``spp`` samples per pixel; the noise floor is measured by
docs/decisions.md, "The path tracer's noise floor") and time.

* **Environment** (:func:`environment_map`): a lat-long map made here (nothing is downloaded): the ray
  caster's sky gradient (warm ground to blue sky) plus two bright sun spots in the directions of its
  two shadowed lights. ``environment`` (a rotation ``R``) turns it as :class:`RayCaster` turns its
  lights and sky: radiance from world direction ``d`` is ``environment_map(R^T d)``.
* **Materials** (:class:`Surface`, :data:`SURFACES`): each part of each scene gets a Mitsuba BSDF;
  colours come from the scene's albedo textures (functions of rest positions) as vertex colours on a
  mesh subdivided (flat, midpoint 1:4 splits) until its edges are shorter than ``max_edge``, so a
  texture keeps its detail at the image's pixel size.
* **Images** (:meth:`PathTracer.render`): the ray caster's contract: straight-alpha display RGBA
  ``[H, W, 4]`` in ``[0, 1]`` (alpha from the film's alpha channel, colour ``linear^(1/2.2)``).
  Deterministic for a seed (Mitsuba's ``scalar_rgb`` variant, a fixed sampler seed per image).
  With ``visible_environment`` (the capture variant, :mod:`ne_jax.benchmark.capture`) the
  environment shows behind the objects and alpha is 1; ``extra_parts`` adds parts such as its ground.

The variant is ``scalar_rgb``: it runs everywhere and its images do not depend on the machine's LLVM
(``llvm_ad_rgb`` would be 2-3x faster but needs libLLVM >= 16, and gives other bytes for a seed).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ne_jax.benchmark import meshes as M
from ne_jax.benchmark.raycaster import GAMMA, LIGHTS
from ne_jax.benchmark.scenes import EditedMesh, Material
from ne_jax.data.cameras import CAMERA_RADIUS

VARIANT = "scalar_rgb"
"""The Mitsuba variant every path-traced image is rendered with."""
INSTALL_HINT = "pip install 'mitsuba>=3.5,<4'"

ENV_WIDTH = 512
"""Environment map width in pixels (height: half); 0.7 degrees per pixel resolves the sun spots."""
SKY_SCALE = 0.9
"""Radiance of the sky gradient relative to the ray caster's ``sky()`` base colours."""
SUNS = ((LIGHTS[0].direction, 2.6, 16.0), (LIGHTS[1].direction, 1.0, 20.0))
"""Sun spots: ``(direction towards the sun, irradiance it gives a facing surface (in units of pi),
angular radius in degrees)``; a Gaussian lobe of radiance around the direction. Broad spots (not a
0.5-degree sun): light from a small bright spot, reflected by the gold ring onto the sphere, is the
caustic path that dominates the noise; at 4-6 degrees the glossy scene is ~3 dB noisier at equal spp."""
MAX_DEPTH = 6
"""Longest light path (Mitsuba's ``max_depth``: 6 = up to four bounces between surfaces)."""
SAMPLER = "ldsampler"
"""Mitsuba's low-discrepancy sampler: up to 3 dB less noise than ``independent`` at the same spp."""


def pixel_footprint(resolution: int, camera_angle_x: float) -> float:
    """Width in world units of one pixel at the cameras' target (``CAMERA_RADIUS`` away): the
    ``max_edge`` :class:`PathTracer` splits textured parts to."""
    return 2.0 * CAMERA_RADIUS * math.tan(0.5 * camera_angle_x) / resolution


@dataclass(frozen=True)
class Surface:
    """A physically based material for one scene part.

    ``kind``: ``"diffuse"`` (Lambertian, albedo from the texture), ``"plastic"`` (Mitsuba
    ``principled``: the texture under a GGX dielectric coat of roughness ``alpha``, IOR 1.5), or
    ``"conductor"`` (``roughconductor`` of the measured metal ``metal``, GGX ``alpha``; the texture
    is not used)."""

    kind: str
    alpha: float = 0.1
    metal: str = "Au"

    def __post_init__(self):
        if self.kind not in ("diffuse", "plastic", "conductor"):
            raise ValueError(f"Surface.kind: expected 'diffuse', 'plastic' or 'conductor', found {self.kind!r}")
        if not 0.0 < self.alpha <= 1.0:
            raise ValueError(f"Surface.alpha: expected a GGX roughness in (0, 1], found {self.alpha}")


SURFACES: dict[str, tuple[Surface, ...]] = {
    # varnished wooden seat, chrome legs, red plastic ring
    "stool": (Surface("plastic", 0.25), Surface("conductor", 0.2, "Cr"), Surface("plastic", 0.15)),
    # glazed mug (open, concave: inter-reflection inside), glazed handle, rough diffuse ball
    "cup": (Surface("plastic", 0.08), Surface("plastic", 0.08), Surface("diffuse")),
    # rough diffuse textured parts
    "blocks": (Surface("diffuse"), Surface("diffuse"), Surface("diffuse")),
    # glossy red plastic sphere, brushed gold ring, glossy blue plastic cube (a smoother ring and sphere
    # make the caustics the ring throws on the sphere, and so the noise, several dB worse)
    "glossy": (Surface("plastic", 0.1), Surface("conductor", 0.2, "Au"), Surface("plastic", 0.15)),
    # the held-out scenes (scenes.HELDOUT_SCENES): glazed vase, rough checkered ball, polished silver ring
    "vase": (Surface("plastic", 0.1), Surface("diffuse"), Surface("conductor", 0.15, "Ag")),
    # glazed bowl with a rough dark inside, its glazed foot, a rough painted box with a dark inside
    "bowl": (Surface("plastic", 0.12), Surface("diffuse"), Surface("plastic", 0.12), Surface("diffuse"),
             Surface("diffuse")),
    # varnished wooden base, chrome stem, brass plate and ring, fabric shade (out, in), glass-like bulb,
    # chrome spokes
    "lamp": (Surface("plastic", 0.25), Surface("conductor", 0.15, "Cr"), Surface("conductor", 0.2, "Cu"),
             Surface("diffuse"), Surface("diffuse"), Surface("plastic", 0.2), Surface("conductor", 0.15, "Cr")),
    # rough textured dish inside, glazed outside, aluminium foot, rough column, glossy striped ball
    "pattern": (Surface("diffuse"), Surface("plastic", 0.25), Surface("conductor", 0.25, "Al"), Surface("diffuse"),
                Surface("plastic", 0.15)),
}
"""The material of each part of each scene (indexed like ``Scene.materials``)."""


def surface_from_material(material: Material) -> Surface:
    """A stand-in :class:`Surface` for a Blinn-Phong material of a scene :data:`SURFACES` does not list:
    diffuse without a highlight, else plastic with the GGX roughness of the Phong exponent."""
    if material.ks <= 0.0 and material.reflect <= 0.0:
        return Surface("diffuse")
    return Surface("plastic", float(min(1.0, math.sqrt(2.0 / (material.shininess + 2.0)))))


def scene_surfaces(scene_name: str, materials: tuple[Material, ...]) -> tuple[Surface, ...]:
    """The :class:`Surface` of each of a scene's ``materials`` (:data:`SURFACES`, else derived)."""
    surfaces = SURFACES.get(scene_name)
    if surfaces is None:
        return tuple(surface_from_material(m) for m in materials)
    if len(surfaces) != len(materials):
        raise ValueError(f"SURFACES[{scene_name!r}]: expected one surface per material ({len(materials)}), "
                         f"found {len(surfaces)}")
    return surfaces


def import_mitsuba():
    """Mitsuba with :data:`VARIANT` set; an ``ImportError`` saying how to install it where missing."""
    try:
        import mitsuba as mi
    except ImportError as err:
        raise ImportError(f"the path-traced benchmark needs Mitsuba 3 ({INSTALL_HINT}); {err}") from err
    if mi.variant() != VARIANT:
        mi.set_variant(VARIANT)
    return mi


# ------------------------------------------------------------------------------ environment


def envmap_directions(width: int = ENV_WIDTH) -> np.ndarray:
    """World direction ``[width/2, width, 3]`` of each pixel centre of a Mitsuba lat-long map with an
    identity ``to_world``: pixel ``(u, v)`` looks along ``(sin(pi v) sin(2 pi u), cos(pi v),
    -sin(pi v) cos(2 pi u))``."""
    h = width // 2
    uu, vv = np.meshgrid((np.arange(width) + 0.5) / width, (np.arange(h) + 0.5) / h)
    st = np.sin(np.pi * vv)
    return np.stack([st * np.sin(2 * np.pi * uu), np.cos(np.pi * vv), -st * np.cos(2 * np.pi * uu)], -1)


def environment_radiance(d: np.ndarray) -> np.ndarray:
    """Linear-RGB radiance ``[n, 3]`` arriving from unit directions ``d`` ``[n, 3]`` (z up): the sky
    gradient plus the sun spots of :data:`SUNS`."""
    t = np.clip(0.5 + 0.5 * d[:, 2], 0.0, 1.0)[:, None]
    rgb = SKY_SCALE * ((1 - t) * np.array([0.12, 0.10, 0.08]) + t * np.array([0.45, 0.6, 0.9]))
    for direction, irradiance, radius_deg in SUNS:
        s = np.asarray(direction, np.float64)
        s = s / np.linalg.norm(s)
        sigma = math.radians(radius_deg) / 2.0
        # A Gaussian lobe exp(-theta^2 / (2 sigma^2)) covers a solid angle of ~2 pi sigma^2; its peak is
        # set so the lobe gives a facing surface the irradiance pi * irradiance (a white diffuse
        # surface then shows ``irradiance``, as the ray caster's lights do).
        peak = math.pi * irradiance / (2 * math.pi * sigma**2)
        theta2 = 2.0 * (1.0 - np.clip(d @ s, -1.0, 1.0))  # ~theta^2 near the sun
        rgb = rgb + (peak * np.exp(-theta2 / (2 * sigma**2)))[:, None] * np.array([1.0, 0.96, 0.9])
    return rgb


def environment_map(width: int = ENV_WIDTH) -> np.ndarray:
    """The environment as a Mitsuba lat-long bitmap ``[width/2, width, 3]`` float32 (see
    :func:`envmap_directions`)."""
    d = envmap_directions(width)
    return environment_radiance(d.reshape(-1, 3)).reshape(*d.shape[:2], 3).astype(np.float32)


# ------------------------------------------------------------------------------------ meshes


def subdivide(values: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One flat 1:4 split: per-vertex ``values [V, D]`` (positions first) gain the midpoint of every
    edge (shared by its two faces); ``faces [F, 3]`` become ``[4F, 3]``. The surface does not move."""
    n_faces = len(faces)
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    unique, inverse = np.unique(edges, axis=0, return_inverse=True)
    mid = len(values) + inverse.reshape(n_faces, 3)
    values = np.concatenate([values, 0.5 * (values[unique[:, 0]] + values[unique[:, 1]])])
    a, b, c = faces.T
    ab, bc, ca = mid.T
    faces = np.concatenate([np.stack(f, 1) for f in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
    return values, faces


def _longest_edge(vertices: np.ndarray, faces: np.ndarray) -> float:
    tri = vertices[faces]
    return float(np.max(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=-1))) if len(faces) else 0.0


def _bsdf(surface: Surface, color: dict) -> dict:
    if surface.kind == "diffuse":
        inner = {"type": "diffuse", "reflectance": color}
    elif surface.kind == "plastic":
        # principled (not roughplastic, which needs a texture's mean): a dielectric coat with Disney's
        # roughness (GGX alpha = roughness^2), F0 = 0.04 (IOR 1.5), the texture as base colour.
        inner = {"type": "principled", "base_color": color, "roughness": math.sqrt(surface.alpha),
                 "metallic": 0.0, "specular": 0.5}
    else:
        inner = {"type": "roughconductor", "distribution": "ggx", "alpha": surface.alpha, "material": surface.metal}
    return {"type": "twosided", "bsdf": inner}


@dataclass(frozen=True, eq=False)
class FlatPart:
    """A part :class:`PathTracer` adds as it is, without the splitting that resolves a scene part's
    texture: ``vertices [V, 3]``, ``faces [F, 3]``, sRGB ``albedo [V, 3]`` per vertex (a texture the
    mesh already resolves, e.g. one colour per cell on the cell's own four vertices) and its
    :class:`Surface`."""

    vertices: np.ndarray
    faces: np.ndarray
    albedo: np.ndarray
    surface: Surface


class PathTracer:
    """Mitsuba 3 path tracer over one (edited) scene mesh; see the module docstring.

    ``mesh``: the mesh to render (``scenes.truth_mesh``), ``materials``: the scene's (for the albedo
    textures), ``surfaces``: one :class:`Surface` per material (:func:`scene_surfaces`),
    ``environment``: a rotation ``[3, 3]`` of the environment (``None``: as defined),
    ``max_edge``: textured parts are split until no edge is longer (world units), ``spp``: samples
    per pixel, ``extra_parts``: :class:`FlatPart` s added as they are (the capture variant's ground),
    ``visible_environment``: camera rays that miss every surface see the environment map (the film's
    alpha is then 1 everywhere) instead of a transparent background."""

    def __init__(self, mesh: EditedMesh, materials: tuple[Material, ...], surfaces: tuple[Surface, ...],
                 environment: np.ndarray | None = None, max_edge: float = 0.02, spp: int = 64,
                 extra_parts: tuple[FlatPart, ...] = (), visible_environment: bool = False):
        if len(surfaces) != len(materials):
            raise ValueError(f"surfaces: expected one per material ({len(materials)}), found {len(surfaces)}")
        if spp < 1:
            raise ValueError(f"spp: expected a positive sample count, found {spp}")
        mi = import_mitsuba()
        self.mi, self.spp, self.faces = mi, int(spp), 0
        normals = M.vertex_normals(mesh.vertices, mesh.faces)
        objects: dict[str, object] = {}
        for i, (material, surface) in enumerate(zip(materials, surfaces)):
            faces = mesh.faces[mesh.material == i]
            if len(faces) == 0:
                continue
            used = np.unique(faces)
            remap = np.full(len(mesh.vertices), -1, np.int64)
            remap[used] = np.arange(len(used))
            values = np.concatenate([mesh.vertices[used], normals[used], mesh.rest[used]], 1)
            faces = remap[faces]
            albedo = material.albedo(values[:, 6:9])
            if surface.kind != "conductor" and np.ptp(albedo, axis=0).max() > 0:  # a texture: resolve it
                while _longest_edge(values[:, :3], faces) > max_edge:
                    values, faces = subdivide(values, faces)
                albedo = material.albedo(values[:, 6:9])
            linear = np.clip(albedo, 0.0, 1.0) ** GAMMA  # sRGB albedo to linear, as the ray caster does
            objects[f"part{i}"] = self._mesh(f"part{i}", values, faces, linear, surface)
            self.faces += len(faces)
        for j, part in enumerate(extra_parts):
            values = np.concatenate([part.vertices, M.vertex_normals(part.vertices, part.faces)], 1)
            linear = np.clip(part.albedo, 0.0, 1.0) ** GAMMA
            objects[f"extra{j}"] = self._mesh(f"extra{j}", values, part.faces, linear, part.surface)
            self.faces += len(part.faces)
        emitter = {"type": "envmap", "bitmap": mi.Bitmap(environment_map())}
        if environment is not None:
            rot = np.eye(4)
            rot[:3, :3] = np.asarray(environment, np.float64)
            emitter["to_world"] = mi.ScalarTransform4f(rot.tolist())
        self.scene = mi.load_dict({
            "type": "scene",
            "integrator": {"type": "path", "max_depth": MAX_DEPTH, "hide_emitters": not visible_environment},
            "environment": emitter,
            **objects,
        })

    def _mesh(self, name: str, values: np.ndarray, faces: np.ndarray, albedo: np.ndarray, surface: Surface):
        mi = self.mi
        props = mi.Properties()
        props["bsdf"] = mi.load_dict(_bsdf(surface, {"type": "mesh_attribute", "name": "vertex_color"}))
        mesh = mi.Mesh(name, len(values), len(faces), props=props, has_vertex_normals=True)
        params = mi.traverse(mesh)
        for key, arr in (("vertex_positions", values[:, :3]), ("vertex_normals", values[:, 3:6])):
            params[key] = type(params[key])(arr.astype(np.float32).ravel())
        params["faces"] = type(params["faces"])(faces.astype(np.uint32).ravel())
        params.update()
        mesh.add_attribute("vertex_color", 3, type(params["vertex_positions"])(albedo.astype(np.float32).ravel()))
        return mesh

    def _sensor(self, c2w: np.ndarray, width: int, height: int, camera_angle_x: float):
        # NeRF/Blender cameras look along -z with +x right; Mitsuba's look along +z with +x to the left.
        to_world = np.asarray(c2w, np.float64) @ np.diag([-1.0, 1.0, -1.0, 1.0])
        return self.mi.load_dict({
            "type": "perspective",
            "fov": math.degrees(camera_angle_x),
            "fov_axis": "x",
            "to_world": self.mi.ScalarTransform4f(to_world.tolist()),
            "film": {"type": "hdrfilm", "width": width, "height": height, "pixel_format": "rgba",
                     "rfilter": {"type": "box"}},
            "sampler": {"type": SAMPLER, "sample_count": self.spp},
        })

    def render_linear(self, c2w: np.ndarray, width: int, height: int, camera_angle_x: float,
                      seed: int = 0) -> np.ndarray:
        """Mitsuba's film: premultiplied linear RGBA ``[H, W, 4]`` float64 (non-finite values zeroed)."""
        sensor = self._sensor(c2w, width, height, camera_angle_x)
        img = np.array(self.mi.render(self.scene, sensor=sensor, spp=self.spp, seed=int(seed)), dtype=np.float64)
        img[~np.isfinite(img)] = 0.0
        return img

    def render(self, c2w: np.ndarray, width: int, height: int, camera_angle_x: float, ss: int | None = None,
               seed: int = 0) -> np.ndarray:
        """Straight-alpha display RGBA ``[H, W, 4]`` float32 in ``[0, 1]`` seen by the camera ``c2w``
        ``[4, 4]`` (OpenGL); ``ss`` is accepted for the ray caster's signature and unused (anti-aliasing
        comes from the ``spp`` samples spread over each pixel); ``seed`` picks the noise."""
        img = self.render_linear(c2w, width, height, camera_angle_x, seed)
        alpha = np.clip(img[..., 3:4], 0.0, 1.0)
        straight = np.where(alpha > 0, img[..., :3] / np.maximum(alpha, 1e-8), 0.0)
        display = np.clip(straight, 0.0, 1.0) ** (1.0 / GAMMA)
        return np.concatenate([display, alpha], -1).astype(np.float32)


__all__ = ["SURFACES", "VARIANT", "FlatPart", "PathTracer", "Surface", "environment_map", "environment_radiance",
           "import_mitsuba", "pixel_footprint", "scene_surfaces", "subdivide", "surface_from_material"]

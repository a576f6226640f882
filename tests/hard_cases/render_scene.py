"""A tiny fixed scene rendered by the end-to-end stage, in this process's dtype; also a script, so
the float32-vs-float64 comparison can render it in a second process with the other dtype
(``JAX_ENABLE_X64`` cannot be switched inside a process once something has been traced):

    python tests/hard_cases/render_scene.py INPUTS.npz OUTPUT.npz

Inputs are float64 numpy arrays whose values are float32-representable (so both processes render
the same numbers); the colour-model parameters travel in the npz as leaves in tree order.
"""

from __future__ import annotations

import functools
import sys

import jax
import jax.numpy as jnp
import numpy as np

from ne_jax.data.rays import Rays
from ne_jax.geometry import PointState
from ne_jax.geometry.capacity import Capacities
from ne_jax.geometry.kdtree import KDTreeConfig
from ne_jax.render.quadrature import QuadratureConfig
from ne_jax.render.renderer import PointScene, RenderConfig, render_rays
from ne_jax.render.shading import init_color_model

# tests/mini_presets.tiny_render at depth 8, spelled out: this file also runs as a script in a subprocess
CFG = RenderConfig(kdtree=KDTreeConfig(depth=8, candidate_min=16, knn_k=8, num_render_levels=2),
                   quadrature=QuadratureConfig(samples_per_level=(4, 6, 8)), chunk=1024)
CAPS = Capacities(frontier=64, max_segments=48, segments_per_ray=None)
CAPACITY, N_POINTS, N_RAYS = 256, 200, 64


def _f32(a):
    return np.asarray(np.asarray(a, np.float32), np.float64)


def scene_inputs(seed: int = 0) -> dict:
    """Points on a bumpy sphere (radius ~1), 56 alive-slot padding, random features / confidences /
    normals, rays aimed at points (a few nearly axis-parallel, a few missing), random params."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(N_POINTS, 3))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    xyz = np.zeros((CAPACITY, 3))
    xyz[:N_POINTS] = x * (1 + 0.05 * rng.normal(size=(N_POINTS, 1)))
    tgt = xyz[rng.integers(N_POINTS, size=N_RAYS)] + 0.02 * rng.normal(size=(N_RAYS, 3))
    d = rng.normal(size=(N_RAYS, 3))
    d[:4] = [[1, 0, 0], [0, -1, 0], [0, 0, 1], [1, 1e-7, 0]]  # axis-parallel and nearly so
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    origin = tgt - 4 * d
    origin[-2:] = [[5, 5, 5], [-5, 0, 0]]  # missing everything: pointing away
    d[-2:] = [[1, 0, 0], [-1, 0, 0]]
    params = init_color_model(CFG.shading, jax.random.key(seed))
    leaves = jax.tree_util.tree_leaves(params)
    out = dict(
        xyz=_f32(xyz), feature=_f32(0.5 * rng.normal(size=(CAPACITY, 32))),
        conf_logit=_f32(rng.normal(1.0, 2.0, size=CAPACITY)), normal=_f32(rng.normal(size=(CAPACITY, 3))),
        origin=_f32(origin), direction=_f32(d), bg=np.array([1.0, 0.5, 0.25]),
    )
    out.update({f"param_{i}": _f32(p) for i, p in enumerate(leaves)})
    return out


def build(inputs: dict, dtype=None, scale: float = 1.0, alive=None, conf_logit=None):
    """``(params, scene, rays, background)`` in ``dtype`` (default: the process's float dtype), the
    scene and rays scaled by ``scale``."""
    dtype = dtype or jnp.zeros(()).dtype
    a = lambda v: jnp.asarray(np.asarray(v), dtype)  # noqa: E731
    structure = jax.tree_util.tree_structure(init_color_model(CFG.shading, jax.random.key(0)))
    n = structure.num_leaves
    params = jax.tree_util.tree_unflatten(structure, [a(inputs[f"param_{i}"]) for i in range(n)])
    alive = np.arange(CAPACITY) < N_POINTS if alive is None else alive
    pts = PointState.from_numpy(np.asarray(inputs["xyz"])[:N_POINTS] * scale, capacity=CAPACITY,
                                feature_dim=32, dtype=dtype)
    pts = pts.replace(feature=a(inputs["feature"]), normal=a(inputs["normal"]),
                      conf_logit=a(inputs["conf_logit"] if conf_logit is None else conf_logit))
    scene = PointScene.build(pts, CFG, CAPS)
    scene = scene.replace(points=scene.points.replace(alive=jnp.asarray(alive)))
    r = len(inputs["origin"])
    rays = Rays(origin=a(np.asarray(inputs["origin"]) * scale), direction=a(inputs["direction"]),
                near=jnp.zeros((r,), dtype), far=jnp.full((r,), 20.0 * scale, dtype))
    return params, scene, rays, a(inputs["bg"])


@functools.partial(jax.jit, static_argnums=0)
def render(cfg, params, scene, rays, bg):
    return render_rays(cfg, params, scene, rays, bg)


def render_arrays(inputs: dict) -> dict:
    out = render(CFG, *build(inputs))
    arrays = {k: np.asarray(v) for k, v in vars(out).items() if k != "lost"}
    arrays["lost"] = np.asarray(out.lost.count)  # segments and frontier nodes lost per ray
    return arrays


if __name__ == "__main__":
    with np.load(sys.argv[1]) as f:
        inp = dict(f)
    np.savez(sys.argv[2], **render_arrays(inp))

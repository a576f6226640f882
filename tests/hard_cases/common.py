"""Shared pieces of the hard-case suite: the active float dtype, tolerances keyed by it, cloud and
ray generators at fixed capacities (one compilation per jitted function for the whole suite), and
finiteness checks.

The suite runs twice in CI: in the default float32 process and again with ``JAX_ENABLE_X64=1``
(``bash run.sh test``); every input is created in :data:`DTYPE` so the second run exercises the
float64 path end to end.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import HealthCheck, settings

from ne_jax.data.rays import Rays
from ne_jax.geometry import PointState
from ne_jax.geometry.capacity import Capacities

from tests.mini_presets import tiny_tree

X64 = bool(jax.config.jax_enable_x64)
"""Whether this process runs with float64 enabled (``JAX_ENABLE_X64=1``)."""

DTYPE = np.dtype(np.float64 if X64 else np.float32)
"""The float dtype of every input the suite builds."""

EPS = float(np.finfo(DTYPE).eps)

# Tolerances against the float64 references, keyed by dtype. Each is stated where it is used too.
TOLERANCES = {
    np.dtype(np.float32): dict(
        slab=64 * float(np.finfo(np.float32).eps),  # relative to the ray's coordinate scale: ambiguity band
        t_rel=1e-5,  # segment end points / sample positions, relative to the coordinate scale
        weight=2e-6,  # KNN weights (in [0, 1]), absolute
        interp=2e-5,  # interpolated values, relative to max |value|
        quad=2e-6,  # quadrature means, relative to max |value|
        ide=2e-5,  # IDE columns, absolute (every column is O(1))
        comp_rtol=2e-5, comp_atol=2e-6,  # compositing outputs
        shade_scale=2e-5,  # shade(f, s*n, s*d) vs shade(f, n, d), absolute on rgb in [0, 1]
        render_scale=1e-5,  # render of a scene scaled by 1e-4 / 1e4 vs unscaled, absolute rgb
    ),
    np.dtype(np.float64): dict(
        slab=64 * float(np.finfo(np.float64).eps),
        t_rel=1e-12,
        weight=1e-12,
        interp=1e-11,
        quad=1e-13,
        ide=1e-11,
        comp_rtol=1e-11, comp_atol=1e-13,
        shade_scale=1e-12,
        render_scale=1e-9,
    ),
}
TOL = TOLERANCES[DTYPE]

# Hypothesis: few examples (each runs jitted code), no deadline (the first example compiles),
# derandomised so CI runs are repeatable.
HYP = settings(deadline=None, derandomize=True, print_blob=True,
               suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])

# One capacity / depth / config for every cloud of the suite: each jitted function compiles once.
CAPACITY = 256
CFG = tiny_tree(depth=8)
CAPS = Capacities(frontier=64, max_segments=48, segments_per_ray=None)

CLOUD_KINDS = ("uniform", "sphere", "coplanar", "collinear", "duplicates", "clusters", "grid")


def make_cloud(kind: str, n: int, seed: int, scale: float = 1.0, offset: float = 0.0,
               deleted: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """A ``CAPACITY``-slot cloud in :data:`DTYPE`: ``n`` points of ``kind`` scaled by ``scale``
    (about unit size before scaling) and shifted by ``offset * scale``; a fraction ``deleted`` of
    them dead (at least one stays alive); dead and padding slots hold garbage (finite, far away)."""
    rng = np.random.default_rng(seed)
    n = int(np.clip(n, 1, CAPACITY))
    if kind == "uniform":
        x = rng.uniform(-1, 1, (n, 3))
    elif kind == "sphere":
        x = rng.normal(size=(n, 3))
        x /= np.linalg.norm(x, axis=1, keepdims=True)
    elif kind == "coplanar":  # exactly z = 0, random in-plane frame on the axes
        x = np.concatenate([rng.uniform(-1, 1, (n, 2)), np.zeros((n, 1))], 1)[:, rng.permutation(3)]
    elif kind == "collinear":  # on an axis-parallel line (exact) or a diagonal one
        t = rng.uniform(-1, 1, n)
        x = np.stack([t, 0.5 * t, -t], 1) if seed % 2 else np.stack([t, np.zeros(n), np.zeros(n)], 1)
    elif kind == "duplicates":  # few distinct positions, each repeated
        base = rng.uniform(-1, 1, (max(1, n // 6), 3))
        x = base[rng.integers(len(base), size=n)]
    elif kind == "clusters":  # tight clusters far apart (spacing << extent)
        c = rng.uniform(-1, 1, (3, 3))
        x = c[rng.integers(3, size=n)] + 1e-3 * rng.normal(size=(n, 3))
    elif kind == "grid":  # regular grid: ties everywhere in distances and medians
        k = int(np.ceil(n ** (1 / 3)))
        g = np.stack(np.meshgrid(*[np.arange(k)] * 3, indexing="ij"), -1).reshape(-1, 3)[:n]
        x = g / max(k - 1, 1) * 2 - 1
    else:
        raise ValueError(kind)
    x = ((x + offset) * scale).astype(DTYPE)
    xyz = np.full((CAPACITY, 3), 1e3 * scale, DTYPE)  # garbage in dead slots: never read
    xyz[:n] = x
    alive = np.zeros(CAPACITY, bool)
    alive[:n] = True
    if deleted > 0 and n > 1:
        kill = rng.random(n) < deleted
        kill[rng.integers(n)] = False
        alive[:n] &= ~kill
    return xyz, alive


def make_state(xyz, alive, seed=0, feature_dim=4, conf_logit=None) -> PointState:
    """A :class:`PointState` in :data:`DTYPE` with random features, normals, IST and confidences."""
    rng = np.random.default_rng(seed)
    c = len(xyz)
    st = PointState.from_numpy(np.where(alive[:, None], xyz, 0), capacity=c, feature_dim=feature_dim,
                               dtype=DTYPE)
    if conf_logit is None:
        conf_logit = rng.normal(scale=2.0, size=c)
    ist = np.eye(3)[None] + 0.2 * rng.normal(size=(c, 3, 3))
    return st.replace(
        xyz=jnp.asarray(xyz, DTYPE),
        alive=jnp.asarray(alive),
        feature=jnp.asarray(rng.normal(size=(c, feature_dim)), DTYPE),
        conf_logit=jnp.asarray(conf_logit, DTYPE),
        normal=jnp.asarray(rng.normal(size=(c, 3)), DTYPE),
        ist=jnp.asarray(ist, DTYPE),
    )


def make_rays(origin, direction, near=0.0, far=None, num=None) -> Rays:
    """Rays in :data:`DTYPE`, padded (repeating the last ray) to ``num`` rays for a fixed shape."""
    o = np.asarray(origin, np.float64).reshape(-1, 3)
    d = np.asarray(direction, np.float64).reshape(-1, 3)
    if num is not None:
        assert len(o) <= num, (len(o), num)
        pad = num - len(o)
        o = np.concatenate([o, np.repeat(o[-1:], pad, 0)])
        d = np.concatenate([d, np.repeat(d[-1:], pad, 0)])
    r = len(o)
    if far is None:
        far = 1e3 * (1.0 + np.abs(o).max())
    return Rays(origin=jnp.asarray(o, DTYPE), direction=jnp.asarray(d, DTYPE),
                near=jnp.full((r,), near, DTYPE), far=jnp.full((r,), far, DTYPE))


def aimed_rays(xyz, alive, rng, n, jitter):
    """``n`` rays from outside the cloud aimed at (jittered) alive points, unit directions."""
    pts = np.asarray(xyz, np.float64)[np.asarray(alive)]
    ext = float(np.abs(pts).max()) + 1e-30
    tgt = pts[rng.integers(len(pts), size=n)] + rng.normal(size=(n, 3)) * jitter
    v = rng.normal(size=(n, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return tgt - v * 4 * ext, v


def assert_finite(tree, what=""):
    """Every floating leaf of a pytree is finite."""
    for path, leaf in jax.tree_util.tree_leaves_with_path(tree):
        a = np.asarray(leaf)
        if np.issubdtype(a.dtype, np.floating):
            assert np.all(np.isfinite(a)), f"{what}{jax.tree_util.keystr(path)}: non-finite values"

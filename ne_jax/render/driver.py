"""The host driver of rendering: any number of rays, and images, in compiled fixed-size chunks.

:func:`render_chunked` walks every ray through the tree first and renders only the rays that meet a
voxel, in chunks of ``RenderConfig.chunk`` (the last padded) split over the devices; capacities
grow as soon as a chunk loses segments, and the chunks that lost are rendered again
(:func:`until_complete` is the same regrowth for any call). :func:`render_image` renders a camera's
pixels on the config's ray grid. The per-ray renderer is :mod:`ne_jax.render.renderer`.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import checkify
from jax.sharding import Mesh
from tqdm.auto import tqdm

from ne_jax.checks import throw
from ne_jax.data.rays import Camera, Rays, camera_rays
from ne_jax.devices import default_mesh, padded_size, shard_rays
from ne_jax.geometry.capacity import Lost
from ne_jax.geometry.intersect import intersect
from ne_jax.render.renderer import PointScene, RenderConfig, RenderOut, render_rays
from ne_jax.render.shading import background_color


@functools.partial(jax.jit, static_argnums=0, static_argnames="mesh")
def _render_chunk(cfg: RenderConfig, params, scene, rays, background, mesh: Mesh | None = None) -> RenderOut:
    """One chunk of rays split over ``mesh`` (default: :func:`~ne_jax.devices.default_mesh`; the
    chunk's size a multiple of the mesh's), the scene and ``params`` replicated."""
    mesh = default_mesh() if mesh is None else mesh
    bg = jnp.broadcast_to(jnp.asarray(background, rays.origin.dtype), (rays.num_rays, 3))
    return shard_rays(functools.partial(render_rays, cfg), mesh, num_replicated=2)(params, scene, rays, bg)


@functools.partial(jax.jit, static_argnums=0)
def _render_chunk_checked(cfg: RenderConfig, params, scene, rays, background):
    """:func:`_render_chunk` under ``checkify`` (``cfg.checks`` on): ``(error, RenderOut)``."""
    render = functools.partial(render_rays, cfg)
    return checkify.checkify(render, errors=checkify.user_checks)(params, scene, rays, background)


def _render_chunk_maybe_checked(cfg: RenderConfig, params, scene, rays, background, mesh: Mesh) -> RenderOut:
    """:func:`_render_chunk`; with ``cfg.checks`` the checked one (on one device), raising
    ``NonFiniteError``."""
    if not cfg.checks:
        return _render_chunk(cfg, params, scene, rays, background, mesh=mesh)
    err, out = _render_chunk_checked(cfg, params, scene, rays, background)
    throw(err)
    return out


SURVEY_CHUNKS = 4
"""Render chunks per call of :func:`render_chunked`'s first stage (the walk alone): with one segment
slot and no shading a call holds little memory, and fewer calls cost less to dispatch (measured in
``experiments/bench_view.py``)."""


def until_complete(scene: PointScene, call, lost_of, max_grow: int = 4):
    """``call(scene)``, and again with the scene's capacities grown (:meth:`PointScene.grown`) while
    ``lost_of(output)`` (a :class:`~ne_jax.geometry.capacity.Lost` or ``LostCounts``) says it lost
    something, at most ``max_grow`` times. Returns ``(output, scene)``: the last output and the scene
    with the capacities it was made with (keep it: the next call compiles no more)."""
    out = call(scene)
    for _ in range(max_grow):
        bigger = scene.grown(lost_of(out))
        if bigger is None:
            break
        scene = bigger
        out = call(scene)
    return out, scene


@functools.partial(jax.jit, static_argnums=0, static_argnames="mesh")
def _survey_chunk(cfg: RenderConfig, params, scene, rays, background, mesh: Mesh | None = None):
    """Which rays of a chunk have anything to render, and the colour behind every ray:
    ``(need [R] bool, color [R, 3])``. A ray needs rendering when the traversal found or lost a
    segment or a node (any capacity: a ray that finds nothing and loses nothing finds nothing with
    larger ones), or when its origin or direction is not finite (so the render's checks see it). One
    segment slot is enough to tell: a second segment counts as lost, and the walk's width is the
    scene's."""
    mesh = default_mesh() if mesh is None else mesh

    def survey(params, scene, rays, bg):
        seg = intersect(scene.tree, rays, cfg.kdtree, scene.capacities.replace(max_segments=1))
        finite = jnp.all(jnp.isfinite(rays.origin), -1) & jnp.all(jnp.isfinite(rays.direction), -1)
        need = (seg.num_emitted > 0) | (seg.lost().count > 0) | ~finite
        return need, background_color(cfg.shading, params, rays.origin, rays.direction, bg)

    return shard_rays(survey, mesh, num_replicated=2)(params, scene, rays, background)


def _in_chunks(rays: Rays, background: np.ndarray, index: np.ndarray, chunk: int) -> list[tuple[Rays, np.ndarray]]:
    """``(rays, background)`` pieces of ``chunk`` rays, the rays ``index`` picks from host arrays (a
    per-ray ``background [R, 3]``), the last piece padded with copies of its last ray. On the host:
    selections of other sizes compile nothing."""
    index = np.concatenate([index, np.repeat(index[-1:], (-index.size) % chunk)])
    return [(jax.tree_util.tree_map(lambda a, sel=index[s:s + chunk]: a[sel], rays), background[index[s:s + chunk]])
            for s in range(0, index.size, chunk)]


def render_chunked(cfg: RenderConfig, params: dict, scene: PointScene, rays: Rays, background,
                   progress: bool | None = None, desc: str = "render", max_grow: int = 8,
                   mesh: Mesh | None = None) -> RenderOut:
    """Render any number of rays in compiled chunks of ``cfg.chunk`` (the last one padded), each
    chunk split over the devices of ``mesh`` (default :func:`~ne_jax.devices.default_mesh`; the
    chunk is rounded up to a multiple of the mesh's size).

    In two stages: every ray is first walked through the tree alone (no packing, KNN or shading;
    :data:`SURVEY_CHUNKS` chunks per call), then only the rays that found a segment are rendered,
    gathered into full chunks; the others get the colour behind the scene. An image whose object
    covers a quarter of it costs a quarter of the KNN and shading work. (With ``cfg.checks`` every
    ray is rendered, so the checks see them all; rays that fit one chunk are rendered at once.)
    The result equals one :func:`render_rays` call over every ray.

    Capacities grow (:meth:`PointScene.grown`, at most ``max_grow`` times) as soon as a chunk is
    seen to lose something, so later chunks render with them, and the chunks that lost are rendered
    again with the grown ones; what is still lost after that is reported in the output's ``lost``.
    ``progress``: show a progress bar (default: when more than 8 chunks are rendered). Deterministic
    rules only (the stochastic rule is a training-time ablation: use :func:`render_rays`)."""
    if cfg.quadrature.rule == "stochastic":
        raise ValueError("render_chunked renders deterministically; the 'stochastic' rule needs render_rays with a key")
    n = rays.num_rays
    mesh = default_mesh() if mesh is None else mesh
    chunk = padded_size(cfg.chunk, mesh)
    rays = jax.device_get(rays)
    background = np.broadcast_to(np.asarray(background, rays.origin.dtype), (n, 3))
    if cfg.checks or n <= chunk:  # the checks see every ray; one chunk holds them all anyway
        todo, color = np.arange(n), None
    else:
        walk = SURVEY_CHUNKS * chunk
        surveyed = jax.device_get([_survey_chunk(cfg, params, scene, r, bg, mesh=mesh)
                                   for r, bg in _in_chunks(rays, background, np.arange(n), walk)])
        need, color = (np.concatenate(xs)[:n] for xs in zip(*surveyed))
        todo = np.flatnonzero(need)
    if todo.size == 0:
        return jax.tree_util.tree_map(jnp.asarray, _background_out(background if color is None else color))
    pieces = _in_chunks(rays, background, todo, chunk)
    if progress is None:
        progress = len(pieces) > 8
    render = lambda s, r, bg: _render_chunk_maybe_checked(cfg, params, s, r, bg, mesh)  # noqa: E731
    outs, used, counts, grows = [], [], [], 0

    def settle(j: int) -> None:  # read chunk j's losses; grow if it lost with the current capacities
        nonlocal scene, grows
        counts[j] = outs[j].lost.counts()
        bigger = scene.grown(counts[j]) if used[j] == scene.capacities and grows < max_grow else None
        if bigger is not None:
            scene, grows = bigger, grows + 1

    for i, (r, bg) in enumerate(tqdm(pieces, desc=desc, unit="chunk", disable=not progress, leave=False)):
        outs.append(render(scene, r, bg))
        used.append(scene.capacities)
        counts.append(None)
        if i:  # one chunk in flight while the one before is read back
            settle(i - 1)
    settle(len(pieces) - 1)
    # the chunks that lost with smaller capacities than the scene's now, again (which may grow them more)
    while redo := [i for i, c in enumerate(counts) if c.total and used[i] != scene.capacities]:
        for i in redo:
            outs[i], used[i] = render(scene, *pieces[i]), scene.capacities
            settle(i)
    hits = jax.tree_util.tree_map(lambda *xs: np.concatenate(xs)[:todo.size], *jax.device_get(outs))
    if todo.size < n:
        full = _background_out(color)
        for a, part in zip(jax.tree_util.tree_leaves(full), jax.tree_util.tree_leaves(hits)):
            a[todo] = part
        hits = full
    return jax.tree_util.tree_map(jnp.asarray, hits)


def _background_out(color: np.ndarray) -> RenderOut:
    """What rays that meet nothing render (host arrays): ``color [R, 3]``; opacity, depth, normal
    and every count zero."""
    r = color.shape[0]
    zero = lambda *shape, dtype=color.dtype: np.zeros((r, *shape), dtype)  # noqa: E731
    i32 = functools.partial(zero, dtype=np.int32)
    return RenderOut(rgb=np.array(color), opacity=zero(), depth=zero(), normal=zero(3), num_segments=i32(),
                     lost=Lost(frontier=i32(), slots=i32(), packing=i32(), emitted=i32()))


def render_image(cfg: RenderConfig, params: dict, scene: PointScene, camera: Camera, background,
                 near: float, far: float, progress: bool | None = None, mesh: Mesh | None = None) -> RenderOut:
    """Render every pixel of ``camera`` (rays split over ``mesh``, see :func:`render_chunked`);
    fields are reshaped to images (``rgb`` ``[H, W, 3]``). With ``cfg.pixel_samples = n > 1`` each
    pixel renders ``n x n`` rays: its ``rgb``, ``opacity``, ``depth`` and ``normal`` are their means,
    ``num_segments`` their sum, and ``lost`` stays per ray (``[H, W, n * n]``)."""
    n = cfg.pixel_samples ** 2
    rays = camera_rays(camera, near, far, cfg.pixel_samples)
    # The rays render alike at any grid: one compiled chunk serves every pixel_samples.
    out = render_chunked(cfg.replace(pixel_samples=1), params, scene, rays, background, progress, desc="render image",
                         mesh=mesh)
    h, w = camera.height, camera.width
    if n == 1:  # one ray a pixel: the rays are the image
        return jax.tree_util.tree_map(lambda a: a.reshape((h, w) + a.shape[1:]), out)
    pixels = lambda a, reduce: reduce(a.reshape((h, w, n) + a.shape[1:]), axis=2)  # noqa: E731
    means = {f: pixels(getattr(out, f), jnp.mean) for f in ("rgb", "opacity", "depth", "normal")}
    return out.replace(**means, num_segments=pixels(out.num_segments, jnp.sum),
                       lost=jax.tree_util.tree_map(lambda a: a.reshape(h, w, n), out.lost))

"""Stage 2, traversal (``intersect``, jitted): random clouds (degenerate, 1e-4 .. 1e4, deleted
points) and hard rays — axis-parallel rays with signed-zero components lying exactly in box face
planes and one ulp either side of them, along box edges, nearly parallel rays (tiny and subnormal
direction components), rays grazing a face at 1e-6 rad, rays starting inside boxes, rays missing
everything — against the float64 recursive reference ``tests/geometry/reference.minimal_voxels``.

Subnormal coordinates count as 0 (XLA:CPU flushes them), like direction components below
``sqrt(tiny)`` (``intersect``'s documented parallel rule).

Tolerances (``common.TOL``): a ray is compared only if the reference's smallest ``|slack|`` over
every box it tested exceeds ``TOL["slab"] * scale`` (``scale`` = the largest coordinate involved;
float32 64 eps, float64 64 eps): closer to a decision boundary, rounding may legitimately decide
either way. Compared rays must emit the same (node, level) list, with end points within
``TOL["t_rel"] * scale``; rays that overflow the fixed capacities (rays along a collinear cloud
cross more than ``max_segments`` voxels) must report it and emit a subset of the reference. At
most a quarter of the rays of one example may be ambiguous. Outputs and the gradients with respect
to origins and directions are finite for every ray. The two-pass walk (``first_pass_frontier``)
gives the one-pass segments bit for bit on the same cases.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from ne_jax.geometry import build_tree, intersect
from ne_jax.geometry.kdtree import MIN_HIT_FACTOR

from geometry.reference import minimal_voxels

from .common import CAPS, CFG, CLOUD_KINDS, DTYPE, HYP, TOL, aimed_rays, assert_finite, make_cloud, make_rays

NUM_RAYS = 96


def hard_rays(tree, xyz, alive, rng):
    """``(origin, direction)`` float64 arrays of the hard cases described in the module docstring."""
    lo, hi = np.asarray(tree.lo, np.float64), np.asarray(tree.hi, np.float64)
    valid = np.asarray(tree.valid)
    r0 = 2 ** (tree.depth - 1) - 1
    boxes = np.flatnonzero(valid[r0 : 2**tree.depth - 1]) + r0
    pts = np.asarray(xyz, np.float64)[alive]
    ext = float(np.abs(pts).max()) + float(tree.spacing) * 4
    o, d = [], []
    for g in rng.choice(boxes, min(3, len(boxes)), replace=False) if len(boxes) else []:
        c = 0.5 * (lo[g] + hi[g])
        a = int(rng.integers(3))
        b, e = (a + 1) % 3, (a + 2) % 3
        v = np.zeros(3)
        v[a] = rng.choice([-1.0, 1.0])
        v[b] = -0.0 if rng.random() < 0.5 else 0.0
        face = lo[g][b] if rng.random() < 0.5 else hi[g][b]
        for pb in (face, np.nextafter(DTYPE.type(face), DTYPE.type(np.inf)),
                   np.nextafter(DTYPE.type(face), DTYPE.type(-np.inf))):
            for pe in (c[e], lo[g][e]):  # face plane / edge
                p = c - v * 3 * ext
                p[b], p[e] = pb, pe
                o.append(p)
                d.append(v.copy())
        # nearly parallel: tiny / subnormal component on the parallel axis
        for tiny in (1e-30, float(np.finfo(DTYPE).tiny) / 4):
            w = v.copy()
            w[b] = tiny
            p = c - v * 3 * ext
            o.append(p)
            d.append(w)
        # grazing a face at 1e-6 rad, crossing its plane at the box centre
        w = v.copy()
        w[b] = 1e-6
        w /= np.linalg.norm(w)
        p = c.copy()
        p[b] = face
        o.append(p - w * 3 * ext)
        d.append(w)
        u = rng.normal(size=3)  # from inside the box
        o.append(c)
        d.append(u / np.linalg.norm(u))
    center = pts.mean(0)
    o.append(center + np.array([0.0, 0.0, 3 * ext]))  # pointing away: misses everything
    d.append(np.array([0.0, -0.0, 1.0]))
    k = NUM_RAYS - len(o)
    ao, ad = aimed_rays(xyz, alive, rng, k, float(tree.spacing))
    return np.concatenate([np.asarray(o), ao]), np.concatenate([np.asarray(d), ad])


def compare_to_reference(tree, rays, seg, cfg):
    tiny = np.finfo(DTYPE).tiny
    o = np.asarray(rays.origin, np.float64)
    o = np.where(np.abs(o) < tiny, 0.0, o)  # XLA:CPU flushes subnormals to zero (FTZ/DAZ)
    d = np.asarray(rays.direction, np.float64)
    d = np.where(np.abs(d) < np.sqrt(np.finfo(DTYPE).tiny), 0.0, d)  # documented: below sqrt(tiny) = parallel
    near, far = np.asarray(rays.near, np.float64), np.asarray(rays.far, np.float64)
    min_len = MIN_HIT_FACTOR * float(tree.spacing)
    first = tree.depth - cfg.num_render_levels
    valid = np.asarray(seg.valid)
    nodes, levels = np.asarray(seg.node), np.asarray(seg.level)
    t_lo, t_hi = np.asarray(seg.t_lo, np.float64), np.asarray(seg.t_hi, np.float64)
    f_over, s_over = np.asarray(seg.frontier_overflow), np.asarray(seg.segment_overflow)
    emitted = np.asarray(seg.num_emitted)
    box = max(np.abs(np.asarray(tree.lo)).max(), np.abs(np.asarray(tree.hi)).max())
    ambiguous = 0
    for r in range(len(o)):
        m = valid[r]
        assert np.all(m[: m.sum()]) and not np.any(m[m.sum():]), r  # valid slots first
        assert np.all(np.diff(t_lo[r][m]) >= 0) and np.all(t_hi[r][m] >= t_lo[r][m]), r
        ref, slack = minimal_voxels(tree, o[r], d[r], near[r], far[r], min_len, first)
        scale = np.abs(o[r]).max() + box
        if slack < TOL["slab"] * scale:
            ambiguous += 1
            continue
        # sorted by node: segments with equal entry distances may come in either order
        got = sorted(zip(nodes[r][m].tolist(), levels[r][m].tolist(), t_lo[r][m], t_hi[r][m]))
        want = sorted(ref)
        if f_over[r] or s_over[r]:  # lost segments are counted, never silent, never invented
            assert set(g[:2] for g in got) <= set(w[:2] for w in want), r
            assert len(got) < len(want) or f_over[r], r
            if not f_over[r]:
                assert emitted[r] == len(want), r
            continue
        assert [g[:2] for g in got] == [w[:2] for w in want], f"ray {r}: {got} != {want}"
        if want:
            np.testing.assert_allclose([g[2:] for g in got], [w[2:] for w in want], rtol=0,
                                       atol=TOL["t_rel"] * scale)
    # Boxes below the coordinates' resolution (one point or one position: the absolute
    # fallback_spacing, 1e-2, at 1e4) leave every ray ambiguous; otherwise few may be.
    if float(tree.spacing) > 1e3 * np.finfo(DTYPE).eps * box:
        assert ambiguous <= len(o) // 4, f"{ambiguous} of {len(o)} rays ambiguous"
    return len(o) - ambiguous


def _grad_loss(tree, rays, caps=CAPS):
    def loss(origin, direction):
        seg = intersect(tree, rays.replace(origin=origin, direction=direction), CFG, caps)
        return jnp.sum(jnp.where(seg.valid, seg.t_hi - seg.t_lo + 0.1 * seg.t_lo, 0.0))

    return jax.grad(loss, argnums=(0, 1))(rays.origin, rays.direction)


@HYP.__class__(HYP, max_examples=12)
@given(st.sampled_from(CLOUD_KINDS), st.integers(1, 256), st.integers(0, 2**16),
       st.sampled_from([1e-4, 1.0, 1e4]), st.sampled_from([0.0, 0.3]))
def test_matches_reference_on_hard_rays(kind, n, seed, scale, deleted):
    xyz, alive = make_cloud(kind, n, seed, scale=scale, deleted=deleted)
    tree = build_tree(xyz, alive, CFG)
    o, d = hard_rays(tree, xyz, alive, np.random.default_rng(seed))
    rays = make_rays(o, d, num=NUM_RAYS)
    seg = intersect(tree, rays, CFG, CAPS)
    assert seg.t_lo.dtype == DTYPE
    assert_finite(seg)
    compare_to_reference(tree, rays, seg, CFG)
    assert_finite(_grad_loss(tree, rays), "grad ")


@HYP.__class__(HYP, max_examples=6)
@given(st.sampled_from(CLOUD_KINDS), st.integers(1, 256), st.integers(0, 2**16), st.sampled_from([1e-4, 1.0, 1e4]))
def test_two_pass_walk_equals_one_pass_on_hard_rays(kind, n, seed, scale):
    """``first_pass_frontier``: the narrow walk plus the full-width retries give the one-pass
    segments bit for bit (every ray may retry), with finite gradients."""
    xyz, alive = make_cloud(kind, n, seed, scale=scale)
    tree = build_tree(xyz, alive, CFG)
    rays = make_rays(*hard_rays(tree, xyz, alive, np.random.default_rng(seed)), num=NUM_RAYS)
    two_pass = CAPS.replace(first_pass_frontier=2, retry_share=1.0)
    one, two = intersect(tree, rays, CFG, CAPS), intersect(tree, rays, CFG, two_pass)
    for f in ("t_lo", "t_hi", "node", "level", "valid", "frontier_overflow", "segment_overflow", "num_emitted"):
        np.testing.assert_array_equal(np.asarray(getattr(two, f)), np.asarray(getattr(one, f)), err_msg=f)
    assert_finite(_grad_loss(tree, rays, two_pass), "grad ")


def test_face_plane_rays_see_the_box_and_one_ulp_outside_does_not():
    """A ray in a box's face plane is inside (closed slab), one ulp outside the plane it is not —
    unless the neighbour box shares that face; checked against the reference exactly (no tolerance:
    parallel axes are exact comparisons)."""
    xyz, alive = make_cloud("uniform", 200, seed=1)
    tree = build_tree(xyz, alive, CFG)
    o, d = hard_rays(tree, xyz, alive, np.random.default_rng(1))
    rays = make_rays(o, d, num=NUM_RAYS)
    seg = intersect(tree, rays, CFG, CAPS)
    assert compare_to_reference(tree, rays, seg, CFG) >= NUM_RAYS - NUM_RAYS // 4
    # the face-plane rays (the first of each group of six) hit something
    assert bool(np.asarray(seg.valid)[0].any())

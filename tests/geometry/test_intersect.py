"""intersect: the same minimal voxels as the float64 recursive reference on the issue's hard rays
and degenerate clouds; overflow is counted and the host helper re-allocates; scale equivariance;
finite gradients; no recompilation.

Every tree here has depth 10 and 1024 point slots and every batch :data:`NUM_RAYS` rays, so the
tests share a few compiled traversals (one per set of capacities)."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ne_jax.geometry import Capacities, KDTreeConfig, build_tree, grow, intersect, intersect_checked, slab_intersect
from ne_jax.geometry.kdtree import MIN_HIT_FACTOR
from ne_jax.numerics import safe_reciprocal, tiny

from tests.mini_presets import tiny_caps, tiny_tree

from .clouds import CLOUDS, hard_rays, make_rays, padded, sphere
from .reference import minimal_voxels, slab64

CFG = tiny_tree(depth=10)
CAPS = tiny_caps()
WIDE = Capacities(frontier=64, max_segments=32)
TWO_PASS = WIDE.replace(first_pass_frontier=2, retry_share=1.0)
NUM_RAYS = 170
"""Rays per batch: the hard rays of four boxes (:func:`hard_case`)."""


def walk(tree, rays, cfg, caps):
    """:func:`intersect` called as :func:`intersect_checked` calls it (``include_grow_level`` given),
    so the two share a compiled program."""
    return intersect(tree, rays, cfg, caps, False)


def compare(tree, rays, seg, cfg, include_grow=False, max_ambiguous=0.05):
    """Assert segments equal the reference for every unambiguous ray; returns #rays compared."""
    o = np.asarray(rays.origin, np.float64)
    d = np.asarray(rays.direction, np.float64)
    near = np.asarray(rays.near, np.float64)
    far = np.asarray(rays.far, np.float64)
    min_len = MIN_HIT_FACTOR * float(tree.spacing)
    first = tree.depth - cfg.num_render_levels - (1 if include_grow else 0)
    assert int(jnp.max(seg.overflow)) == 0
    valid = np.asarray(seg.valid)
    nodes, levels = np.asarray(seg.node), np.asarray(seg.level)
    t_lo, t_hi = np.asarray(seg.t_lo, np.float64), np.asarray(seg.t_hi, np.float64)
    skipped = 0
    for r in range(o.shape[0]):
        ref, slack = minimal_voxels(tree, o[r], d[r], near[r], far[r], min_len, first)
        scale = 1.0 + np.abs(o[r]).max() + np.abs(np.asarray(tree.hi)).max()
        tol = 1e-5 * scale
        m = valid[r]
        # valid slots first and sorted by entry distance
        assert np.all(m[: m.sum()]) and not np.any(m[m.sum() :])
        assert np.all(np.diff(t_lo[r][m]) >= 0)
        if slack < tol:
            skipped += 1
            continue
        got = sorted(zip(nodes[r][m].tolist(), levels[r][m].tolist(), t_lo[r][m], t_hi[r][m]))
        want = sorted(ref)
        assert [g[:2] for g in got] == [w[:2] for w in want], f"ray {r}: {got} != {want}"
        if got:
            np.testing.assert_allclose([g[2:] for g in got], [w[2:] for w in want], rtol=1e-5, atol=tol)
    assert skipped <= max_ambiguous * o.shape[0] + 1, f"{skipped} of {o.shape[0]} rays ambiguous"
    return o.shape[0] - skipped


def hard_case(name, seed=0):
    """``(tree, rays, cfg)``: the padded cloud ``name``'s tree and its hard rays of four boxes, at one
    depth for every cloud; a cloud with fewer boxes gets more random rays, up to :data:`NUM_RAYS`
    (one compilation per set of capacities serves every cloud)."""
    xyz, alive = padded(name)
    tree = build_tree(xyz, alive, CFG)
    o, d = hard_rays(tree, xyz, alive, seed=seed, n_boxes=4)
    if len(o) < NUM_RAYS:
        o, d = hard_rays(tree, xyz, alive, seed=seed, n_boxes=4, n_random=24 + NUM_RAYS - len(o))
    assert len(o) == NUM_RAYS, len(o)
    return tree, make_rays(o, d), CFG


@pytest.mark.parametrize("name", sorted(CLOUDS))
def test_matches_reference_on_hard_rays(name):
    tree, rays, cfg = hard_case(name)
    seg, cap = intersect_checked(tree, rays, cfg, WIDE)
    compare(tree, rays, seg, cfg)
    assert int(jnp.sum(seg.num_segments)) > 0
    seg_g, _ = intersect_checked(tree, rays, cfg, cap, include_grow_level=True)
    compare(tree, rays, seg_g, cfg, include_grow=True)


def test_axis_parallel_zero_signs_agree():
    """Four copies of a ray in a box's face plane, with every sign of zero in its direction (tiled
    to a full batch): the same segments."""
    xyz, alive = padded("sphere_700")
    tree = build_tree(xyz, alive, CFG)
    g = 2 ** (tree.depth - 1) - 1 + int(np.flatnonzero(np.asarray(tree.valid)[2 ** (tree.depth - 1) - 1 :])[0])
    c = 0.5 * (np.asarray(tree.lo[g]) + np.asarray(tree.hi[g]))
    lo = np.asarray(tree.lo[g])
    o = np.stack([np.array([c[0], lo[1], c[2]], np.float32) - np.array([5, 0, 0], np.float32)] * 4)
    d = np.array([[1, 0.0, 0.0], [1, -0.0, 0.0], [1, 0.0, -0.0], [1, -0.0, -0.0]], np.float32)
    assert np.signbit(d[1, 1]) and np.signbit(d[3, 2])
    seg = walk(tree, make_rays(np.resize(o, (NUM_RAYS, 3)), np.resize(d, (NUM_RAYS, 3))), CFG, CAPS)
    for f in ("node", "t_lo", "t_hi", "valid"):
        a = np.asarray(getattr(seg, f))
        assert np.all(a == a[0]), f
    assert bool(np.asarray(seg.valid)[0].any())  # the face-plane ray sees the box
    assert g in np.asarray(seg.node)[0][np.asarray(seg.valid)[0]]


def test_slab_exact_cases():
    lo = jnp.zeros(3)
    hi = jnp.ones(3)
    big = 1e3

    def run(o, d, min_len=0.0):
        d = jnp.asarray(d, jnp.float32)
        return slab_intersect(lo, hi, jnp.asarray(o, jnp.float32), safe_reciprocal(d), jnp.abs(d) < tiny(jnp.float32),
                              0.0, big, min_len)

    # parallel, inside the slab (on the face plane): hit over the full extent along x
    t0, t1, h = run([-1.0, 0.0, 0.5], [1.0, -0.0, 0.0])
    assert bool(h) and float(t0) == 1.0 and float(t1) == 2.0
    # parallel, just outside
    assert not bool(run([-1.0, -1e-7, 0.5], [1.0, 0.0, 0.0])[2])
    # through an edge (zero length): miss with min_len > 0, "hit" of length 0 never counts
    v = np.array([1.0, 1.0, 0.0]) / np.sqrt(2)
    t0, t1, h = run([-1.0, 0.0 + 0.0, 0.5] , [v[0], -v[1], 0.0], 1e-6)  # leaves through the edge y=0
    assert not bool(h)
    # corner: (1,1,1) direction through (0,0,0) from outside touching only the corner
    w = np.array([1.0, -1.0, 1.0]) / np.sqrt(3)
    assert not bool(run(-w * 2, w, 1e-6)[2])
    # starting inside: t_lo = near = 0
    t0, t1, h = run([0.5, 0.5, 0.5], [0.0, 0.0, -1.0])
    assert bool(h) and float(t0) == 0.0 and float(t1) == pytest.approx(0.5)
    # direction components of every sign of zero, and denormals, never give NaN
    for dd in ([0.0, 0.0, 1.0], [-0.0, -0.0, 1.0], [1e-45, -1e-45, 1.0], [1e-30, 0.0, -1.0]):
        out = run([0.0, 1.0, 2.0], dd)
        assert all(np.isfinite(float(x)) or not bool(out[2]) for x in out[:2])
        ref = slab64(np.zeros(3), np.ones(3), [0.0, 1.0, 2.0], np.float32(dd), 0.0, big, 0.0)
        assert bool(out[2]) == ref[2]


@pytest.mark.parametrize("factor, exact", [(1024.0, True), (1 / 1024.0, True), (1e3, False), (1e-3, False)])
def test_scale_equivariance(factor, exact):
    xyz, alive = padded("sphere_700")
    tree = build_tree(xyz, alive, CFG)
    o, d = hard_rays(tree, xyz, alive, seed=4, n_boxes=4)
    if not exact:
        # Rays placed exactly on box faces / edges of the unscaled tree are not on them after an
        # inexact scaling: compare the generic rays (aimed at points).
        o, d = hard_rays(tree, xyz, alive, seed=4, n_boxes=4, n_random=NUM_RAYS)
        o, d = o[-NUM_RAYS:], d[-NUM_RAYS:]
    xs = (xyz.astype(np.float64) * factor).astype(np.float32)
    tree_s = build_tree(xs, alive, CFG)
    far = 1e3
    seg = walk(tree, make_rays(o, d, far=far), CFG, CAPS)
    seg_s = walk(tree_s, make_rays(o.astype(np.float64) * factor, d, far=far * factor), CFG, CAPS)
    assert int(jnp.max(seg.overflow)) == 0 and int(jnp.max(seg_s.overflow)) == 0
    same = np.all((np.asarray(seg.node) == np.asarray(seg_s.node)) & (np.asarray(seg.valid) == np.asarray(seg_s.valid)),
                  axis=1)
    if exact:  # powers of two: every float operation commutes with the scaling
        assert same.all()
        np.testing.assert_array_equal(np.asarray(seg.t_lo) * factor, np.asarray(seg_s.t_lo))
    else:
        assert same.mean() > 0.95, same.mean()
        m = np.asarray(seg.valid)[same]
        np.testing.assert_allclose(np.asarray(seg_s.t_lo)[same][m] / factor, np.asarray(seg.t_lo)[same][m],
                                   rtol=1e-4, atol=1e-4)


def test_overflow_counted_and_retry_reallocates():
    """8 frontier nodes and 4 segment slots lose nodes and segments on the sphere's hard rays; one
    growth step holds them all."""
    tree, rays, cfg = hard_case("sphere_700")
    small = Capacities(frontier=8, max_segments=4)
    seg = walk(tree, rays, cfg, small)
    assert int(jnp.max(seg.frontier_overflow)) > 0 and int(jnp.max(seg.segment_overflow)) > 0
    # never silent: every ray whose reference list is longer than what came back reports overflow
    full, cap = intersect_checked(tree, rays, cfg, small)
    assert cap.frontier > small.frontier and cap.max_segments > small.max_segments
    lost = np.asarray(full.num_segments) > np.asarray(seg.num_segments)
    assert np.all(np.asarray(seg.overflow)[lost] > 0)
    np.testing.assert_array_equal(np.asarray(seg.lost().count), np.asarray(seg.overflow))
    compare(tree, rays, full, cfg)


SEG_FIELDS = ("t_lo", "t_hi", "node", "level", "valid", "frontier_overflow", "segment_overflow", "num_emitted")


@pytest.mark.parametrize("name", ["sphere_700", "coplanar", "random_300"])
def test_two_pass_equals_one_wide_pass(name):
    tree, rays, cfg = hard_case(name)
    one = walk(tree, rays, cfg, WIDE)
    assert int(jnp.max(one.frontier_overflow)) == 0
    narrow = walk(tree, rays, cfg, WIDE.replace(frontier=2))
    assert int(jnp.sum(narrow.frontier_overflow > 0)) > 0  # the second pass has rays to walk again
    two = walk(tree, rays, cfg, TWO_PASS)
    for f in SEG_FIELDS:
        np.testing.assert_array_equal(np.asarray(getattr(two, f)), np.asarray(getattr(one, f)), err_msg=f)


def test_two_pass_beyond_the_retry_share_is_counted():
    """Half the rays may be walked again, more than half overflow the narrow pass: the first ones
    get the wide pass's segments, the rest keep the narrow pass's and count their loss; growth then
    retries every ray."""
    tree, rays, cfg = hard_case("sphere_700")
    one, narrow = walk(tree, rays, cfg, WIDE), walk(tree, rays, cfg, WIDE.replace(frontier=2))
    over = np.asarray(narrow.frontier_overflow) > 0
    cap = rays.num_rays // 2
    assert over.sum() > cap
    caps = TWO_PASS.replace(retry_share=cap / rays.num_rays)
    two = walk(tree, rays, cfg, caps)
    redone = np.flatnonzero(over)[:cap]  # the first overflowing rays are walked again
    kept = np.flatnonzero(over)[cap:]
    for f in SEG_FIELDS:
        got, a, b = (np.asarray(getattr(x, f)) for x in (two, one, narrow))
        np.testing.assert_array_equal(got[redone], a[redone], err_msg=f)
        np.testing.assert_array_equal(got[~over], a[~over], err_msg=f)
        np.testing.assert_array_equal(got[kept], b[kept], err_msg=f)
    assert np.all(np.asarray(two.frontier_overflow)[kept] > 0)  # never silent
    full, grown = intersect_checked(tree, rays, cfg, caps)  # growth retries more rays before it widens
    assert grown.first_pass_frontier == 2 and grown.frontier == 64 and grown.retry_share > caps.retry_share
    compare(tree, rays, full, cfg)
    all_retried = caps.replace(retry_share=1.0)
    assert grow(all_retried, two.lost()) == all_retried.replace(frontier=128)
    assert grow(WIDE, narrow.lost()) == WIDE.replace(frontier=128)


@functools.partial(jax.jit, static_argnames="caps")
@jax.grad
def _grad_wrt_origin(origin, tree, rays, caps):
    """Gradient of a sum of segment lengths and entry distances with respect to the rays' origins."""
    seg = intersect(tree, rays.replace(origin=origin), CFG, caps)
    return jnp.sum(jnp.where(seg.valid, seg.t_hi - seg.t_lo + 0.1 * seg.t_lo, 0.0))


def test_grad_wrt_origin_finite():
    for name, caps in (("sphere_700", CAPS), ("identical", CAPS), ("coplanar", CAPS), ("one_point", CAPS),
                       ("sphere_700", TWO_PASS), ("coplanar", TWO_PASS)):
        tree, rays, _ = hard_case(name)
        g = _grad_wrt_origin(rays.origin, tree, rays, caps)
        assert np.all(np.isfinite(np.asarray(g))), name
        assert float(jnp.abs(g).sum()) > 0 or name == "one_point"


@pytest.mark.parametrize("caps", [CAPS, TWO_PASS], ids=["one_pass", "two_pass"])
def test_no_recompilation_for_same_capacities(caps):
    cfg = CFG
    xyz = sphere(1024, seed=7)
    t1 = build_tree(xyz, np.arange(1024) < 900, cfg)
    t2 = build_tree(xyz * 1.5, np.arange(1024) >= 50, cfg)
    o, d = hard_rays(t1, xyz, np.ones(1024, bool), n_boxes=4)
    r1 = make_rays(o, d)
    r2 = make_rays(o + 0.01, d[::-1])
    walk(t1, r1, cfg, caps).t_lo.block_until_ready()
    size = intersect._cache_size()
    for tree, rays in ((t1, r2), (t2, r1), (t2, r2)):
        walk(tree, rays, cfg, caps).t_lo.block_until_ready()
    assert intersect._cache_size() == size


def test_bad_rays_raise():
    tree = build_tree(sphere(50), np.ones(50, bool), CFG)
    rays = make_rays(np.zeros((3, 3)), np.ones((3, 3)))
    with pytest.raises(ValueError, match=r"rays.near: expected shape \[R=3\], found shape \(2,\)"):
        intersect(tree, rays.replace(near=jnp.zeros(2)), CFG)
    with pytest.raises(ValueError, match=r"cfg.num_render_levels: expected the tree's value 2, found 4"):
        intersect(tree, rays, KDTreeConfig())

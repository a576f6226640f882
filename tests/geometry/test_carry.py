"""carry_tree: a tree carried through a rigid motion cuts the moved rays exactly where the original
tree cut the original rays (hard rays included); deletions shrink and empty nodes; smooth
deformations keep every point within the fit's residual of its boxes and every box inside its
parent; torn subtrees are rebuilt locally; bad input is named; gradients stay finite; repeated calls
do not recompile; a held carry context carries as one made on the spot, and another cloud's is refused."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ne_jax.edit.deformations import bend_points, cut_points, rigid_motion
from ne_jax.geometry import build_tree, intersect
from ne_jax.geometry.carry import carry_context, carry_tree, carry_tree_with_report, held_points

from tests.mini_presets import tiny_tree

from .clouds import hard_rays, make_rays, sphere

CFG = tiny_tree()


@pytest.fixture(scope="module")
def cloud():
    x = sphere(1500, seed=4)
    x[:, 2] *= 0.6  # an ellipsoid: no symmetry that could hide a wrong frame
    return x, np.ones(len(x), bool), build_tree(x, np.ones(len(x), bool), CFG)


def _aimed_rays(x, seed=0, n=300):
    rng = np.random.default_rng(seed)
    o = rng.normal(size=(n, 3))
    o = 3.0 * o / np.linalg.norm(o, axis=1, keepdims=True)
    d = x[rng.integers(0, len(x), n)] + 0.1 * rng.normal(size=(n, 3)) - o
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


def _moved(o, d, m):
    rot, t = m[:3, :3], m[:3, 3]
    return (o @ rot.T + t).astype(np.float32), (d @ rot.T).astype(np.float32)


def assert_same_segments(a, b, atol):
    assert int(jnp.max(a.overflow)) == 0 and int(jnp.max(b.overflow)) == 0
    np.testing.assert_array_equal(np.asarray(a.valid), np.asarray(b.valid))
    np.testing.assert_array_equal(np.asarray(a.node), np.asarray(b.node))
    np.testing.assert_allclose(np.asarray(a.t_lo), np.asarray(b.t_lo), atol=atol)
    np.testing.assert_allclose(np.asarray(a.t_hi), np.asarray(b.t_hi), atol=atol)


@pytest.mark.parametrize("angle", [0.0, 3.0, 40.0, 90.0, 180.0])
def test_rigid_motion_cuts_moved_rays_where_the_original_tree_cut(cloud, angle):
    x, alive, tree = cloud
    m = rigid_motion((1.0, 2.0, -0.5), angle, pivot=(0.1, 0.0, 0.2), translation=(0.3, -0.2, 0.05))
    y = (x @ m[:3, :3].T + m[:3, 3]).astype(np.float32)
    carried, report = carry_tree_with_report(tree, x, y, alive, CFG)
    assert carried.has_frames and report["torn"] == 0 and report["max_residual"] < 1e-3
    o, d = _aimed_rays(x)
    before = intersect(tree, make_rays(o, d), CFG)
    after = intersect(carried, make_rays(*_moved(o, d, m)), CFG)
    assert int(jnp.sum(before.valid)) > 300
    assert_same_segments(before, after, atol=2e-5)
    # the candidate sets are the built ones, and the length unit is kept
    np.testing.assert_array_equal(np.asarray(carried.candidates), np.asarray(tree.candidates))
    assert float(carried.spacing) == float(tree.spacing)


def test_rigid_motion_hard_rays(cloud):
    """Axis-parallel rays, rays in face planes, along edges, at corners, from inside boxes: the
    moved ones give the same segments wherever the original ray is not on a decision boundary."""
    x, alive, tree = cloud
    m = rigid_motion((0.0, 0.0, 1.0), 90.0)  # maps axis-parallel rays to axis-parallel rays
    y = (x @ m[:3, :3].T + m[:3, 3]).astype(np.float32)
    carried = carry_tree(tree, x, y, alive, CFG)
    o, d = hard_rays(tree, x, alive, n_boxes=4)
    before = intersect(tree, make_rays(o, d), CFG)
    after = intersect(carried, make_rays(*_moved(o, d, m)), CFG)
    assert np.isfinite(np.asarray(after.t_lo)).all() and np.isfinite(np.asarray(after.t_hi)).all()

    def cut(seg):
        return np.where(np.asarray(seg.valid), np.asarray(seg.node), -1)

    # rays on a decision boundary (in a face plane, through an edge) may go either way after any
    # rounding: compare the rays whose cut survives nudging the origin by 1e-5 both ways
    stable = np.ones(len(o), bool)
    for eps in (1e-5, -1e-5):
        stable &= np.all(cut(intersect(tree, make_rays(o + eps, d), CFG)) == cut(before), axis=1)
    assert stable.sum() > 0.3 * len(o)
    same = np.all(cut(before) == cut(after), axis=1)
    assert same[stable].all(), f"{(~same[stable]).sum()} of {stable.sum()} stable hard rays cut differently"
    moved = make_rays(*_moved(o, d, m))
    grad = jax.grad(lambda o: jnp.sum(intersect(carried, moved.replace(origin=o), CFG).t_lo))(moved.origin)
    assert np.isfinite(np.asarray(grad)).all()


def _frame_positions(tree, y):
    """Each slot's edited position in the frame its boxes live in, ``[P, 3]`` (NaN for empty slots)."""
    perm = np.asarray(tree.perm)
    ok = perm < tree.capacity
    pos = np.where(ok[:, None], y[np.minimum(perm, tree.capacity - 1)], np.nan).astype(np.float64)
    if tree.has_frames:
        f = tree.frame_level
        span = 2 ** (tree.depth - f)
        rot = np.repeat(np.asarray(tree.frame_rot, np.float64), span, axis=0)
        sh = np.repeat(np.asarray(tree.frame_shift, np.float64), span, axis=0)
        pos = np.einsum("pab,pb->pa", rot, pos) + sh
    return pos, ok


def assert_points_inside_their_boxes(tree, y, alive, from_level, slack=1e-5):
    pos, ok = _frame_positions(tree, y)
    ok &= alive[np.minimum(np.asarray(tree.perm), tree.capacity - 1)]
    lo, hi = np.asarray(tree.lo, np.float64), np.asarray(tree.hi, np.float64)
    for level in range(from_level, tree.depth + 1):
        node = (2**level - 1) + np.arange(tree.num_slots) // 2 ** (tree.depth - level)
        inside = (lo[node] - slack <= pos) & (pos <= hi[node] + slack)
        assert np.all(inside.all(axis=1) | ~ok), f"level {level}: {(~inside.all(axis=1) & ok).sum()} points outside"


def test_smooth_deformation_keeps_points_in_boxes_and_boxes_nested(cloud):
    x, alive, tree = cloud
    y = np.asarray(bend_points(jnp.asarray(x), (0, 0, -0.6), (0, 0, 1), (1, 0, 0), np.deg2rad(30), 2.0))
    carried, report = carry_tree_with_report(tree, x, y, alive, CFG)
    assert report["torn"] == 0 and 0 < report["max_residual"] < 2.0
    # the boxes are not grown: a point stays within the fit's residual of them
    assert_points_inside_their_boxes(carried, y, alive, carried.frame_level,
                                     slack=report["max_residual"] * float(carried.spacing) + 1e-5)
    # levels above the frame level: world boxes holding their children's
    lo, hi, cnt = (np.asarray(a) for a in (carried.lo, carried.hi, carried.count))
    for g in range(2**carried.frame_level - 1):
        for k in (2 * g + 1, 2 * g + 2):
            if k < 2**carried.frame_level - 1 and cnt[k] > 0:
                assert np.all(lo[g] <= lo[k]) and np.all(hi[k] <= hi[g])
    # the bent cloud still renders: every ray aimed at a point gets a segment near it
    o, d = _aimed_rays(y, seed=3)
    seg = intersect(carried, make_rays(o.astype(np.float32), d.astype(np.float32)), CFG)
    assert int(jnp.max(seg.overflow)) == 0 and float(jnp.mean(jnp.any(seg.valid, axis=1))) > 0.9


def test_deletions_shrink_and_empty_nodes(cloud):
    x, alive, tree = cloud
    keep = alive & (x[:, 0] < 0.3)
    carried, report = carry_tree_with_report(tree, x, x, keep, CFG)
    assert report["emptied"] > 0
    cnt_new, cnt_old = np.asarray(carried.count), np.asarray(tree.count)
    assert cnt_new[0] == keep.sum() and np.all(cnt_new <= cnt_old)
    valid = np.asarray(carried.valid)
    assert not valid[cnt_new == 0].any()
    assert_points_inside_their_boxes(carried, x, keep, carried.frame_level)
    # untouched nodes keep their boxes bit for bit; shrunk ones lie inside the built ones
    lo_n, hi_n, lo_o, hi_o = (np.asarray(a) for a in (carried.lo, carried.hi, tree.lo, tree.hi))
    f0 = 2**carried.frame_level - 1
    same = (cnt_new == cnt_old)[f0:]
    np.testing.assert_array_equal(lo_n[f0:][same], lo_o[f0:][same])
    full = (cnt_new > 0)[f0:]
    assert np.all(lo_n[f0:][full] >= lo_o[f0:][full] - 1e-6) and np.all(hi_n[f0:][full] <= hi_o[f0:][full] + 1e-6)
    # no ray finds a segment in the deleted half
    o, d = _aimed_rays(x, seed=5)
    seg = intersect(carried, make_rays(o, d.astype(np.float32)), CFG)
    pts = np.asarray(make_rays(o, d).origin)[:, None] + np.asarray(seg.t_hi)[..., None] * d[:, None]
    margin = 4 * float(tree.spacing)
    assert not np.any(np.asarray(seg.valid) & (pts[..., 0] > 0.3 + margin) & (np.asarray(seg.t_lo) > 0))


def test_torn_subtrees_are_rebuilt_locally(cloud):
    x, alive, tree = cloud
    y = np.asarray(cut_points(jnp.asarray(x), (0.05, 0, 0), (1, 0, 0), 0.5))
    carried, report = carry_tree_with_report(tree, x, y, alive, CFG)
    assert report["torn"] > 0
    # torn subtrees hold their points; the others within the tear threshold (2 spacings)
    assert_points_inside_their_boxes(carried, y, alive, carried.frame_level, slack=2 * float(carried.spacing) + 1e-5)
    # rays through the gap: torn subtrees are split again on the edited points, so (like a rebuild,
    # whose median splits need not fall in the gap either) few voxels straddle it; carried without
    # the local rebuild, 88 segments did
    o = np.stack([np.full(200, 0.05), np.linspace(-0.9, 0.9, 200), np.zeros(200)], 1).astype(np.float32)
    d = np.tile(np.array([[0.0, 0.0, 1.0]], np.float32), (200, 1))
    rays = make_rays(o - 2 * d, d)
    gap = int(jnp.sum(intersect(carried, rays, CFG).valid))
    rebuilt = int(jnp.sum(intersect(build_tree(y, alive, CFG), rays, CFG).valid))
    assert gap <= 2 * rebuilt + 10, (gap, rebuilt)
    cand = np.asarray(carried.candidates)
    assert np.all((cand < tree.capacity) | (cand == tree.capacity))


def test_bad_input_is_named(cloud):
    x, alive, tree = cloud
    with pytest.raises(ValueError, match="xyz: expected shape"):
        carry_tree(tree, x, x[:-1], alive, CFG)
    more = np.concatenate([x, x[:1]])
    wider = build_tree(more, np.append(alive, False), CFG)
    with pytest.raises(ValueError, match="alive: expected the tree's points"):
        carry_tree(wider, more, more, np.ones(len(more), bool), CFG)
    y = x.copy()
    y[7] = np.nan
    with pytest.raises(ValueError, match="xyz: expected finite positions.*index 7"):
        carry_tree(tree, x, y, alive, CFG)
    with pytest.raises(ValueError, match="no frames"):
        carry_tree(carry_tree(tree, x, x, alive, CFG), x, x, alive, CFG)


def test_carried_trees_do_not_recompile(cloud):
    x, alive, tree = cloud
    o, d = _aimed_rays(x, n=64)
    rays = make_rays(o, d)
    for angle in (10.0, 20.0, 30.0):
        m = rigid_motion((1.0, 0.0, 1.0), angle)
        y = (x @ m[:3, :3].T + m[:3, 3]).astype(np.float32)
        jax.block_until_ready(intersect(carry_tree(tree, x, y, alive, CFG), rays, CFG))
        if angle == 10.0:
            before = intersect._cache_size()
    assert intersect._cache_size() == before


def test_uniform_scaling_scales_segments_and_the_length_unit(cloud):
    x, alive, tree = cloud
    s, t = 1.3, np.array([0.2, -0.1, 0.3], np.float32)
    carried = carry_tree(tree, x, (s * x + t).astype(np.float32), alive, CFG)
    assert float(carried.spacing) == pytest.approx(s * float(tree.spacing), rel=1e-5)
    o, d = _aimed_rays(x)
    before = intersect(tree, make_rays(o, d), CFG)
    after = intersect(carried, make_rays((s * o + t).astype(np.float32), d), CFG)
    np.testing.assert_array_equal(np.asarray(before.node), np.asarray(after.node))
    np.testing.assert_allclose(s * np.asarray(before.t_lo), np.asarray(after.t_lo), atol=3e-5)
    np.testing.assert_allclose(s * np.asarray(before.t_hi), np.asarray(after.t_hi), atol=3e-5)


def test_a_held_context_carries_as_one_made_on_the_spot_and_another_clouds_is_refused(cloud):
    x, alive, tree = cloud
    context = carry_context(x, held_points(tree), CFG)
    np.testing.assert_array_equal(held_points(tree), alive)
    y = np.asarray(cut_points(jnp.asarray(x), (0.05, 0, 0), (1, 0, 0), 0.5))  # torn: the limit is used
    spot, spot_report = carry_tree_with_report(tree, x, y, alive, CFG)
    held, held_report = carry_tree_with_report(tree, x, y, alive, CFG, context=context)
    assert held_report == spot_report and spot_report["torn"] > 0
    jax.tree_util.tree_map(np.testing.assert_array_equal, held, spot)
    with pytest.raises(ValueError, match="another cloud.*other positions"):
        carry_tree(tree, x, y, alive, CFG, context=carry_context(1.01 * x, alive, CFG))
    fewer = alive.copy()
    fewer[:10] = False
    with pytest.raises(ValueError, match=f"another cloud.*{len(x) - 10} points, the tree holds {len(x)}"):
        carry_tree(tree, x, y, alive, CFG, context=carry_context(x, fewer, CFG))
    with pytest.raises(ValueError, match="made with another"):
        carry_tree(tree, x, y, alive, CFG, context=carry_context(x, alive, CFG.replace(margin_factor=2.0)))

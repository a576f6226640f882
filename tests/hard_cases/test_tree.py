"""Stage 1, tree (``build_tree``, host numpy): structural invariants and candidate sets against the
float64 checks of ``tests/geometry/reference.py`` on random clouds — degenerate (coplanar,
collinear, duplicates, grids, tight clusters), at scene sizes 1e-4 .. 1e4, with deleted points —
and exact scale equivariance under powers of two (2^-13 ~ 1.2e-4, 2^13 ~ 8e3)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from ne_jax.geometry import build_tree

from geometry.reference import check_candidates, check_tree

from .common import CFG, CLOUD_KINDS, DTYPE, HYP, assert_finite, make_cloud

clouds = st.tuples(
    st.sampled_from(CLOUD_KINDS),
    st.integers(1, 256),
    st.integers(0, 2**16),
    st.sampled_from([1e-4, 2.0**-13, 1.0, 2.0**13, 1e4]),
    st.sampled_from([0.0, 0.0, 0.3]),
)


@HYP.__class__(HYP, max_examples=25)
@given(clouds)
def test_random_clouds_keep_the_invariants(cloud):
    kind, n, seed, scale, deleted = cloud
    xyz, alive = make_cloud(kind, n, seed, scale=scale, deleted=deleted)
    tree = build_tree(xyz, alive, CFG)
    assert tree.lo.dtype == DTYPE and tree.spacing.dtype == DTYPE
    assert_finite(tree)
    sp = float(tree.spacing)
    assert sp > 0
    if kind != "duplicates" and alive.sum() > 1:  # spacing is the mean NN distance, in scene units
        assert sp <= 4 * scale
    # check_tree's tolerances are absolute (1e-6), which means nothing at 1e-4: at power-of-two scales
    # check the tree scaled to unit size (exact, so ties in extents and points on faces stay exact);
    # at decimal scales check it as is (the exact parts — containment, counts, split axes — still bite).
    div = scale if np.log2(scale).is_integer() else 1.0
    f64 = lambda a: np.asarray(a, np.float64) / div  # noqa: E731
    unit = tree.replace(lo=f64(tree.lo), hi=f64(tree.hi), split_value=f64(tree.split_value))
    check_tree(unit, f64(xyz), alive, CFG)
    check_candidates(unit, f64(xyz), alive, CFG, max_nodes=64)


@pytest.mark.parametrize("kind", ["uniform", "coplanar", "collinear", "grid", "clusters"])
@pytest.mark.parametrize("power", [-13, 13])
def test_power_of_two_scaling_is_exact(kind, power):
    """Every float operation of the build commutes with a power-of-two scaling (no rounding), so the
    scaled tree is the unscaled one scaled, bit for bit: topology, candidates, boxes, spacing."""
    xyz, alive = make_cloud(kind, 200, seed=3, deleted=0.2)
    f = DTYPE.type(2.0**power)
    a = build_tree(xyz, alive, CFG)
    b = build_tree(xyz * f, alive, CFG)
    for name in ("perm", "count", "valid", "split_axis", "candidates"):
        np.testing.assert_array_equal(np.asarray(getattr(a, name)), np.asarray(getattr(b, name)), err_msg=name)
    for name in ("lo", "hi", "split_value", "spacing"):
        np.testing.assert_array_equal(np.asarray(getattr(a, name)) * f, np.asarray(getattr(b, name)), err_msg=name)


def test_dead_slots_never_matter():
    """Dead slots holding anything finite or not (NaN, inf, huge) build the same tree."""
    xyz, alive = make_cloud("sphere", 150, seed=5, deleted=0.3)
    ref = build_tree(xyz, alive, CFG)
    for junk in (np.nan, np.inf, -1e30, 0.0):
        x = xyz.copy()
        x[~alive] = junk
        t = build_tree(x, alive, CFG)
        for name in ("perm", "lo", "hi", "candidates", "valid", "spacing"):
            np.testing.assert_array_equal(np.asarray(getattr(t, name)), np.asarray(getattr(ref, name)), err_msg=name)

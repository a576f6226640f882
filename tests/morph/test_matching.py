"""K-D-tree matching: a bijection, equal to a slow recursive reference, exact on copies, and
stable on degenerate and extreme clouds; size equalisation and chained paths."""

from __future__ import annotations

import numpy as np
import pytest

from ne_jax.morph.matching import equal_size, index_path, kd_match
from ne_jax.morph.path import linear_path, path_from_clouds


def reference_match(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The obvious recursion: split axis = widest axis of the union, each cloud split at its own
    rank ``m // 2`` along it, leaves pair one point of each."""
    perm = np.empty(len(a), np.int64)

    def go(ia, ib):
        if len(ia) == 1:
            perm[ia[0]] = ib[0]
            return
        u = np.concatenate([a[ia], b[ib]])
        axis = int(np.argmax(u.max(0) - u.min(0)))
        sa, sb = ia[np.argsort(a[ia, axis], kind="stable")], ib[np.argsort(b[ib, axis], kind="stable")]
        h = len(ia) // 2
        go(sa[:h], sb[:h])
        go(sa[h:], sb[h:])

    go(np.arange(len(a)), np.arange(len(b)))
    return perm


def _is_permutation(p, n):
    return p.shape == (n,) and np.array_equal(np.sort(p), np.arange(n))


@pytest.mark.parametrize("n", [1, 2, 3, 7, 100, 1023])
def test_matching_is_a_bijection_equal_to_the_recursive_reference(n):
    rng = np.random.default_rng(n)
    a, b = rng.random((n, 3)), rng.normal(size=(n, 3)) * [3.0, 1.0, 0.5]
    p = kd_match(a, b)
    assert _is_permutation(p, n)
    np.testing.assert_array_equal(p, reference_match(a, b))


def test_identical_clouds_match_to_the_identity_and_copies_point_to_point():
    rng = np.random.default_rng(0)
    a = rng.random((500, 3))
    np.testing.assert_array_equal(kd_match(a, a), np.arange(500))
    np.testing.assert_array_equal(kd_match(a, a + [10.0, -3.0, 0.5]), np.arange(500))  # translated copy
    q = rng.permutation(500)
    np.testing.assert_array_equal(a[q][kd_match(a, a[q])], a)  # a shuffled copy is unshuffled


def test_matching_keeps_relative_positions():
    """Two different shapes: matched pairs agree in their rank along every axis far better than chance."""
    rng = np.random.default_rng(1)
    a = rng.random((2000, 3))
    b = rng.normal(size=(2000, 3))
    p = kd_match(a, b)
    for axis in range(3):
        ra, rb = np.argsort(np.argsort(a[:, axis])), np.argsort(np.argsort(b[p, axis]))
        assert np.corrcoef(ra, rb)[0, 1] > 0.5


@pytest.mark.parametrize("case", ["duplicates", "collinear", "coplanar", "tiny", "huge"])
def test_degenerate_and_extreme_clouds_still_give_a_bijection(case):
    rng = np.random.default_rng(2)
    n = 257
    a = rng.random((n, 3))
    b = {"duplicates": np.repeat(rng.random((4, 3)), [64, 64, 64, 65], axis=0),
         "collinear": np.outer(rng.random(n), [1.0, 2.0, 3.0]),
         "coplanar": np.c_[rng.random((n, 2)), np.zeros(n)],
         "tiny": None, "huge": None}[case]
    if case in ("tiny", "huge"):  # both clouds at 1e-4 or 1e4: the matching looks at ranks and spans only
        scale = 1e-4 if case == "tiny" else 1e4
        a, b = scale * a, scale * rng.normal(size=(n, 3))
        np.testing.assert_array_equal(kd_match(a, b), kd_match(a / scale, b / scale))
    p = kd_match(a, b)
    assert _is_permutation(p, n)
    np.testing.assert_array_equal(p, reference_match(a, b))


def test_bad_clouds_are_refused_with_the_argument_named():
    a = np.zeros((5, 3))
    with pytest.raises(ValueError, match="equal size.*5 and 4"):
        kd_match(a, np.zeros((4, 3)))
    with pytest.raises(ValueError, match=r"b: expected an \[N, 3\] point cloud, found shape \(5, 2\)"):
        kd_match(a, np.zeros((5, 2)))
    bad = np.zeros((5, 3))
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="a: expected finite positions.*row 3"):
        kd_match(bad, a)


def test_equal_size_keeps_the_smaller_cloud_and_the_highest_priorities():
    ka, kb = equal_size(10, 4)
    np.testing.assert_array_equal(kb, np.arange(4))
    assert ka.size == 4 and np.all(np.diff(ka) > 0) and ka.max() < 10
    prio = np.arange(10.0)
    ka, kb = equal_size(10, 4, priority_a=prio)
    np.testing.assert_array_equal(ka, [6, 7, 8, 9])
    a1, _ = equal_size(10, 4, seed=3)
    a2, _ = equal_size(10, 4, seed=3)
    np.testing.assert_array_equal(a1, a2)
    with pytest.raises(ValueError, match=r"priority per point \[10\]"):
        equal_size(10, 4, priority_a=np.ones(3))


def test_index_path_recovers_the_indices_of_shuffled_intermediate_clouds(tmp_path):
    rng = np.random.default_rng(4)
    a = rng.random((300, 3))
    truth = [a + [0.1 * t, 0.0, 0.0] for t in range(4)]  # small steps: the matching follows each point
    shuffled = [truth[0]] + [c[rng.permutation(300)] for c in truth[1:]]
    for got, want in zip(index_path(shuffled), truth):
        np.testing.assert_array_equal(got, want)
    # the plug-in interface: intermediate clouds as files, A and B at the ends
    np.save(tmp_path / "mid1.npy", shuffled[1])
    np.save(tmp_path / "mid2.npy", shuffled[2])
    path = path_from_clouds(a, shuffled[3], [tmp_path / "mid1.npy", tmp_path / "mid2.npy"])
    for got, want in zip(path, truth):
        np.testing.assert_array_equal(got, want)
    with pytest.raises(ValueError, match=r"mid1.npy: expected 300 points .* found 299"):
        np.save(tmp_path / "mid1.npy", shuffled[1][:299])
        path_from_clouds(a, shuffled[3], [tmp_path / "mid1.npy"])
    with pytest.raises(FileNotFoundError, match="missing.ply: expected an intermediate cloud"):
        path_from_clouds(a, shuffled[3], [tmp_path / "missing.ply"])


def test_linear_path_runs_from_a_to_b_along_the_matching():
    rng = np.random.default_rng(5)
    a, b = rng.random((64, 3)), rng.random((64, 3)) + 2.0
    path = linear_path(a, b, 5)
    assert len(path) == 5
    np.testing.assert_array_equal(path[0], a)
    np.testing.assert_allclose(path[-1], b[kd_match(a, b)], atol=1e-12)
    np.testing.assert_allclose(path[2], 0.5 * (a + b[kd_match(a, b)]), atol=1e-12)
    with pytest.raises(ValueError, match="steps: expected at least 2"):
        linear_path(a, b, 1)

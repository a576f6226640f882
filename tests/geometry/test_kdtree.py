"""build_tree: structural invariants against the points (float64), candidate sets against brute
force, degenerate clouds, configuration errors."""

import numpy as np
import pytest

from ne_jax.geometry import KDTreeConfig, build_tree, tree_depth

from tests.mini_presets import tiny_tree

from .clouds import CLOUDS, sphere
from .reference import build_tree_reference, check_candidates, check_tree

CFG = tiny_tree()


@pytest.mark.parametrize("name", sorted(CLOUDS))
def test_tree_invariants(name):
    xyz, alive = CLOUDS[name]
    tree = build_tree(xyz, alive, CFG)
    check_tree(tree, xyz, alive, CFG)
    check_candidates(tree, xyz, alive, CFG)
    n = int(alive.sum())
    assert tree.depth == tree_depth(n, CFG)
    assert 2**tree.depth >= n and (tree.depth == CFG.num_render_levels + 1 or 2 ** (tree.depth - 1) < n)
    assert np.isfinite(float(tree.spacing)) and float(tree.spacing) > 0
    assert np.all(np.isfinite(np.asarray(tree.lo))) and np.all(np.isfinite(np.asarray(tree.hi)))
    # At least one rendering-level box is valid: every cloud here is renderable.
    lv = tree.render_levels
    start, stop = 2 ** lv[0] - 1, 2**tree.depth - 1
    assert np.asarray(tree.valid)[start:stop].any()


def test_default_config_candidates_and_spacing():
    xyz = sphere(3000, seed=5)
    alive = np.ones(len(xyz), bool)
    cfg = KDTreeConfig()
    tree = build_tree(xyz, alive, cfg)
    check_tree(tree, xyz, alive, cfg)
    check_candidates(tree, xyz, alive, cfg, max_nodes=200)
    assert tree.candidates.shape == (2**tree.depth - 2**tree.grow_level, 96)
    from scipy.spatial import cKDTree

    d, _ = cKDTree(xyz).query(xyz, k=2)
    np.testing.assert_allclose(float(tree.spacing), d[:, 1].mean(), rtol=1e-5)
    # On a clean surface cloud almost all rendering boxes are valid.
    r0 = 2 ** tree.render_levels[0] - 1
    assert np.asarray(tree.valid)[r0 : 2**tree.depth - 1].mean() > 0.95


def test_far_outlier_boxes_are_invalid():
    xyz = np.concatenate([sphere(2000, seed=6), np.array([[40.0, 0, 0], [40.5, 0, 0]], np.float32)])
    tree = build_tree(xyz, np.ones(len(xyz), bool), KDTreeConfig())
    perm = np.asarray(tree.perm)
    bottom = tree.depth - 1
    rows = perm.reshape(-1, 2)
    hit = [i for i, r in enumerate(rows) if (r == 2000).any() or (r == 2001).any()]
    # Nodes holding the outliers: their 96 candidates reach across the scene -> invalid.
    assert not np.asarray(tree.valid)[[2**bottom - 1 + i for i in hit]].any()


def test_fixed_depth_gives_fixed_shapes():
    cfg = tiny_tree(depth=9)
    xyz = sphere(600, 1)
    a = build_tree(xyz, np.arange(600) < 300, cfg)  # same capacity, different alive counts
    b = build_tree(xyz, np.arange(600) >= 100, cfg)
    import jax

    assert jax.tree_util.tree_structure(a) == jax.tree_util.tree_structure(b)
    assert all(x.shape == y.shape for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)))
    with pytest.raises(ValueError, match=r"alive: expected at most 2\*\*depth = 512 alive points.*found 513"):
        build_tree(sphere(513, 3), np.ones(513, bool), cfg)


def test_tree_helpers():
    tree = build_tree(sphere(100, 1), np.ones(100, bool), CFG)
    assert tree.children(0) == (1, 2) and tree.parent(2) == 0 and tree.parent(1) == 0
    assert tree.level_start(3) == 7 and tree.num_nodes == 2 ** (tree.depth + 1) - 1
    assert tree.render_levels == (tree.depth - 2, tree.depth - 1) and tree.grow_level == tree.depth - 3


@pytest.mark.parametrize(
    "xyz, alive, match",
    [
        (np.zeros((4, 2)), np.ones(4, bool), r"xyz: expected shape \[C, 3\], found shape \(4, 2\)"),
        (np.zeros((4, 3)), np.ones(3, bool), r"alive: expected shape \[C=4\], found shape \(3,\)"),
        (np.zeros((4, 3)), np.ones(4, int), r"alive: expected a bool mask, found dtype int"),
        (np.zeros((4, 3)), np.zeros(4, bool), r"alive: expected at least one alive point, found none"),
        (np.array([[0, 0, 0], [np.inf, 0, 0.0]]), np.ones(2, bool), r"xyz: expected finite positions.*index 1"),
    ],
)
def test_build_errors(xyz, alive, match):
    with pytest.raises(ValueError, match=match):
        build_tree(xyz, alive, CFG)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(knn_k=200), r"KDTreeConfig.knn_k: expected an integer in \[1, 96\], found 200"),
        (dict(depth=3), r"KDTreeConfig.depth: expected None or an integer in .* = \[5, 21\], found 3"),
        (dict(margin_factor=0.0), r"KDTreeConfig.margin_factor: expected > 0"),
    ],
)
def test_config_errors(kwargs, match):
    with pytest.raises(ValueError, match=match):
        KDTreeConfig(**kwargs)


def test_config_is_hashable_with_the_papers_defaults():
    assert hash(KDTreeConfig(depth=21)) == hash(KDTreeConfig(depth=21))
    assert KDTreeConfig().num_candidates == 96 and KDTreeConfig().knn_k == 32
    assert tiny_tree().num_candidates == 16


@pytest.mark.parametrize(
    "cfg", [tiny_tree(), KDTreeConfig(), KDTreeConfig(depth=13), tiny_tree(depth=15)],
    ids=["tiny", "default", "depth13", "tiny_depth15"],
)
def test_candidates_exact_on_every_node(cfg):
    """Every candidate row of a node holding points (the cascade's picks and its fallback queries
    alike) holds exactly the ``num_candidates`` nearest alive points in nondecreasing distance: its
    distances equal, entry by entry, scipy's sorted k-NN distances from the box centre (only tied
    points may be swapped). Rows of empty nodes (a fixed depth far above log2(n) leaves most deep
    nodes empty; nothing reads them) hold only the sentinel."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(11)
    xyz = np.concatenate(
        [
            sphere(3000, seed=7),
            0.02 * rng.normal(size=(300, 3)).astype(np.float32) + np.float32([0.0, 0.0, 1.0]),
            np.float32([[6.0, 0, 0], [6.5, 0, 0], [0, -9.0, 0]]),
        ]
    )
    alive = rng.random(len(xyz)) > 0.05
    alive[-3:] = True
    tree = build_tree(xyz, alive, cfg)
    lo, hi = np.asarray(tree.lo, np.float64), np.asarray(tree.hi, np.float64)
    cand = np.asarray(tree.candidates)
    cap, kc = len(xyz), cfg.num_candidates
    nodes = tree.first_candidate_node + np.arange(cand.shape[0])
    full = np.asarray(tree.count)[nodes] > 0
    if cfg.depth is not None and cfg.depth > 13:
        assert 0 < full.sum() < full.size / 2  # the case this test is for: mostly empty deep nodes
    np.testing.assert_array_equal(cand[~full], cap)
    cand, nodes = cand[full], nodes[full]
    center = 0.5 * (lo + hi)[nodes]
    pts = np.flatnonzero(alive)
    d_ref, _ = cKDTree(xyz[pts].astype(np.float64)).query(center, k=kc)
    x = np.concatenate([xyz.astype(np.float64), np.full((1, 3), np.inf)])
    got = np.sqrt(sum((x[cand][..., a] - center[:, None, a]) ** 2 for a in range(3)))
    np.testing.assert_array_equal(got, d_ref)
    assert np.all(alive[cand[cand < cap]])
    real = np.where(cand < cap, cand, -1 - np.arange(kc))  # distinct sentinels
    assert all(len(set(r)) == kc for r in real)


_SAME_CLOUDS = {
    "sphere_deleted": (lambda rng: sphere(3000, seed=4), KDTreeConfig()),
    "uniform": (lambda rng: rng.uniform(-1, 1, (20000, 3)).astype(np.float32), KDTreeConfig()),
    "grid_duplicates": (
        lambda rng: np.repeat(
            np.stack(np.meshgrid(*[np.arange(9, dtype=np.float32)] * 3, indexing="ij"), -1).reshape(-1, 3), 2, 0
        ),
        tiny_tree(),
    ),
    "clusters_fixed_depth": (
        lambda rng: np.concatenate([sphere(2000, seed=5), 0.01 * rng.normal(size=(500, 3)).astype(np.float32)]),
        KDTreeConfig(depth=16),
    ),
    "tiny_fixed_depth": (lambda rng: rng.normal(size=(300, 3)).astype(np.float32), tiny_tree(depth=12)),
}


def _row_sq_dists(tree, xyz, rows):
    """``[rows, kc]`` float64 squared distances (``dx² + dy² + dz²``, as the build sums them) of the
    candidates of candidate rows ``rows`` from their box centres (inf for the sentinel)."""
    lo, hi = np.asarray(tree.lo, np.float64), np.asarray(tree.hi, np.float64)
    c = 0.5 * (lo + hi)[tree.first_candidate_node + rows]
    x = np.concatenate([np.asarray(xyz, np.float64), np.full((1, 3), np.inf)])
    cand = np.minimum(np.asarray(tree.candidates)[rows], len(xyz))
    return sum((x[cand][..., a] - c[:, None, a]) ** 2 for a in range(3))


def _slot_rank(tree, cap):
    """``[cap + 1]`` each point's position in the tree's slot order (the sentinel last)."""
    perm = np.asarray(tree.perm)
    rank = np.full(cap + 1, cap + 1, np.int64)
    real = perm[perm < cap]
    rank[real] = np.arange(real.size)
    return rank


def assert_canonical_candidates(tree, xyz, alive, max_rows=300, seed=0):
    """Every non-empty candidate row is the canonical one: the ``kc`` alive points first by squared
    distance from the box centre, then by slot (position in ``perm``), checked against brute force
    over all alive points on up to ``max_rows`` rows (the ties of a grid or of duplicates included)."""
    cap = len(xyz)
    rank = _slot_rank(tree, cap)
    cand = np.asarray(tree.candidates)
    kc = cand.shape[1]
    nodes = tree.first_candidate_node + np.arange(cand.shape[0])
    rows = np.flatnonzero(np.asarray(tree.count)[nodes] > 0)
    if rows.size > max_rows:
        rows = np.sort(np.random.default_rng(seed).choice(rows, max_rows, replace=False))
    lo, hi = np.asarray(tree.lo, np.float64), np.asarray(tree.hi, np.float64)
    pts = np.flatnonzero(alive)
    x = np.asarray(xyz, np.float64)[pts]
    for r in rows:
        c = 0.5 * (lo + hi)[tree.first_candidate_node + r]
        d2 = (x[:, 0] - c[0]) ** 2
        d2 += (x[:, 1] - c[1]) ** 2
        d2 += (x[:, 2] - c[2]) ** 2
        want = pts[np.lexsort((rank[pts], d2))[:kc]]
        want = np.concatenate([want, np.full(kc - want.size, cap)])
        np.testing.assert_array_equal(cand[r], want, err_msg=f"row {r}")


@pytest.mark.parametrize("name", sorted(_SAME_CLOUDS))
def test_build_matches_the_reference_build(name):
    """The build equals the previous one (``reference.build_tree_reference``, a verbatim copy of the
    build at b94223a) bit for bit on every field but the candidate rows: partition, boxes, splits,
    validity, spacing. Candidate rows equal the reference's except where points are equidistant
    from the box centre: the build orders those by slot (the canonical order, independent of the
    cascade's superset widths), the reference in whatever order its scipy queries and supersets
    gave. There the rows hold the same squared distances entry by entry, differing only at entries
    whose distance is tied within the row, or at the last place (tied with a point left out)."""
    rng = np.random.default_rng(3)
    make, cfg = _SAME_CLOUDS[name]
    xyz = make(rng)
    alive = rng.random(len(xyz)) > 0.1
    a = build_tree_reference(xyz, alive, cfg)
    b = build_tree(xyz, alive, cfg)
    for field in ("lo", "hi", "count", "valid", "split_axis", "split_value", "perm", "candidates", "spacing"):
        x, y = np.asarray(getattr(a, field)), np.asarray(getattr(b, field))
        assert x.dtype == y.dtype and x.shape == y.shape, field
        if field != "candidates":
            np.testing.assert_array_equal(x, y, err_msg=field)
    assert (a.depth, a.capacity, a.num_render_levels) == (b.depth, b.capacity, b.num_render_levels)
    ca, cb = np.asarray(a.candidates), np.asarray(b.candidates)
    rows = np.flatnonzero((ca != cb).any(axis=1))
    if rows.size:
        d2 = _row_sq_dists(b, xyz, rows)
        np.testing.assert_array_equal(_row_sq_dists(a, xyz, rows), d2)
        tied = (d2[:, 1:] == d2[:, :-1])
        tied = np.pad(tied, ((0, 0), (1, 0))) | np.pad(tied, ((0, 0), (0, 1)))
        tied[:, -1] = True  # the last place: tied with a point outside the row (its distance is checked)
        assert np.all(tied[ca[rows] != cb[rows]])
    assert_canonical_candidates(b, xyz, alive)


_HARD = {
    "duplicates": lambda rng: np.repeat(rng.normal(size=(40, 3)).astype(np.float32), 7, 0),
    "single_point": lambda rng: np.float32([[0.25, -1.0, 3.0]]),
    "plane": lambda rng: np.concatenate([rng.uniform(-1, 1, (600, 2)), np.zeros((600, 1))], 1).astype(np.float32),
    "grid": lambda rng: np.stack(np.meshgrid(*[np.arange(7, dtype=np.float32)] * 3, indexing="ij"), -1).reshape(-1, 3),
    "symmetric_pairs": lambda rng: (lambda p: np.concatenate([p, -p]))(
        rng.integers(-4, 5, (300, 3)).astype(np.float32)
    ),
}


@pytest.mark.parametrize("cfg", [tiny_tree(), KDTreeConfig(), tiny_tree(depth=14)], ids=["tiny", "default", "deep"])
@pytest.mark.parametrize("name", sorted(_HARD))
def test_candidates_are_canonical_on_hard_clouds(name, cfg):
    """Duplicates, one point, a plane, a grid (everything tied), point pairs symmetric about the
    origin, and a fixed depth far above log2(n) (empty levels): every candidate row is the
    canonical one, checked against brute force."""
    rng = np.random.default_rng(5)
    xyz = _HARD[name](rng)
    alive = np.ones(len(xyz), bool)
    tree = build_tree(xyz, alive, cfg)
    if len(xyz) <= 400:  # check_tree is quadratic in the boxes of a level
        check_tree(tree, xyz, alive, cfg)
    assert_canonical_candidates(tree, xyz, alive)


@pytest.mark.parametrize("name", ["grid_duplicates", "clusters_fixed_depth"])
def test_candidates_do_not_depend_on_the_cascade(name, monkeypatch):
    """The superset widths, the fallback queries and the threads change the speed, never the
    result: narrow supersets (most nodes fall back to a query), wide ones, and one thread or
    several give the same tree bit for bit, ties included."""
    from ne_jax.geometry import kdtree

    rng = np.random.default_rng(3)
    make, cfg = _SAME_CLOUDS[name]
    xyz = make(rng)
    alive = rng.random(len(xyz)) > 0.1
    ref = build_tree(xyz, alive, cfg)
    kc = cfg.num_candidates
    for widths, threads, block in ((lambda levels, *a: [kc + 1] * (levels - 1) + [kc], 1, 1024),
                                   (lambda levels, *a: [8 * kc] * (levels - 1) + [kc], 2, 4),
                                   (None, 3, 2)):
        if widths is not None:
            monkeypatch.setattr(kdtree, "_superset_widths", lambda kc_, levels, *a, w=widths: w(levels, *a))
        monkeypatch.setattr(kdtree, "_THREADS", threads)
        monkeypatch.setattr(kdtree, "_GROW_BLOCK", block)
        got = build_tree(xyz, alive, cfg)
        for field in ("candidates", "valid", "lo", "perm"):
            np.testing.assert_array_equal(np.asarray(getattr(got, field)), np.asarray(getattr(ref, field)),
                                          err_msg=field)
        monkeypatch.undo()


SPLIT_CASES = [(1, 6, "normal"), (300, 12, "normal"), (5000, 16, "normal"), (4096, 12, "rounded"),
               (777, 10, "signed_zeros")]


def _split_cloud(n: int, kind: str) -> np.ndarray:
    """``n`` normal points; ``rounded``: on a coarse grid (ties); ``signed_zeros``: y is -0.0 or 0.0."""
    rng = np.random.default_rng(n)
    x = rng.normal(size=(n, 3))
    if kind == "rounded":
        x = np.round(2 * x)
    if kind == "signed_zeros":
        x[:, 1] = np.where(rng.random(n) < 0.5, -0.0, 0.0)
    return x


@pytest.mark.parametrize("n, depth, kind", SPLIT_CASES)
def test_split_levels_match_the_reference(n, depth, kind):
    """``_split_levels`` (also used by ``carry_tree``'s local rebuilds) returns what the previous
    implementation returned, byte for byte: ties (rounded coordinates), signed zeros, and levels
    below log2(n) where nodes hold one point or none."""
    from ne_jax.geometry.kdtree import _split_levels

    from .reference import _ref_split_levels

    x = _split_cloud(n, kind)
    a, b = _ref_split_levels(x, depth), _split_levels(x, depth)
    flat = lambda r: list(r[0]) + list(r[1]) + [r[2]] + [v for part in r[3] for v in part]  # noqa: E731
    for u, v in zip(flat(a), flat(b), strict=True):
        assert u.dtype == v.dtype and u.shape == v.shape and u.tobytes() == v.tobytes()


@pytest.mark.parametrize("n, depth, kind", SPLIT_CASES)
def test_cell_boxes_match_the_reference(n, depth, kind):
    """``_cell_boxes`` (also used by ``carry_tree``) returns what the previous implementation
    returned, byte for byte: signed zeros on split faces, empty nodes, single-point levels."""
    from ne_jax.geometry.kdtree import _cell_boxes, _split_levels

    from .reference import _ref_cell_boxes

    x = _split_cloud(n, kind)
    axes, values, _, (lo, hi, cnt) = _split_levels(x, depth)
    for margin in (0.0, 0.05):
        a = _ref_cell_boxes(CFG, axes, values, lo, hi, cnt, depth, margin)
        b = _cell_boxes(CFG, axes, values, lo, hi, cnt, depth, margin)
        for u, v in zip([*a[0], *a[1]], [*b[0], *b[1]], strict=True):
            assert u.dtype == v.dtype and u.shape == v.shape and u.tobytes() == v.tobytes()

"""IST: exact on rigid motions and on linear maps that keep the normal direction, equal to a float64
numpy reference of the frame map's polar factor elsewhere, finite and orthogonal on degenerate
frames, differentiable; a held neighbour table is handed back for the same deletions, another
cloud's is refused.

Every cloud is padded with dead slots to :data:`CAP` (dead slots take no part in the IST and are
cut off again): :func:`ist_from_plan` compiles once per configuration for the file."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ne_jax.edit.deformations import bend_points, rotation_matrix
from ne_jax.edit.ist import ISTConfig, compute_ist, ist_from_plan, ist_neighbors, nearest_rotation, plan_ist
from ne_jax.pointcloud.normals import NormalConfig, estimate_normals

from .reference import frame_map_polar

UNORIENTED = NormalConfig(orient="none")
R = np.asarray(rotation_matrix([1.0, 2.0, 3.0], 0.7), np.float64)
CAP = 1600  # slots of every cloud (the largest has 1600 points)


def sphere(n=1500, seed=0):
    x = np.random.default_rng(seed).normal(size=(n, 3))
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def plane(m=30):
    g = np.stack(np.meshgrid(np.linspace(-1, 1, m), np.linspace(-1, 1, m)), -1).reshape(-1, 2)
    g = g + np.random.default_rng(1).uniform(-0.01, 0.01, g.shape)  # no exact grid ties
    return np.c_[g, np.zeros(len(g))], np.tile([0.0, 0.0, 1.0], (len(g), 1))


def padded(n, *arrays):
    """``[n, ...]`` arrays padded with zeros to ``CAP`` rows."""
    return [np.concatenate([a, np.zeros((CAP - n,) + a.shape[1:], a.dtype)]) for a in map(np.asarray, arrays)]


def ist_of(x0, n0, x1, n1, alive=None, cfg=ISTConfig(), conf=None):
    """:func:`compute_ist` of ``n`` points in ``CAP`` slots (the rest dead): ``(ist [n], sign [n], report)``."""
    n = len(x0)
    alive = np.ones(n, bool) if alive is None else alive
    conf = np.full(n, 0.5) if conf is None else conf
    ist, sign, report = compute_ist(cfg, *padded(n, x0, n0, x1, n1, alive, conf))
    return np.asarray(ist, np.float64)[:n], np.asarray(sign)[:n], report


def assert_rotations(ist, tol=1e-5):
    assert np.isfinite(ist).all()
    eye = np.einsum("cji,cjk->cik", ist, ist)
    np.testing.assert_allclose(eye, np.broadcast_to(np.eye(3), eye.shape), atol=tol)
    np.testing.assert_allclose(np.linalg.det(ist), 1.0, atol=tol)


def test_global_rotation_gives_r_transpose_everywhere():
    x0 = sphere()
    n0 = estimate_normals(UNORIENTED, x0)
    x1 = x0 @ R.T
    n1 = estimate_normals(UNORIENTED, x1)  # re-estimated, own arbitrary signs
    ist, sign, report = ist_of(x0, n0, x1, n1)
    assert report["good"] == len(x0)
    # float32 arithmetic on O(1) values; Open3D's normals of the rotated cloud differ by ~1e-7
    np.testing.assert_allclose(ist, np.broadcast_to(R.T, ist.shape), atol=1e-5)
    # the orientation sign turns the edited normals into the rotated original ones
    np.testing.assert_allclose(sign[:, None] * n1, n0 @ R.T, atol=1e-4)


def test_identity_edit_gives_identity():
    x0 = sphere()
    n0 = estimate_normals(UNORIENTED, x0)
    ist, sign, _ = ist_of(x0, n0, x0, n0)
    np.testing.assert_allclose(ist, np.broadcast_to(np.eye(3), ist.shape), atol=1e-5)
    assert (sign == 1).all()


@pytest.mark.parametrize("stretch", [(1.5, 0.7, 1.3), (0.4, 2.5, 0.2)])
def test_linear_map_keeping_the_normal_gives_its_rotation_part(stretch):
    x0, n0 = plane()
    lin = R @ np.diag(stretch)  # polar decomposition R S, the plane normal an eigenvector of S
    x1 = x0 @ lin.T
    n1 = -np.tile(np.linalg.inv(lin).T @ [0, 0, 1.0], (len(x0), 1))  # deliberately the flipped sign
    n1 /= np.linalg.norm(n1, axis=1, keepdims=True)
    ist, sign, report = ist_of(x0, n0, x1, n1)
    assert report["good"] == len(x0)
    np.testing.assert_allclose(ist, np.broadcast_to(R.T, ist.shape), atol=1e-5)
    assert (sign == -1).all()


def test_general_linear_map_matches_float64_reference():
    x0, n0 = plane(20)
    sym = np.array([[1.4, 0.3, 0.2], [0.3, 0.8, -0.25], [0.2, -0.25, 1.1]])  # SPD, normal not an eigenvector
    lin = R @ sym
    x1 = x0 @ lin.T
    n1 = estimate_normals(UNORIENTED, x1).astype(np.float64)
    n = len(x0)
    cloud = padded(n, x0, n0, x1, n1, np.ones(n, bool), np.full(n, 0.5))
    cfg = ISTConfig(smooth_iters=0)
    plan = plan_ist(cfg, *cloud)
    ist, _, _ = ist_of(x0, n0, x1, n1, cfg=cfg)
    ref = frame_map_polar(x0, n0, x1, n1, np.asarray(plan.pair)[:n])
    np.testing.assert_allclose(ist, ref, atol=2e-5)  # float32 solve + Newton vs float64 SVD
    # for a linear map the frame map does not depend on which two neighbours span the frame: the
    # pairs chosen among 3 candidates instead of 8, through the same program
    other = plan_ist(ISTConfig(smooth_iters=0, candidates=3), *cloud)
    assert (np.asarray(other.pair)[:n] != np.asarray(plan.pair)[:n]).any()
    args = [jnp.asarray(a, jnp.float32) for a in cloud[:4]]
    ist3 = ist_from_plan(cfg, plan.replace(pair=other.pair, good=other.good), *args)[0]
    np.testing.assert_allclose(np.asarray(ist3, np.float64)[:n], ist, atol=2e-5)


def test_bend_matches_the_jacobian_rotation_on_the_surface():
    x0, n0 = plane(40)
    def bend(p):
        return bend_points(p, (0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0), np.deg2rad(60.0), 2.0)

    bent_and_jacobian = jax.jit(lambda x: (bend(x), jax.vmap(jax.jacfwd(lambda p: bend(p[None])[0]))(x)))
    x1, jac = (np.asarray(a, np.float64) for a in bent_and_jacobian(jnp.asarray(x0, jnp.float32)))
    n1 = estimate_normals(UNORIENTED, x1)
    ist, _, report = ist_of(x0, n0, x1, n1)
    assert report["good"] > 0.95 * len(x0)
    u, _, vt = np.linalg.svd(np.linalg.inv(jac))  # a bend is locally a rotation: polar(J^-1) = J^-1
    expected = u @ vt
    angle = np.degrees(np.arccos(np.clip((np.einsum("cij,cij->c", ist, expected) - 1) / 2, -1, 1)))
    interior = np.all(np.abs(x0[:, :2]) < 0.9, axis=1)  # PCA normals tilt at the border
    assert np.median(angle[interior]) < 0.5 and angle[interior].max() < 3.0


def test_degenerate_frames_are_finite_rotations():
    rng = np.random.default_rng(3)
    line = np.c_[np.linspace(-1, 1, 40), np.zeros(40), np.zeros(40)]
    dup = np.repeat(sphere(100), 3, axis=0)  # coincident triples
    x0 = np.concatenate([line, dup, sphere(200, 2)])
    n0 = np.concatenate([np.zeros((40, 3)), estimate_normals(UNORIENTED, x0[40:])])  # zero normals on the line
    x1 = x0 @ R.T
    n1 = np.concatenate([np.zeros((40, 3)), estimate_normals(UNORIENTED, x1[40:])])
    alive = rng.uniform(size=len(x0)) > 0.3  # deleted neighbours
    ist, sign, report = ist_of(x0, n0, x1, n1, alive=alive)
    assert_rotations(ist)
    assert np.isfinite(sign).all()
    assert report["good"] + report["filled"] + report["identity"] == alive.sum()
    # where a frame exists or was filled, it is the rotation's
    ok = np.abs(ist - R.T).max(axis=(1, 2)) < 1e-4
    assert ok[alive].mean() > 0.5
    np.testing.assert_allclose(ist[~alive], np.broadcast_to(np.eye(3), ist[~alive].shape))


def test_all_collinear_cloud_falls_back_to_identity():
    x0 = np.c_[np.linspace(-1, 1, 30), np.zeros(30), np.zeros(30)]
    n0 = np.tile([0.0, 0.0, 1.0], (30, 1))
    ist, _, report = ist_of(x0, n0, x0 @ R.T, n0 @ R.T)
    assert report["good"] == 0 and report["identity"] == 30
    np.testing.assert_allclose(ist, np.broadcast_to(np.eye(3), ist.shape))


def test_nearest_rotation_matches_svd_polar():
    rng = np.random.default_rng(5)
    m = rng.normal(size=(200, 3, 3))
    m[np.linalg.det(m) < 0, :, 0] *= -1
    cond = np.linalg.cond(m)
    m = m[cond < 50]
    u, _, vt = np.linalg.svd(m)
    rotation = jax.jit(nearest_rotation)  # one program a shape, not one per operation
    got = np.asarray(rotation(jnp.asarray(m, jnp.float32)), np.float64)
    np.testing.assert_allclose(got, u @ vt, atol=2e-5)
    rot = np.asarray(rotation_matrix([0.3, -1.0, 0.5], 2.0))
    np.testing.assert_allclose(np.asarray(rotation(jnp.asarray(rot))), rot, atol=2e-7)


GRAD_CFG = ISTConfig(polar_iters=6, fill_passes=1)


def _rot(t):
    return rotation_matrix([0.0, 0.3, 1.0], t)


@jax.jit
def _weighted_ist_and_grad(t, plan, x0, n0, n1, w):
    """``sum(IST(t) * w)`` and its derivative in the rotation angle ``t`` (one program for every
    angle and cloud of :func:`test_gradients_through_the_ist_are_finite`)."""
    return jax.value_and_grad(lambda t: jnp.sum(ist_from_plan(GRAD_CFG, plan, x0, n0, x0 @ _rot(t).T, n1)[0] * w))(t)


@pytest.mark.parametrize("angle", [0.0, 0.7])
def test_gradients_through_the_ist_are_finite(angle):
    """d/dtheta of the IST under a fixed plan, on a cloud with degenerate points too; at theta = 0
    (identity) as well. Checked against a central difference. Fewer polar iterations and fill passes
    than the default (as ``tests/edit/test_differentiable.py``): the same operations in a smaller
    graph, so the gradient compiles in seconds instead of ~50 s on a 2-core CPU."""
    x0 = np.concatenate([sphere(300), np.c_[np.linspace(-1, 1, 10), np.zeros(10), np.zeros(10)]])
    n0 = np.concatenate([estimate_normals(UNORIENTED, x0[:300]), np.zeros((10, 3))])
    x1 = x0 @ np.asarray(_rot(angle)).T
    n1 = np.concatenate([estimate_normals(UNORIENTED, x1[:300]), np.zeros((10, 3))])
    plan = plan_ist(GRAD_CFG, x0, n0, x1, n1, np.ones(310, bool), np.full(310, 0.5))
    x0j, n0j, n1j = (jnp.asarray(a, jnp.float32) for a in (x0, n0, n1))
    w = jnp.asarray(np.random.default_rng(0).normal(size=(310, 3, 3)), jnp.float32)

    def f(t):
        return _weighted_ist_and_grad(jnp.float32(t), plan, x0j, n0j, n1j, w)

    g = f(angle)[1]
    assert np.isfinite(float(g))
    h = 1e-2
    fd = (float(f(angle + h)[0]) - float(f(angle - h)[0])) / (2 * h)
    assert abs(float(g) - fd) < 0.02 * max(1.0, abs(fd))


def test_ist_neighbors_hands_back_the_held_table_for_the_same_deletions_and_refuses_another_clouds():
    x = sphere(300, seed=3)
    alive = np.ones(len(x), bool)
    cfg = ISTConfig()
    held = ist_neighbors(cfg, x, alive)
    assert ist_neighbors(cfg, x.astype(np.float64), alive, held) is held
    assert not (held.neighbors.flags.writeable or held.valid.flags.writeable or held.xyz0.flags.writeable)
    fewer = alive.copy()
    fewer[:40] = False  # an edit that deletes: a table of its own, as made on the spot
    made = ist_neighbors(cfg, x, fewer, held)
    spot = ist_neighbors(cfg, x, fewer)
    assert made is not held
    np.testing.assert_array_equal(made.neighbors, spot.neighbors)
    np.testing.assert_array_equal(made.valid, spot.valid)
    with pytest.raises(ValueError, match="another cloud.*other positions"):
        ist_neighbors(cfg, 1.01 * x, alive, held)
    with pytest.raises(ValueError, match="another cloud"):
        ist_neighbors(cfg, x[:-1], alive[:-1], held)
    with pytest.raises(ValueError, match="8 candidates"):
        ist_neighbors(cfg, x, alive, ist_neighbors(ISTConfig(candidates=4), x, alive))
    # plan_ist takes the table and chooses what it chooses without it
    n = estimate_normals(UNORIENTED, x)
    args = (x, n, x @ R.T, n @ R.T, alive, np.full(len(x), 0.5))
    jax.tree_util.tree_map(np.testing.assert_array_equal, plan_ist(cfg, *args, neighbors=held), plan_ist(cfg, *args))

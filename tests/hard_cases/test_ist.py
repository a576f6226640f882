"""Stages IST and edit (``ist_from_plan`` jitted, ``plan_ist`` / ``apply_edit`` host): the suite's
clouds (uniform, sphere, coplanar, collinear, duplicates, clusters, grid) at scales 1e-4, 1 and 1e4,
with deleted points, zero normals and confidences near 0 and 1, under a random rigid motion and under
a twist.

Asserted: every IST is finite and orthogonal with determinant +1 (float32 2e-5, float64 1e-10);
under a rigid rotation ``R`` every frame the plan calls good gives ``R^T`` and equals a float64 numpy
reference of the frame map's polar factor (float32 1e-4, float64 1e-9, absolute on entries of a
rotation); dead slots keep the identity; gradients w.r.t. the edited positions are finite;
``apply_edit`` keeps finite positions and unit (or zero, for dead slots) normals.

``apply_edit`` runs a fixed family of twists (:data:`TWISTS`): each edit compiles its own program.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from ne_jax.edit.apply import apply_edit
from ne_jax.edit.deformations import Edit, rotation_matrix, twist_points
from ne_jax.edit.ist import ISTConfig, ist_from_plan, plan_ist
from ne_jax.pointcloud.normals import NormalConfig, estimate_normals

from edit.reference import frame_map_polar

from .common import CLOUD_KINDS, DTYPE, HYP, X64, assert_finite, make_cloud, make_state

ORTHO = 1e-10 if X64 else 2e-5
MATCH = 1e-9 if X64 else 1e-4
CFG = ISTConfig(smooth_iters=0)  # smoothing would mix good frames with filled ones at boundaries


def _twist(rate, axis):
    return Edit("twist", "twist", lambda p: twist_points(p, (0.0, 0.0, 0.0), axis, rate))


_AXES = np.random.default_rng(7).normal(size=(8, 3))
TWISTS = [_twist(rate, axis) for rate, axis in zip((-2.0, -1.4, -0.7, -0.05, 0.05, 0.8, 1.5, 2.0), _AXES)]
"""Twists of rates across ``[-2, 2]`` about random axes."""


def normals_of(xyz, alive, zero_fraction=0.0, seed=0):
    n = np.zeros(xyz.shape, np.float64)
    idx = np.flatnonzero(alive)
    n[idx] = estimate_normals(NormalConfig(orient="none"), np.asarray(xyz, np.float64)[idx])
    if zero_fraction:
        n[idx[np.random.default_rng(seed).random(idx.size) < zero_fraction]] = 0.0
    return n


def run_ist(x0, n0, x1, n1, alive, conf):
    plan = plan_ist(CFG, x0, n0, x1, n1, alive, conf)
    args = [jnp.asarray(a, DTYPE) for a in (x0, n0, x1, n1)]
    ist, sign, counts = ist_from_plan(CFG, plan, *args)
    return plan, np.asarray(ist, np.float64), np.asarray(sign), args


def assert_rotations(ist, alive):
    assert np.isfinite(ist).all()
    gram = np.einsum("cji,cjk->cik", ist, ist)
    np.testing.assert_allclose(gram, np.broadcast_to(np.eye(3), gram.shape), atol=ORTHO)
    np.testing.assert_allclose(np.linalg.det(ist), 1.0, atol=3 * ORTHO)
    np.testing.assert_array_equal(ist[~alive], np.broadcast_to(np.eye(3), ist[~alive].shape))


@pytest.mark.parametrize("kind", CLOUD_KINDS)
@pytest.mark.parametrize("scale", [1e-4, 1.0, 1e4])
def test_rigid_motion_on_hard_clouds(kind, scale):
    rng = np.random.default_rng(hash((kind, scale)) % 2**32)
    xyz, alive = make_cloud(kind, 200, seed=3, scale=scale, deleted=0.2)
    x0 = np.asarray(xyz, np.float64)
    n0 = normals_of(x0, alive, zero_fraction=0.1)
    rot = np.asarray(rotation_matrix(rng.normal(size=3), rng.uniform(-np.pi, np.pi)), np.float64)
    rot = np.linalg.qr(rot)[0] * np.sign(np.diag(np.linalg.qr(rot)[1]))  # exactly orthogonal in float64
    x1 = x0 @ rot.T + scale * rng.normal(size=3)
    n1 = n0 @ rot.T
    conf = 1.0 / (1.0 + np.exp(-rng.choice([-30.0, 0.0, 30.0], size=len(x0))))
    plan, ist, sign, _ = run_ist(x0, n0, x1, n1, alive, conf)
    assert_rotations(ist, alive)
    assert np.isfinite(sign).all()
    good = np.asarray(plan.good)
    # the reference sees the same (dtype-rounded) inputs: a cluster 1e-3 wide at 1e-4 keeps only
    # ~1e-4 relative precision in float32 coordinates, which no algorithm can recover
    x0, n0, x1, n1 = (np.asarray(a, DTYPE).astype(np.float64) for a in (x0, n0, x1, n1))
    ref = frame_map_polar(x0, n0, x1, n1, np.asarray(plan.pair), good)
    np.testing.assert_allclose(ist[good], ref[good], atol=MATCH)
    # ... and the exact answer R^T within the precision the rounded coordinates allow
    spread = max(1.0, float(np.abs(x0[alive]).max() / scale / 1e-3) if kind == "clusters" else 1.0)
    np.testing.assert_allclose(ist[good], np.broadcast_to(rot.T, ist[good].shape), atol=MATCH * spread)


@jax.jit
def _ist_gradient(plan, x0, n0, x1, n1, w):
    """d sum(IST * w) / d edited positions (one program for every cloud)."""
    return jax.grad(lambda p: jnp.sum(ist_from_plan(CFG, plan, x0, n0, p, n1)[0] * w))(x1)


@pytest.mark.parametrize("kind", ["sphere", "coplanar", "collinear", "duplicates", "clusters"])
def test_gradients_w_r_t_edited_positions_are_finite(kind):
    xyz, alive = make_cloud(kind, 150, seed=5, deleted=0.1)
    x0 = np.asarray(xyz, np.float64)
    n0 = normals_of(x0, alive, zero_fraction=0.1)
    x1 = np.asarray(twist_points(jnp.asarray(x0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 0.8), np.float64)
    n1 = normals_of(x1, alive)
    plan, ist, _, args = run_ist(x0, n0, x1, n1, alive, np.full(len(x0), 0.5))
    assert_rotations(ist, alive)
    w = jnp.asarray(np.random.default_rng(0).normal(size=(len(x0), 3, 3)), DTYPE)
    grad = _ist_gradient(plan, *args, w)
    assert_finite(grad, f"{kind}: d IST / d positions")


@given(seed=st.integers(0, 2**16), kind=st.sampled_from(CLOUD_KINDS), deleted=st.sampled_from([0.0, 0.5, 0.95]),
       edit=st.sampled_from(TWISTS))
@HYP
def test_apply_edit_on_random_clouds_and_edits_is_finite(seed, kind, deleted, edit):
    rng = np.random.default_rng(seed)
    xyz, alive = make_cloud(kind, int(rng.integers(1, 200)), seed=seed, deleted=deleted)
    points = make_state(xyz, alive, seed=seed)
    points = points.replace(normal=jnp.asarray(normals_of(np.asarray(xyz, np.float64), alive), DTYPE))
    edited = apply_edit(points, edit)
    assert_finite(edited, f"{kind}: ")
    ist = np.asarray(edited.ist, np.float64)
    now = np.asarray(edited.alive)
    # the stored IST composes with make_state's random (non-orthogonal) one; the new part is a rotation
    assert np.isfinite(ist).all() and np.isfinite(np.asarray(edited.xyz)[now]).all()
    nrm = np.linalg.norm(np.asarray(edited.normal, np.float64)[now], axis=1)
    np.testing.assert_allclose(nrm, 1.0, atol=1e-5)

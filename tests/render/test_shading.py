"""The colour model: declared effects absent from the param tree and the traced program, the
identity-IST bit-for-bit contract, IST equivariance, finite gradients at hard inputs, and one
compilation for repeated calls."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ne_jax.render.ide import ide_dim
from ne_jax.render.shading import (
    Effects,
    ShadingConfig,
    background_color,
    init_color_model,
    shade,
    sphere_exit_point,
)

R, M, F = 3, 4, 32
REFNERF_ONLY = {"diffuse", "tint", "roughness", "bottleneck", "specular"}
SPECULAR = {"tint", "roughness", "bottleneck", "specular"}


def _inputs(seed=0, unit=False):
    rng = np.random.default_rng(seed)
    f = jnp.asarray(rng.normal(size=(R, M, F)), jnp.float32)
    n = rng.normal(size=(R, M, 3))
    d = rng.normal(size=(R, M, 3))
    if unit:
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
    ist = np.broadcast_to(np.eye(3), (R, M, 3, 3))
    return f, jnp.asarray(n, jnp.float32), jnp.asarray(d, jnp.float32), jnp.asarray(ist, jnp.float32)


def _cfg(**fx):
    return ShadingConfig(effects=Effects(**fx))


@functools.cache
def _params(cfg):
    return init_color_model(cfg, jax.random.key(0))


def _rotation(seed):
    q, r = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


# ---- effects: parameters ---------------------------------------------------------------------------


@pytest.mark.parametrize("fx,present,absent", [
    (dict(), {"trunk", "density", "normal"} | REFNERF_ONLY, {"traditional"}),
    (dict(specular=False), {"trunk", "density", "normal", "diffuse"}, SPECULAR | {"traditional"}),
    (dict(ist=True, point_normals=False), {"trunk"} | REFNERF_ONLY, {"traditional"}),
    (dict(specular=False, color_head="traditional"), {"trunk", "density", "normal", "traditional"},
     REFNERF_ONLY),
])
def test_param_tree_has_exactly_the_declared_branches(fx, present, absent):
    params = _params(_cfg(**fx))
    keys = set(params["shader"])
    assert present <= keys and not (absent & keys), keys
    assert "background" not in params


def test_sizes_match_design_facts():
    p = _params(_cfg())["shader"]
    assert p["trunk"]["in"]["kernel"].shape == (32, 48)
    assert p["trunk"]["res_1"]["kernel"].shape == (48, 48)
    assert p["bottleneck"]["kernel"].shape == (48, 128)
    assert p["specular"]["hidden_0"]["kernel"].shape == (128 + ide_dim(5) + 1, 48)
    assert p["specular"]["hidden_1"]["kernel"].shape == (48, 16)
    assert p["specular"]["out"]["kernel"].shape == (16, 3)
    assert p["tint"]["kernel"].shape == (48, 3) and p["roughness"]["kernel"].shape == (48, 1)


def test_background_sphere_params_only_when_declared():
    p = _params(_cfg(background_model="sphere"))
    assert "background" in p
    o = jnp.zeros((5, 3))
    d = jnp.asarray(np.random.default_rng(0).normal(size=(5, 3)), jnp.float32)
    c = np.asarray(background_color(_cfg(background_model="sphere"), p, o, d))
    assert c.shape == (5, 3) and np.all(c >= -0.001) and np.all(c <= 1.001)
    const = background_color(_cfg(), _params(_cfg()), o, d, constant=jnp.asarray([1.0, 0.5, 0.0]))
    np.testing.assert_array_equal(np.asarray(const), np.tile([1.0, 0.5, 0.0], (5, 1)))
    with pytest.raises(ValueError):
        background_color(_cfg(), _params(_cfg()), o, d)


# ---- effects: the traced program ---------------------------------------------------------------------


def _jaxpr(cfg):
    f, n, d, ist = _inputs()
    def fn(params, f, n, d, ist):
        return shade(cfg, params, f, n, d, ist)
    return jax.make_jaxpr(fn)(_params(cfg), f, n, d, ist)


def _used_invars(closed):
    jaxpr = closed.jaxpr
    used = {id(v) for e in jaxpr.eqns for v in e.invars if hasattr(v, "aval") and not hasattr(v, "val")}
    used |= {id(v) for v in jaxpr.outvars}
    return [id(v) in used for v in jaxpr.invars]


def _count(closed, name):
    """Occurrences of primitive ``name`` in a jaxpr, nested jaxprs (custom_jvp, pjit) included."""
    from jax.extend.core import subjaxprs

    def walk(jaxpr):
        return sum(e.primitive.name == name for e in jaxpr.eqns) + sum(walk(s) for s in subjaxprs(jaxpr))

    return walk(closed.jaxpr)


def _input_usage(cfg):
    """(normal used, view_dir used, ist used) from the jaxpr's input variables."""
    closed = _jaxpr(cfg)
    n_param_leaves = len(jax.tree_util.tree_leaves(_params(cfg)))
    used = _used_invars(closed)
    assert all(used[:n_param_leaves]), "every parameter of a declared branch is used"
    f_used, n_used, d_used, ist_used = used[n_param_leaves:]
    assert f_used
    return n_used, d_used, ist_used


@pytest.mark.parametrize("fx,expect", [
    (dict(), (True, True, False)),
    (dict(ist=True), (True, True, True)),
    (dict(point_normals=False), (False, True, False)),
    (dict(point_normals=False, ist=True), (False, True, True)),
    (dict(specular=False, ist=True), (False, False, False)),
    (dict(specular=False, color_head="traditional", ist=True), (False, True, True)),
])
def test_undeclared_inputs_are_not_in_the_program(fx, expect):
    assert _input_usage(_cfg(**fx)) == expect
    fxo = Effects(**fx)
    assert (fxo.uses_point_normals, fxo.uses_view_dir, fxo.uses_ist) == expect


def test_disabled_specular_is_absent_from_jaxpr_and_hlo():
    full, bare = _cfg(), _cfg(specular=False)
    def kernels(cfg):
        return sum(1 for path, _ in jax.tree_util.tree_flatten_with_path(_params(cfg))[0]
                   if path[-1].key == "kernel")
    for cfg in (full, bare):
        assert _count(_jaxpr(cfg), "dot_general") == kernels(cfg)
    assert kernels(full) == 14 and kernels(bare) == 8
    # no IDE: no exp of the attenuation, no sigmoid of the tint, in the lowered program either
    f, n, d, ist = _inputs()
    def hlo(cfg):
        return jax.jit(functools.partial(shade, cfg)).lower(_params(cfg), f, n, d, ist).as_text()
    assert hlo(full).count("dot_general") == 14 and hlo(bare).count("dot_general") == 8
    assert len(_jaxpr(bare).jaxpr.eqns) < len(_jaxpr(full).jaxpr.eqns) / 2


# ---- behaviour ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("fx", [dict(), dict(point_normals=False),
                                dict(specular=False, color_head="traditional")])
@pytest.mark.parametrize("jit", [False, True])
def test_identity_ist_is_the_unedited_result(fx, jit):
    f, n, d, ist = _inputs(seed=1)  # non-unit normals and directions on purpose
    plain, edited = _cfg(**fx), _cfg(ist=True, **fx)
    params = _params(plain)
    assert jax.tree_util.tree_structure(params) == jax.tree_util.tree_structure(_params(edited))
    run = (lambda cfg, *a: jax.jit(functools.partial(shade, cfg))(*a)) if jit else shade
    a = run(plain, params, f, n, d, None)
    b = run(edited, params, f, n, d, ist)
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        if jit:  # two compiled programs: XLA may fuse them differently, so they agree to float32 rounding
            np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-6, atol=1e-6)
        else:  # operation by operation, the identity IST changes nothing at all
            assert np.array_equal(np.asarray(x), np.asarray(y))


@pytest.mark.parametrize("fx", [dict(), dict(point_normals=False),
                                dict(specular=False, color_head="traditional")])
def test_rotation_ist_equals_unedited_shading_of_rotated_inputs(fx):
    """IST maps edited -> original frame: shading an edited segment with IST = Q equals shading the
    original segment seen along ``Q d`` with point normal ``Q n`` (reflection is equivariant)."""
    f, n, d, _ = _inputs(seed=2, unit=True)
    q = jnp.asarray(_rotation(3), jnp.float32)
    ist = jnp.broadcast_to(q, (R, M, 3, 3))
    plain, edited = _cfg(**fx), _cfg(ist=True, **fx)
    params = _params(plain)
    def rot(v):
        return jnp.einsum("ij,rmj->rmi", q, v)
    a = shade(edited, params, f, n, d, ist)
    b = shade(plain, params, f, rot(n), rot(d))
    np.testing.assert_allclose(np.asarray(a.rgb), np.asarray(b.rgb), atol=2e-6)


def test_view_independence_without_specular_and_normal_independence_without_point_normals():
    f, n, d, _ = _inputs(seed=4)
    _, n2, d2, _ = _inputs(seed=5)
    bare = _cfg(specular=False)
    a, b = shade(bare, _params(bare), f, n, d), shade(bare, _params(bare), f, n2, d2)
    assert np.array_equal(np.asarray(a.rgb), np.asarray(b.rgb))
    pred = _cfg(point_normals=False)
    a, b = shade(pred, _params(pred), f, n, d), shade(pred, _params(pred), f, n2, d)
    assert np.array_equal(np.asarray(a.rgb), np.asarray(b.rgb))
    full = _cfg()
    a, b = shade(full, _params(full), f, n, d), shade(full, _params(full), f, n2, d)
    assert not np.allclose(np.asarray(a.rgb), np.asarray(b.rgb))


def test_pred_normal_mix_blends_between_point_and_predicted():
    f, n, d, _ = _inputs(seed=6, unit=True)
    cfg, pred = _cfg(), _cfg(point_normals=False)
    p = _params(cfg)
    base = shade(cfg, p, f, n, d)
    np.testing.assert_allclose(np.asarray(shade(cfg, p, f, n, d, pred_normal_mix=0.0).rgb),
                               np.asarray(base.rgb), atol=1e-6)
    np.testing.assert_allclose(np.asarray(shade(cfg, p, f, n, d, pred_normal_mix=1.0).rgb),
                               np.asarray(shade(pred, p, f, n, d).rgb), atol=1e-6)


def test_outputs_ranges_and_color_formula():
    f, n, d, _ = _inputs(seed=7, unit=True)
    cfg = _cfg()
    p = _params(cfg)
    out = shade(cfg, p, f, n, d)
    assert out.sigma.shape == (R, M) and out.rgb.shape == (R, M, 3)
    assert np.all(np.asarray(out.sigma) > 0) and np.all(np.asarray(out.roughness) > 0)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(out.pred_normal), axis=-1), 1, atol=1e-6)
    rgb = np.asarray(out.rgb)
    assert np.all(rgb >= -0.001) and np.all(rgb <= 1.001)
    # c = sigmoid(0.5 diffuse + tint * specular) * 1.002 - 0.001, recomputed from the submodules
    from ne_jax.render.ide import integrated_dir_enc
    from ne_jax.render.shading import MLP, Trunk, reflect
    ps = p["shader"]
    h = Trunk(48).apply({"params": ps["trunk"]}, f)
    diffuse = MLP((16,), 3).apply({"params": ps["diffuse"]}, h)
    tint = jax.nn.sigmoid(h @ ps["tint"]["kernel"] + ps["tint"]["bias"])
    rough = jax.nn.softplus(h @ ps["roughness"]["kernel"] + ps["roughness"]["bias"] - 1.0)
    bott = jax.nn.elu(h @ ps["bottleneck"]["kernel"] + ps["bottleneck"]["bias"])
    nn_ = n / jnp.linalg.norm(n, axis=-1, keepdims=True)
    dd = d / jnp.linalg.norm(d, axis=-1, keepdims=True)
    spec_in = jnp.concatenate([bott, integrated_dir_enc(reflect(dd, nn_), rough),
                               jnp.sum(nn_ * dd, -1, keepdims=True)], -1)
    spec = MLP((48, 16), 3).apply({"params": ps["specular"]}, spec_in)
    want = jax.nn.sigmoid(0.5 * diffuse + tint * spec) * 1.002 - 0.001
    np.testing.assert_allclose(rgb, np.asarray(want), atol=2e-6)


def test_missing_inputs_and_bad_effects_raise():
    f, n, d, _ = _inputs()
    with pytest.raises(ValueError):
        shade(_cfg(), _params(_cfg()), f, None, d)
    with pytest.raises(ValueError):
        shade(_cfg(ist=True), _params(_cfg()), f, n, d, None)
    with pytest.raises(ValueError):
        Effects(color_head="traditional")  # specular belongs to the refnerf head
    with pytest.raises(ValueError):
        Effects(background_model="skybox")
    # inputs an effect does not read may be None
    shade(_cfg(point_normals=False), _params(_cfg()), f, None, d)


def test_sphere_exit_point():
    rng = np.random.default_rng(8)
    o = rng.uniform(-1, 1, size=(20, 3))
    d = rng.normal(size=(20, 3))
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    u = np.asarray(sphere_exit_point(jnp.asarray(o), jnp.asarray(d), 4.0), np.float64)
    for i in range(20):  # the far root of |o + t d| = 4, by the quadratic formula
        b = o[i] @ d[i]
        t = -b + np.sqrt(b * b - (o[i] @ o[i] - 16))
        np.testing.assert_allclose(u[i], (o[i] + t * d[i]) / 4, atol=2e-6)
    miss = np.asarray(sphere_exit_point(jnp.asarray([[10.0, 0, 0]]), jnp.asarray([[0.0, 1, 0]]), 4.0))
    np.testing.assert_array_equal(miss, [[0.0, 1, 0]])


# ---- gradients and compilation ----------------------------------------------------------------------


@pytest.mark.parametrize("fx", [dict(ist=True), dict(specular=False, color_head="traditional", ist=True)])
def test_gradients_finite_at_hard_inputs(fx):
    """Zero normal, zero view direction, zero (singular) IST, huge and zero features."""
    cfg = _cfg(**fx)
    f, n, d, ist = _inputs(seed=9)
    f = f.at[0, 0].set(0.0).at[0, 1].set(1e4)
    n = n.at[1, 0].set(0.0)
    d = d.at[1, 1].set(0.0)
    ist = ist.at[2, 0].set(0.0)

    def loss(params, f, n, ist):
        out = shade(cfg, params, f, n, d, ist)
        return jnp.mean((out.rgb - 0.3) ** 2) + jnp.mean(out.sigma) + jnp.mean(out.pred_normal[..., 2])

    grads = jax.jit(jax.grad(loss, argnums=(0, 1, 2, 3)))(_params(cfg), f, n, ist)
    for leaf in jax.tree_util.tree_leaves(grads):
        assert np.all(np.isfinite(np.asarray(leaf)))


def test_no_recompilation_on_repeated_calls():
    cfg = _cfg(ist=True)
    traces = []

    @jax.jit
    def run(params, f, n, d, ist):
        traces.append(1)
        return shade(cfg, params, f, n, d, ist).rgb

    p = _params(cfg)
    for seed in range(3):
        f, n, d, ist = _inputs(seed=seed)
        run(p, f, n, d, ist).block_until_ready()
    p2 = jax.tree_util.tree_map(lambda x: x + 1, p)
    run(p2, f, n, d, ist).block_until_ready()
    assert len(traces) == 1 and run._cache_size() == 1

"""The view-dependence probe's stand-in colour model: seen along the normal, whatever the camera."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from experiments.view_dependence import ViewFromNormal
from ne_jax.render.shading import Effects, ShadingConfig, init_color_model, shade


def _inputs(seed):
    rng = np.random.default_rng(seed)
    f = jnp.asarray(rng.normal(size=(5, 32)), jnp.float32)
    n = rng.normal(size=(5, 3))
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return f, jnp.asarray(n, jnp.float32), jnp.asarray(rng.normal(size=(5, 3)), jnp.float32)


def test_shades_as_seen_along_the_normal_and_ignores_the_camera():
    cfg = ShadingConfig(effects=Effects())
    params = init_color_model(cfg, jax.random.key(0))
    f, n, d = _inputs(0)
    _, _, d2 = _inputs(1)
    probe = ViewFromNormal(cfg)
    a, b = shade(probe, params, f, n, d), shade(probe, params, f, n, d2)
    assert np.array_equal(np.asarray(a.rgb), np.asarray(b.rgb))  # the camera no longer matters
    along = shade(cfg, params, f, n, -n)
    np.testing.assert_allclose(np.asarray(a.rgb), np.asarray(along.rgb), rtol=1e-6, atol=1e-7)
    assert not np.allclose(np.asarray(shade(cfg, params, f, n, d).rgb), np.asarray(a.rgb))
    assert hash(probe) == hash(ViewFromNormal(cfg))  # static: usable as a jit argument
    assert probe.effects == cfg.effects and probe.feature_dim == cfg.feature_dim

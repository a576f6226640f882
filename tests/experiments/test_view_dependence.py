"""The view-dependence probe's stand-in colour model: seen along the normal, whatever the camera."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from experiments.view_dependence import ViewFromNormal
from ne_jax.render.shading import Effects, ShadingConfig, init_color_model, shade

# One compiled program per colour model (flax's eager init and apply compile every operation apiece).
_init = jax.jit(init_color_model, static_argnums=0)
_shade = jax.jit(shade, static_argnums=0)


def _inputs(seed):
    rng = np.random.default_rng(seed)
    f = jnp.asarray(rng.normal(size=(5, 32)), jnp.float32)
    n = rng.normal(size=(5, 3))
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return f, jnp.asarray(n, jnp.float32), jnp.asarray(rng.normal(size=(5, 3)), jnp.float32)


def test_shades_as_seen_along_the_normal_and_ignores_the_camera():
    cfg = ShadingConfig(effects=Effects())
    params = _init(cfg, jax.random.key(0))
    f, n, d = _inputs(0)
    _, _, d2 = _inputs(1)
    probe = ViewFromNormal(cfg)
    a, b = _shade(probe, params, f, n, d), _shade(probe, params, f, n, d2)  # the probe as a jit argument
    assert np.array_equal(np.asarray(a.rgb), np.asarray(b.rgb))  # the camera no longer matters
    along = _shade(cfg, params, f, n, -n)
    np.testing.assert_allclose(np.asarray(a.rgb), np.asarray(along.rgb), rtol=1e-6, atol=1e-7)
    assert not np.allclose(np.asarray(_shade(cfg, params, f, n, d).rgb), np.asarray(a.rgb))
    assert hash(probe) == hash(ViewFromNormal(cfg))  # static: usable as a jit argument
    assert probe.effects == cfg.effects and probe.feature_dim == cfg.feature_dim

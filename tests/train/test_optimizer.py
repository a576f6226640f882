"""TrainConfig.optimizer: the confidence logits' steps scaled by confidence_lr, nothing else; the
per-point moments follow the cloud through a round with either optimizer state."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from ne_jax.geometry.points import PointState
from ne_jax.train.state import TrainConfig, TrainState

STEPS = 100
"""The length of the learning-rate schedule."""


def _tree(c=5):
    return {"params": {"w": jnp.ones((3, 2))},
            "points": {"feature": jnp.ones((c, 4)), "conf_logit": jnp.zeros((c,))}}


@pytest.mark.parametrize("k", [1.0, 10.0])
def test_confidence_steps_are_scaled_and_nothing_else(k):
    tree = _tree()
    grads = jax.tree_util.tree_map(lambda a: jnp.full_like(a, 0.3), tree)
    base, scaled = TrainConfig(lr=1e-2), TrainConfig(lr=1e-2, confidence_lr=k)
    u1, _ = base.optimizer(STEPS).update(grads, base.optimizer(STEPS).init(tree), tree)
    u2, _ = scaled.optimizer(STEPS).update(grads, scaled.optimizer(STEPS).init(tree), tree)
    np.testing.assert_allclose(np.asarray(u2["points"]["conf_logit"]), k * np.asarray(u1["points"]["conf_logit"]),
                               rtol=1e-6)
    for path in (("params", "w"), ("points", "feature")):
        np.testing.assert_array_equal(np.asarray(u2[path[0]][path[1]]), np.asarray(u1[path[0]][path[1]]))


def test_rejects_a_non_positive_rate():
    with pytest.raises(ValueError, match="confidence_lr"):
        TrainConfig(confidence_lr=0.0)


def test_moments_follow_a_grown_cloud_with_the_scaled_optimizer():
    cfg = TrainConfig(confidence_lr=10.0)
    tree = _tree(5)
    opt = cfg.optimizer(STEPS)
    grads = jax.tree_util.tree_map(jnp.ones_like, tree)
    _, opt_state = opt.update(grads, opt.init(tree), tree)
    state = TrainState(params=tree["params"], points=tree["points"], opt_state=opt_state,
                       step=jnp.zeros((), jnp.int32), key=jax.random.PRNGKey(0), skipped=jnp.zeros((), jnp.int32))
    grown = PointState.from_numpy(np.zeros((8, 3), np.float32), feature_dim=4)
    new = state.with_points(grown, np.arange(5, 8))
    mu = new.opt_state[0][0].mu["points"]["conf_logit"]  # chain((adam = (ScaleByAdam, ...)), scale)
    assert mu.shape == (8,) and np.all(np.asarray(mu[:5]) != 0) and np.all(np.asarray(mu[5:]) == 0)
    opt.update(jax.tree_util.tree_map(jnp.ones_like, new.trainables), new.opt_state, new.trainables)

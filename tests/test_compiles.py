"""count_compiles: a public count of backend compilations (jax.monitoring), no private JAX API."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ne_jax.compiles import count_compiles


def test_counts_a_first_call_and_not_a_repeated_one():
    fn = jax.jit(lambda x: jnp.sin(x) * 2.0 + 1.0)
    x, y = jnp.arange(5.0), jnp.ones(5)
    with count_compiles() as first:
        fn(x).block_until_ready()
    assert first.count >= 1 and any("<lambda>" in n for n in first.names) and first.seconds > 0
    with count_compiles() as again:
        fn(x).block_until_ready()
        fn(y).block_until_ready()  # same shape and dtype: served from the cache
    assert again.count == 0 and int(again) == 0 and again.names == []


def test_a_new_shape_compiles_again_and_blocks_nest():
    fn = jax.jit(lambda x: x * 3)
    fn(jnp.zeros(3)).block_until_ready()
    with count_compiles() as outer:
        with count_compiles() as inner:
            fn(jnp.zeros(4)).block_until_ready()  # a new shape
        fn(jnp.zeros(4)).block_until_ready()
    assert inner.names.count("jit(<lambda>)") == 1 and outer.names == inner.names


def test_the_listener_is_removed_after_the_block():
    with count_compiles() as done:
        pass
    jax.jit(lambda x: x - 7)(jnp.zeros(2)).block_until_ready()
    assert done.count == 0

"""Safe numerics: functions whose values *and gradients* stay finite at their hard inputs.

Every helper uses the double-``where`` pattern (the unsafe branch never sees a bad input, so its
gradient is never ``0 * inf = nan``). The rest of the code uses these instead of ad-hoc epsilons.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def tiny(dtype) -> float:
    """Smallest positive normal number of ``dtype`` (float32: ~1.2e-38)."""
    return float(jnp.finfo(dtype).tiny)


def safe_norm(x: jax.Array, axis: int = -1, keepdims: bool = False) -> jax.Array:
    """Euclidean norm along ``axis``; value 0 and gradient 0 (not NaN) at the zero vector.

    Computed as ``s * sqrt(sum((x / s)^2))`` with ``s = max|x_i|`` (held constant for the gradient,
    which is then exactly ``x / |x|``), so the squares neither overflow nor underflow: float32
    vectors longer than ~1.8e19 or shorter than ~1e-19 get their true norm (a plain ``sum(x^2)``
    gives ``inf`` or flushes to 0 there). Infinite components give ``inf``, NaN propagates."""
    scale = jax.lax.stop_gradient(jnp.max(jnp.abs(x), axis=axis, keepdims=True))
    ok = (scale > 0) & (scale < jnp.inf)
    s = jnp.where(ok, scale, 1.0)
    xs = x / s
    sq = jnp.sum(xs * xs, axis=axis, keepdims=True)
    norm = jnp.where(ok, s * jnp.sqrt(jnp.where(ok, sq, 1.0)), jnp.where(scale == 0, 0.0, scale))
    return norm if keepdims else jnp.squeeze(norm, axis=axis)


def safe_normalize(x: jax.Array, axis: int = -1, fallback: jax.Array | None = None) -> jax.Array:
    """``x / |x|`` along ``axis``; the zero vector maps to ``fallback`` (default: zeros), finite grad.

    Computed as ``(x / s) / |x / s|`` with ``s = max|x_i|`` held constant for the gradient (exact:
    the result does not depend on ``s``), so neither the value nor the Jacobian ``(I - u u^T) / |x|``
    overflows or underflows in between: it is finite wherever ``1 / |x|`` is representable."""
    scale = jax.lax.stop_gradient(jnp.max(jnp.abs(x), axis=axis, keepdims=True))
    is_zero = scale == 0
    xs = x / jnp.where(is_zero | (scale == jnp.inf), 1.0, scale)
    sq = jnp.sum(xs * xs, axis=axis, keepdims=True)
    unit = xs / jnp.sqrt(jnp.where(is_zero, 1.0, sq))
    if fallback is None:
        fallback = jnp.zeros_like(x)
    return jnp.where(is_zero, jnp.broadcast_to(fallback, x.shape), unit)


def safe_log(x: jax.Array) -> jax.Array:
    """``log(x)`` clamped below at the dtype's smallest normal: finite for ``x <= 0``, grad 0 there."""
    floor = tiny(x.dtype)
    ok = x > floor
    return jnp.where(ok, jnp.log(jnp.where(ok, x, 1.0)), jnp.log(jnp.asarray(floor, x.dtype)))


def safe_exp(x: jax.Array) -> jax.Array:
    """``exp(x)`` with ``x`` clamped so the result stays finite in ``x``'s dtype."""
    hi = float(jnp.log(jnp.finfo(x.dtype).max)) - 1.0
    return jnp.exp(jnp.minimum(x, hi))


def safe_div(num: jax.Array, den: jax.Array, fallback: float = 0.0) -> jax.Array:
    """``num / den`` where ``den != 0``, ``fallback`` where ``den == 0``; finite gradient everywhere."""
    ok = den != 0
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), fallback)


def safe_reciprocal(x: jax.Array, fallback: float = 0.0) -> jax.Array:
    """``1 / x`` where ``|x|`` is at least the dtype's smallest normal (so the result is finite),
    ``fallback`` elsewhere — including ``0.0``, ``-0.0`` and denormals, whose reciprocal would be
    ``inf``. Gradient ``-1/x^2`` on the safe side, 0 on the fallback side; it overflows to ``-inf``
    for ``|x| < sqrt(tiny)`` (float32 ~1.1e-19), so callers that differentiate through it must treat
    those inputs as the fallback case themselves (``intersect`` does).

    Ray-box slab tests use this for ray directions: a component that gets the fallback is treated as
    exactly parallel to the slab by the caller, never multiplied through as ``0 * inf = nan``."""
    ok = jnp.abs(x) >= tiny(x.dtype)
    return jnp.where(ok, 1.0 / jnp.where(ok, x, 1.0), jnp.asarray(fallback, x.dtype))


# --- added with the rendering pieces (ne_jax/render) -------------------------------------------


def safe_sqrt(x: jax.Array) -> jax.Array:
    """``sqrt(x)`` for ``x > 0`` (above the dtype's smallest normal), 0 elsewhere; value and gradient
    finite everywhere (the gradient is 0 where the result is 0, never ``inf`` at ``x = 0``)."""
    ok = x > tiny(x.dtype)
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, x, 1.0)), jnp.zeros_like(x))


def stable_ranks(key: jax.Array) -> jax.Array:
    """``[..., n]`` int32: each entry's place in a stable ascending sort of ``key [..., n]`` (the
    entries smaller, plus the equal ones before it: ties keep their order, as ``lax.top_k`` and a
    stable ``lax.sort`` break them). ``n**2`` comparisons that XLA:CPU vectorises, which beats
    ``top_k`` and ``sort`` there for ``n`` up to about 32."""
    slot = jnp.arange(key.shape[-1])
    other, this = key[..., None, :], key[..., :, None]
    before = (other < this) | ((other == this) & (slot[None, :] < slot[:, None]))
    return jnp.sum(before, axis=-1, dtype=jnp.int32)

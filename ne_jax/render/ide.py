"""Ref-NeRF's integrated directional encoding (IDE) and a NeRF positional encoding.

``IDE(w, r)_{l,m} = exp(-l(l+1)/2 * r) * Y_l^m(w)`` for the degrees ``l = 1, 2, 4, ..., 2^(deg-1)``
and orders ``m = 0..l`` (Ref-NeRF, Verbin et al. 2022, eq. 7 with roughness ``r = 1/kappa``); the
complex harmonics are returned as ``[Re, Im]``, so degree 5 gives ``2 * 36 = 72`` dims (the ``m = 0``
imaginary parts are identically 0 and kept, as in Ref-NeRF and the released code).

``Y_l^m`` (orthonormal, Condon-Shortley phase, as scipy's ``sph_harm_y``) is evaluated without
trigonometry as ``(x + i y)^m * Q_l^m(z)`` with ``(x+iy)^m = sin^m(theta) e^{i m phi}`` and
``Q_l^m = N_l^m (-1)^m d^m P_l/dz^m``. Ref-NeRF expands ``Q_l^m`` in monomials ``z^k`` (coefficients
up to ~1e5 for ``l = 16``, which cancel: ~1e-2 absolute error in float32); here ``Q_l^m`` comes from
the stable three-term recurrence in ``l`` (``(l-m) P_l^m = (2l-1) z P_{l-1}^m - (l+m-1) P_{l-2}^m``)
with the normalisations ``N_l^m`` folded into per-step constants built on the host with
``math.factorial`` (float64, cached): ~1e-6 absolute error in float32 for every degree used.
``(x + i y)^m`` is formed by real recurrences (no complex dtypes on device).
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

MAX_DEGREE = 5
"""Highest supported encoding degree (``l`` up to 16); higher degrees lose float32 accuracy."""


def ide_orders(degree: int = 5) -> tuple[tuple[int, int], ...]:
    """The ``(l, m)`` pairs of the encoding, in output order: ``l = 2^i`` for ``i < degree``, ``m = 0..l``."""
    if not 1 <= degree <= MAX_DEGREE:
        raise ValueError(f"IDE degree must be in [1, {MAX_DEGREE}], got {degree}")
    return tuple((2**i, m) for i in range(degree) for m in range(2**i + 1))


def ide_dim(degree: int = 5) -> int:
    """Output width of ``integrated_dir_enc`` (degree 5: 72)."""
    return 2 * len(ide_orders(degree))


def _norm(l: int, m: int) -> float:
    """``N_l^m = sqrt((2l+1)/(4 pi) (l-m)!/(l+m)!)`` in float64."""
    return math.sqrt((2 * l + 1) / (4 * math.pi) * math.factorial(l - m) / math.factorial(l + m))


def _double_factorial(n: int) -> int:
    return math.prod(range(n, 0, -2)) if n > 0 else 1


@functools.cache
def ide_tables(degree: int = 5) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Host float64 tables for ``l_max = 2^(degree-1)``, ``m = 0..l_max`` along the last axis:
    ``seed [l_max+1]`` (``Q_m^m = N_m^m (-1)^m (2m-1)!!``), recurrence constants ``a, b [l_max+1, l_max+1]``
    (row ``l``: ``Q_l^m = a z Q_{l-1}^m - b Q_{l-2}^m`` for ``l > m``), and for the outputs the
    column ``(l, m)`` selectors ``ls, ms [N]``."""
    lm = ide_orders(degree)
    l_max = 2 ** (degree - 1)
    seed = np.asarray([_norm(m, m) * (-1) ** m * _double_factorial(2 * m - 1)
                       for m in range(l_max + 1)])
    a = np.zeros((l_max + 1, l_max + 1))
    b = np.zeros((l_max + 1, l_max + 1))
    for l in range(1, l_max + 1):
        for m in range(l):
            a[l, m] = (2 * l - 1) / (l - m) * _norm(l, m) / _norm(l - 1, m)
            if l - 2 >= m:
                b[l, m] = (l + m - 1) / (l - m) * _norm(l, m) / _norm(l - 2, m)
    ls = np.asarray([l for l, _ in lm])
    ms = np.asarray([m for _, m in lm])
    for arr in (seed, a, b, ls, ms):
        arr.setflags(write=False)
    return seed, a, b, ls, ms


def attenuation_exponents(degree: int = 5) -> np.ndarray:
    """``l(l+1)/2`` per ``(l, m)`` output column ``[N]`` (float64)."""
    return np.asarray([0.5 * l * (l + 1) for l, _ in ide_orders(degree)])


def _legendre_q(z: jax.Array, degree: int) -> list[jax.Array]:
    """``[Q_l^m(z) for l in 0..l_max]``, each ``[..., l_max+1]`` over ``m`` (0 where ``m > l``)."""
    seed, a, b, _, _ = ide_tables(degree)
    l_max = seed.shape[0] - 1
    dtype = z.dtype
    m = np.arange(l_max + 1)
    seed_d = jnp.asarray(seed, dtype)
    q = [jnp.where(jnp.asarray(m == 0), seed_d, 0.0) * jnp.ones_like(z)]  # l = 0
    for l in range(1, l_max + 1):
        prev2 = q[-2] if l >= 2 else jnp.zeros_like(q[-1])
        step = jnp.asarray(a[l], dtype) * z * q[-1] - jnp.asarray(b[l], dtype) * prev2
        q.append(jnp.where(jnp.asarray(m == l), seed_d, jnp.where(jnp.asarray(m < l), step, 0.0)))
    return q


def integrated_dir_enc(direction: jax.Array, roughness: jax.Array, degree: int = 5) -> jax.Array:
    """IDE of unit directions ``[..., 3]`` with roughness ``[..., 1]`` (or ``[...]``) -> ``[..., ide_dim]``.

    Output layout: ``[Re Y * att for (l, m) in ide_orders] + [Im Y * att ...]`` with
    ``att = exp(-l(l+1)/2 * roughness)``. ``roughness = 0`` gives the plain spherical harmonics."""
    _, _, _, ls, ms = ide_tables(degree)
    dtype = direction.dtype
    roughness = jnp.asarray(roughness, dtype)
    if roughness.ndim == direction.ndim - 1:
        roughness = roughness[..., None]
    x, y, z = direction[..., 0:1], direction[..., 1:2], direction[..., 2:3]
    re, im = [jnp.ones_like(x)], [jnp.zeros_like(x)]
    for _ in range(int(ms.max())):  # (x + i y)^(m+1) = (x + i y)^m (x + i y)
        re, im = re + [re[-1] * x - im[-1] * y], im + [re[-1] * y + im[-1] * x]
    # Static column selection with lax-level slices: fancy indexing by a numpy array mixes int32 and
    # int64 index arithmetic when float64 is switched on in a process that already traced float32.
    re = jnp.concatenate([re[m] for m in ms], axis=-1)
    im = jnp.concatenate([im[m] for m in ms], axis=-1)
    q = _legendre_q(z, degree)
    legendre = jnp.concatenate([q[l][..., m:m + 1] for l, m in zip(ls, ms)], axis=-1)
    att = jnp.exp(-jnp.asarray(attenuation_exponents(degree), dtype) * roughness)
    scale = legendre * att
    return jnp.concatenate([re * scale, im * scale], axis=-1)


def positional_encoding(x: jax.Array, num_freqs: int, include_input: bool = True) -> jax.Array:
    """NeRF encoding ``[x, sin(2^k pi x), cos(2^k pi x) for k < num_freqs]``: ``[..., D]`` ->
    ``[..., D (include_input + 2 num_freqs)]``."""
    freqs = jnp.asarray(np.pi * 2.0 ** np.arange(num_freqs), x.dtype)
    xb = (x[..., None, :] * freqs[:, None]).reshape(*x.shape[:-1], -1)
    parts = [x] if include_input else []
    return jnp.concatenate(parts + [jnp.sin(xb), jnp.cos(xb)], axis=-1)

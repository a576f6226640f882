"""Fixed quadrature rules for the per-segment means (data flow steps 3 and 5 of docs/design.md).

A segment ``[t_lo, t_hi]`` is sampled at ``s`` evenly spaced points with both end points
(``u_j = j / (s-1)``); the segment mean of a field is approximated by ``w . y`` with weights ``w [s]``
that sum to 1. For every deterministic rule the mean of the rule's interpolant is a *linear*
functional of the samples, so the weights are computed once per ``(s, rule)`` on the host
(numpy float64, cached) and integration is a weighted sum (``integrate``).

Rules (``h = 1/(s-1)`` in segment units; "degree" = highest polynomial degree integrated exactly,
"order" = exponent ``p`` of the error ``O(h^p)`` on smooth fields, measured in ``tests/render``):

* ``"hermite"`` — the released code's rule: piecewise cubic Hermite interpolant whose node
  derivatives are secant averages. Integrated, the interior derivatives telescope and the rule is
  the trapezoid rule plus the end correction ``h^2/12 (m_first - m_last)``; only the end derivatives
  matter. The released code takes them as one-sided secants ``m_0 = (y_1 - y_0)/h``,
  ``m_last = (y_{s-1} - y_{s-2})/h``; with these the weights are ``h (5/12, 13/12, 1, ..., 1, 13/12,
  5/12)``. The secants are first-order accurate with errors of opposite sign at the two ends
  (``+h/2 f''(a)``, ``-h/2 f''(b)``), so the rule's error is ``h^3/24 (f''(a) + f''(b)) + O(h^4)``:
  degree 1 (not even quadratics), order 3.
* ``"hermite_o4"`` — same correction with second-order one-sided end derivatives
  ``m_0 = (-3 y_0 + 4 y_1 - y_2) / (2h)`` (mirrored at the end): Gregory's end-corrected trapezoid;
  degree 3, order 4 (the Euler-Maclaurin ``h^4`` term is the floor). ``s = 3`` gives Simpson.
* ``"spline"`` — mean of the not-a-knot cubic spline through the samples (scipy ``CubicSpline``,
  weights by integrating the spline of each unit basis vector): degree 3, order 4.
* ``"spline_natural"`` — natural cubic spline (zero second derivative at the ends): degree 1; the
  wrong end condition makes an ``O(h^2)`` interpolation error confined to ``O(h)`` next to the ends
  (it decays geometrically inwards), so the mean is off by ``O(h^3)``: order 3.
* ``"trapezoid"`` — degree 1, order 2.
* ``"stochastic"`` — the paper's ablation baseline: stratified random positions (one uniform sample in
  each of ``s`` equal bins, NeRF-style jitter; needs a PRNG key) and the plain mean ``1/s``. Unbiased;
  RMS error ``O(s^-1.5)`` on smooth fields.

For ``s == 1`` every rule is the single sample; for ``s == 2`` every deterministic rule is the
trapezoid rule (``"hermite_o4"`` needs ``s >= 3`` for its end stencils and falls back to it).

Per-level tables: segments of different K-D levels use different ``s`` (facts list:
``s = 8, 11, 16, 22, 22`` bottom level first). ``level_table`` pads every level to ``S = max(s)``
slots (padded slots repeat the end point and carry weight 0), so one fixed-shape sample array serves
all levels and a gather by level picks each segment's fractions and weights.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from scipy.interpolate import CubicSpline

RULES: tuple[str, ...] = (
    "hermite",
    "hermite_o4",
    "spline",
    "spline_natural",
    "trapezoid",
    "stochastic",
)
"""Every rule name accepted by this module."""

DETERMINISTIC_RULES: tuple[str, ...] = tuple(r for r in RULES if r != "stochastic")

EXACT_DEGREE: dict[str, int] = {
    "hermite": 1,
    "hermite_o4": 3,
    "spline": 3,
    "spline_natural": 1,
    "trapezoid": 1,
}
"""Highest polynomial degree each deterministic rule integrates exactly (for ``s >= 4``)."""


def _check(s: int, rule: str) -> None:
    if rule not in RULES:
        raise ValueError(f"unknown quadrature rule {rule!r}; expected one of {RULES}")
    if int(s) != s or s < 1:
        raise ValueError(f"samples per segment must be a positive int, got {s!r}")


def _trapezoid(s: int) -> np.ndarray:
    h = 1.0 / (s - 1)
    w = np.full(s, h)
    w[0] = w[-1] = 0.5 * h
    return w


@functools.cache
def _weights(s: int, rule: str) -> np.ndarray:
    _check(s, rule)
    if s == 1:
        w = np.ones(1)
    elif rule == "stochastic":
        w = np.full(s, 1.0 / s)
    elif s == 2 or rule == "trapezoid" or (rule == "hermite_o4" and s < 3):
        w = _trapezoid(s)
    elif rule in ("hermite", "hermite_o4"):
        h = 1.0 / (s - 1)
        # derivative stencils (coefficients of y, already divided by h): m = D @ y
        d_first = np.zeros(s)
        d_last = np.zeros(s)
        if rule == "hermite":
            d_first[:2] = np.array([-1.0, 1.0]) / h
            d_last[-2:] = np.array([-1.0, 1.0]) / h
        else:
            d_first[:3] = np.array([-3.0, 4.0, -1.0]) / (2.0 * h)
            d_last[-3:] = np.array([1.0, -4.0, 3.0]) / (2.0 * h)
        w = _trapezoid(s) + h * h / 12.0 * (d_first - d_last)
    else:  # cubic splines
        bc = "not-a-knot" if rule == "spline" else "natural"
        x = np.linspace(0.0, 1.0, s)
        w = CubicSpline(x, np.eye(s), axis=0, bc_type=bc).integrate(0.0, 1.0)
    w = np.asarray(w, np.float64)
    w.setflags(write=False)
    return w


def quadrature_weights(s: int, rule: str = "hermite") -> np.ndarray:
    """Host weights ``[s]`` float64 (read-only, cached), ``sum == 1``: ``w . y`` is the segment mean
    of the rule's interpolant through samples at ``u = linspace(0, 1, s)`` (random for stochastic)."""
    return _weights(int(s), rule)


def sample_fractions(s: int, rule: str = "hermite", key: jax.Array | None = None,
                     shape: tuple[int, ...] = (), dtype=None) -> jax.Array:
    """Sample positions as fractions of the segment, ``[*shape, s]`` in ``[0, 1]``, increasing.

    Deterministic rules: ``linspace(0, 1, s)`` (broadcast). ``"stochastic"``: ``(j + U_j) / s`` with
    ``U ~ Uniform[0, 1)`` from ``key`` (required), independent per segment and slot."""
    _check(s, rule)
    dtype = dtype or jnp.result_type(float)
    if rule == "stochastic":
        if key is None:
            raise ValueError("the stochastic rule needs a PRNG key")
        jitter = jax.random.uniform(key, (*shape, s), dtype)
        return (jnp.arange(s, dtype=dtype) + jitter) / s
    u = jnp.asarray(np.linspace(0.0, 1.0, s), dtype)
    return jnp.broadcast_to(u, (*shape, s))


def positions_from_fractions(t_lo: jax.Array, t_hi: jax.Array, u: jax.Array) -> jax.Array:
    """``t [..., S]`` at fractions ``u`` of ``[t_lo, t_hi]``: ``t_lo + u L`` for ``u <= 1/2`` and
    ``t_hi - (1 - u) L`` above (``L = t_hi - t_lo``), so both end points are exact and a zero-length
    segment gives exactly ``t_lo`` everywhere."""
    lo, hi = t_lo[..., None], t_hi[..., None]
    span = hi - lo
    return jnp.where(u <= 0.5, lo + u * span, hi - (1 - u) * span)


def sample_positions(t_lo: jax.Array, t_hi: jax.Array, s: int, rule: str = "hermite",
                     key: jax.Array | None = None) -> jax.Array:
    """Distances ``t [..., s]`` of the samples of segments ``[t_lo, t_hi]`` (each ``[...]``).

    Use with ``quadrature_weights(s, rule)``; a zero-length segment gives ``s`` equal positions."""
    t_lo = jnp.asarray(t_lo)
    t_hi = jnp.asarray(t_hi)
    u = sample_fractions(s, rule, key, jnp.broadcast_shapes(t_lo.shape, t_hi.shape),
                         jnp.result_type(t_lo, t_hi))
    return positions_from_fractions(t_lo, t_hi, u)


def integrate(values: jax.Array, weights, axis: int = -2) -> jax.Array:
    """Weighted sum over the sample axis: the segment means.

    ``values [..., s, *trailing]`` (``axis`` names the sample axis, default ``-2`` for ``[..., s, D]``;
    use ``axis=-3`` for IST matrices ``[..., s, 3, 3]``). ``weights`` is ``[s]`` (one rule for all
    segments) or ``[..., s]`` (per segment, broadcasting against the leading dims, e.g. rows of a
    ``level_table``). Returns ``values`` without the sample axis. Full float precision on every
    backend (no TF32)."""
    values = jnp.asarray(values)
    axis = axis % values.ndim
    lead = values.shape[:axis]
    s = values.shape[axis]
    trailing = values.shape[axis + 1:]
    w = jnp.asarray(weights, values.dtype)
    if w.shape[-1] != s:
        raise ValueError(f"weights have {w.shape[-1]} samples, values {s}")
    v = values.reshape(*lead, s, -1)
    if w.ndim == 1:
        out = jnp.einsum("...sd,s->...d", v, w, precision=lax.Precision.HIGHEST)
    else:
        w = jnp.broadcast_to(w, (*lead, s))
        out = jnp.einsum("...sd,...s->...d", v, w, precision=lax.Precision.HIGHEST)
    return out.reshape(*lead, *trailing)


@dataclasses.dataclass(frozen=True)
class QuadratureConfig:
    """Static quadrature settings of a scene (hashable: usable as a jit static argument)."""

    rule: str = "hermite"
    """One of ``RULES``; the released code's rule by default."""
    samples_per_level: tuple[int, ...] = (8, 11, 16, 22, 22)
    """``s`` per rendering level, bottom level first (facts list; the 5th is the growing level)."""

    def __post_init__(self):
        for s in self.samples_per_level:
            _check(s, self.rule)

    @property
    def max_samples(self) -> int:
        """``S``: the padded number of sample slots of every segment."""
        return max(self.samples_per_level)


def at_test_time(cfg: QuadratureConfig) -> QuadratureConfig:
    """The rule a model is rendered with outside training: ``cfg`` itself for deterministic rules;
    for ``"stochastic"`` the trapezoid rule on the same samples per level (evenly spaced samples,
    equal inner weights: NeRF's un-jittered test-time sampling, the expectation of the stratified
    draws up to the end points)."""
    if cfg.rule != "stochastic":
        return cfg
    return dataclasses.replace(cfg, rule="trapezoid")


@functools.cache
def _level_table(rule: str, samples: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    big = max(samples)
    u = np.ones((len(samples), big))
    w = np.zeros((len(samples), big))
    for i, s in enumerate(samples):
        u[i, :s] = np.linspace(0.0, 1.0, s) if s > 1 else 0.5
        w[i, :s] = quadrature_weights(s, rule)
    u.setflags(write=False)
    w.setflags(write=False)
    return u, w


def level_table(cfg: QuadratureConfig) -> tuple[np.ndarray, np.ndarray]:
    """Host tables ``(u [L, S], w [L, S])`` float64: fractions and weights per level, padded slots
    at ``u = 1`` with weight 0 (a single-sample level samples the midpoint)."""
    return _level_table(cfg.rule, tuple(int(s) for s in cfg.samples_per_level))


def _bins(cfg: QuadratureConfig, level_index: jax.Array, dtype, offset) -> tuple[jax.Array, jax.Array, jax.Array]:
    """``s`` equal bins per segment: ``(u [..., S], inside [..., S], s [..., 1])`` with sample ``j`` at
    fraction ``(j + offset_j) / s``; padded slots ``j >= s`` at ``u = 1``."""
    samples = tuple(int(v) for v in cfg.samples_per_level)
    idx = jnp.clip(jnp.asarray(level_index), 0, len(samples) - 1)
    s = jnp.asarray(samples, dtype)[idx][..., None]
    j = jnp.arange(cfg.max_samples, dtype=dtype)
    inside = j < s
    return jnp.where(inside, (j + offset) / s, 1.0), inside, s


def _jitter(cfg: QuadratureConfig, level_index: jax.Array, dtype, key) -> jax.Array:
    """The stratified draws ``U [..., S] ~ Uniform[0, 1)`` of the stochastic rule (one per bin)."""
    if key is None:
        raise ValueError("the stochastic rule needs a PRNG key")
    return jax.random.uniform(key, (*jnp.shape(level_index), cfg.max_samples), dtype)


def level_samples(cfg: QuadratureConfig, t_lo: jax.Array, t_hi: jax.Array,
                  level_index: jax.Array, key: jax.Array | None = None
                  ) -> tuple[jax.Array, jax.Array]:
    """Sample distances and weights of segments of mixed levels: ``(t [..., S], w [..., S])``.

    ``level_index [...]`` int indexes ``cfg.samples_per_level`` (0 = bottom rendering level; values
    outside ``[0, L)`` are clipped — mask invalid slots downstream). Padded slots get weight 0. For
    ``"stochastic"`` the first ``s`` slots of each segment are stratified over ``s`` bins."""
    t_lo = jnp.asarray(t_lo)
    dtype = jnp.result_type(t_lo, t_hi)
    if cfg.rule == "stochastic":
        u, inside, s = _bins(cfg, level_index, dtype, _jitter(cfg, level_index, dtype, key))
        w = jnp.where(inside, 1.0 / s, 0.0)
    else:
        u_tab, w_tab = level_table(cfg)
        idx = jnp.clip(jnp.asarray(level_index), 0, len(cfg.samples_per_level) - 1)
        u = jnp.asarray(u_tab, dtype)[idx]
        w = jnp.asarray(w_tab, dtype)[idx]
    return positions_from_fractions(t_lo, jnp.asarray(t_hi), u), w


def sample_intervals(cfg: QuadratureConfig, t_lo: jax.Array, t_hi: jax.Array, level_index: jax.Array,
                     key: jax.Array | None = None) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Sample positions of the renderer's point-sampling mode (``integration="samples"``):
    ``(t [..., S], inside [..., S], s [..., 1])`` for segments ``[t_lo, t_hi]`` (``[...]``) of levels
    ``level_index`` (clipped as in :func:`level_samples`); ``s`` the samples of each segment.

    A segment with ``s`` samples owns ``s`` equal sub-intervals; sample ``j`` lies at fraction
    ``(j + 1/2) / s`` (deterministic rules) or ``(j + U_j) / s`` (``"stochastic"``: the same draws,
    hence the same positions, as :func:`level_samples` with that key). Padded slots ``j >= s`` sit at
    ``t_hi`` with ``inside`` False."""
    t_lo = jnp.asarray(t_lo)
    dtype = jnp.result_type(t_lo, t_hi)
    offset = _jitter(cfg, level_index, dtype, key) if cfg.rule == "stochastic" else jnp.asarray(0.5, dtype)
    u, inside, s = _bins(cfg, level_index, dtype, offset)
    return positions_from_fractions(t_lo, jnp.asarray(t_hi), u), inside, s

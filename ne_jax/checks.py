"""Runtime finiteness checks an experiment can switch on: the first non-finite value, named by stage.

Built on :mod:`jax.experimental.checkify` (user checks). Off, they cost nothing: the flag is a static
Python bool, and :func:`stage_check` returns before tracing anything, so the compiled program is the
one without checks. On, every checked array gets one ``checkify.check`` ("all finite"), and the
first failing check in program order -- the first stage that saw a NaN or Inf -- is raised as a
:class:`NonFiniteError` naming the stage, the array, and the first bad element and its value.

Usage::

    cfg = RenderConfig(checks=True)
    render_chunked(cfg, params, scene, rays, bg)         # raises NonFiniteError on a NaN / Inf
    make_train_step(train_cfg, cfg, total_steps=n)(state, scene, batch)  # the same for the training step

Inside a function (under ``checks``)::

    stage_check(cfg.checks, "shading", sigma=sigma, rgb=rgb)

and to run such a function: ``checked(fn)`` (jitted, checkified, throws). Rendering stages, in
order: ``traversal`` (ray origins / directions and the valid segments' ``t_lo``/``t_hi``),
``interpolation`` (the integrated or interpolated means), ``shading`` (``sigma``, ``rgb``),
``compositing`` (``rgb``, ``opacity``, ``depth``); the training step adds ``loss/<term>``,
``backward`` (gradients) and ``update`` (the updated trainables).

Calling :func:`~ne_jax.render.renderer.render_rays` yourself with ``checks`` on: wrap the function
that calls it in :func:`checked` (a plain ``jax.jit`` refuses an un-functionalized check).

Message format (one line; the index is the flat row-major index into the named array, whose shape
is given; in the segment arrays of the render a row is a packed segment slot, not a ray)::

    non-finite value at stage 'traversal': origin[shape (64, 3)] first at flat index 15 = nan (`check` failed)
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jax.experimental import checkify


class NonFiniteError(FloatingPointError):
    """A NaN or Inf found by a switched-on stage check; the message names the stage and the array."""


def stage_check(enabled: bool, stage: str, *, where=None, **arrays) -> None:
    """When ``enabled`` (static), check that every array (or pytree of arrays) in ``arrays`` is finite.

    One ``checkify.check`` per float leaf; its message names ``stage``, the array (keyword name, plus
    the leaf's path in a pytree), its shape, the first non-finite flat (row-major) index and its
    value. ``None`` values, empty and non-float arrays are skipped. ``where``: a bool mask
    of the arrays' leading dimensions; only its True elements are checked (slots that may
    legitimately hold Inf, e.g. invalid segments, are left out; the mask is built only when
    ``enabled``, so it costs nothing when off). Must run under
    :func:`checkify.checkify` (e.g. via :func:`checked`); with ``enabled`` False it does nothing."""
    if not enabled:
        return
    for name, tree in arrays.items():
        items = [(path, jnp.asarray(leaf)) for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]]
        items = [(path, a) for path, a in items if a.size and jnp.issubdtype(a.dtype, jnp.inexact)]
        if not items:
            continue
        if where is not None:
            items = [(path, jnp.where(jnp.reshape(where, where.shape + (1,) * (a.ndim - where.ndim)), a, 0))
                     for path, a in items]
        # one search for the first bad element over all leaves (ravelled in leaf order); each leaf's
        # check reports it relative to the leaf, which is right for the first failing leaf -- the
        # one checkify reports (an argmax per leaf would cost compile time per leaf)
        dtype = jnp.result_type(*(a.dtype for _, a in items))
        flat = jnp.concatenate([a.reshape(-1).astype(dtype) for _, a in items])
        g = jnp.argmax(~jnp.isfinite(flat))
        value = flat[g]
        offset = 0
        for path, a in items:
            i = g - offset
            offset += a.size
            label = name + jax.tree_util.keystr(path)
            message = (f"non-finite value at stage '{stage}': {label}[shape {tuple(a.shape)}] first at flat "
                       "index {i} = {value}")
            _check_finite(message, jnp.all(jnp.isfinite(a)), i, value)


@functools.partial(jax.jit, static_argnums=0)
def _check_finite(message: str, ok, i, value) -> None:
    """``checkify.check(ok, message, i=i, value=value)`` in a program of its own whose arguments are
    ``ok``, ``i`` and ``value``. Building a check describes each formatting argument (JAX 0.10's
    ``ShapeDtypeStruct.like`` reads a tracer's ``sharding``, and the tracer's ``AttributeError``
    prints the equations of its program that read a constant); in the caller's trace those are whole
    nested programs, most of the time a checked training step took to trace
    (docs/decisions.md, runtime checks)."""
    checkify.check(ok, message, i=i, value=value)


def throw(err: checkify.Error) -> None:
    """Raise ``err``'s first failed check as a :class:`NonFiniteError` (nothing when none failed)."""
    msg = err.get()
    if msg is not None:
        raise NonFiniteError(msg)


def checked(fn, **jit_kwargs):
    """``fn`` jitted under ``checkify.checkify(..., errors=checkify.user_checks)``: same arguments,
    same results, and a :class:`NonFiniteError` when a :func:`stage_check` inside failed.
    ``jit_kwargs`` go to :func:`jax.jit` (static arguments are not allowed: close over them)."""
    run = jax.jit(checkify.checkify(fn, errors=checkify.user_checks), **jit_kwargs)

    def wrapper(*args, **kwargs):
        err, out = run(*args, **kwargs)
        throw(err)
        return out

    wrapper.__wrapped__ = fn
    wrapper.jitted = run
    return wrapper


__all__ = ["NonFiniteError", "checked", "stage_check", "throw"]

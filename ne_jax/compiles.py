"""Counting XLA compilations with JAX's public monitoring hooks (house habit 9: prove that nothing
recompiles).

``with count_compiles() as c: ...`` then ``c.count`` is the number of backend compilations that
ran inside the block and ``c.names`` the names of the functions compiled, in order. It listens to
the duration event JAX records around every backend compilation (:data:`BACKEND_COMPILE_EVENT`,
through :func:`jax.monitoring.register_event_duration_secs_listener`), so it counts every
compilation in the process while the block runs: a jitted function's first call per input shape,
and the first eager call of an operation too. A call served from a function's in-memory cache
compiles nothing and is not counted.
"""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Iterator

import jax

BACKEND_COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"
"""The event JAX records (with the compile's duration and ``fun_name``) for each backend compilation."""


@dataclasses.dataclass
class Compiles:
    """The compilations seen by one :func:`count_compiles` block (filled while it runs)."""

    names: list[str] = dataclasses.field(default_factory=list)
    """Names of the compiled functions, in order (one entry per compilation)."""
    seconds: float = 0.0
    """Time spent in those compilations."""

    @property
    def count(self) -> int:
        """How many backend compilations ran."""
        return len(self.names)

    def __int__(self) -> int:
        return self.count


@contextlib.contextmanager
def count_compiles() -> Iterator[Compiles]:
    """Count the backend compilations that run inside the ``with`` block (see the module docstring)."""
    seen = Compiles()

    def listener(event: str, duration: float, **kwargs) -> None:
        if event == BACKEND_COMPILE_EVENT:
            seen.names.append(str(kwargs.get("fun_name", "?")))
            seen.seconds += float(duration)

    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        yield seen
    finally:
        with contextlib.suppress(AssertionError, ValueError):  # already removed (clear_event_listeners)
            jax.monitoring.unregister_event_duration_listener(listener)


__all__ = ["BACKEND_COMPILE_EVENT", "Compiles", "count_compiles"]

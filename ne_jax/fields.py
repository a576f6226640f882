"""Validation of config fields: one error message for every frozen config."""

from __future__ import annotations

from typing import Any


def require(cfg: Any, ok: bool, name: str, expected: str) -> None:
    """Raise ``ValueError("<Type>.<name>: expected <expected>, found <value>")`` unless ``ok``."""
    if not ok:
        raise ValueError(f"{type(cfg).__name__}.{name}: expected {expected}, found {getattr(cfg, name)!r}")


__all__ = ["require"]

"""Helpers the format readers share: numbers, image files and their sizes, text matrices."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from ne_jax.data.png import DataError, fail

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
"""Image files the folder-listing readers (NSVF, LLFF) and `process-images` pick up, compared
case-insensitively."""


def number(value: Any, path: Any, where: str) -> float:
    """``value`` as a finite float, or :class:`DataError` naming ``path`` and ``where``."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise fail(path, where, f"expected a number, found {type(value).__name__} {value!r:.100}")
    if not math.isfinite(float(value)):
        raise fail(path, where, f"expected a finite number, found {value!r}")
    return float(value)


def positive(value: float, path: Any, where: str, what: str) -> float:
    if not value > 0:
        raise fail(path, where, f"expected a positive {what}, found {value!r}")
    return value


def zero_is_none(coeffs: tuple[float, ...]) -> tuple[float, ...] | None:
    """OpenCV distortion coefficients, or ``None`` when all are zero (a pinhole camera)."""
    return None if all(c == 0.0 for c in coeffs) else tuple(float(c) for c in coeffs)


def image_size(image: Path, referenced_by: Any, where: str | None) -> tuple[int, int]:
    """``(width, height)`` of ``image`` from its header (no pixels are decoded). A missing or
    unreadable file raises :class:`DataError` naming it and the file that references it."""
    from PIL import Image, UnidentifiedImageError

    if not image.is_file():
        raise fail(referenced_by, where, f"image {str(image)!r} does not exist")
    try:
        with Image.open(image) as im:
            width, height = im.size
    except (OSError, UnidentifiedImageError, ValueError) as e:
        raise fail(referenced_by, where, f"cannot read image {str(image)!r}: {e}") from None
    return int(width), int(height)


def check_size(image: Path, referenced_by: Any, where: str | None, width: int, height: int) -> None:
    """Require ``image`` to be ``width x height`` pixels (the size its intrinsics refer to)."""
    w, h = image_size(image, referenced_by, where)
    if (w, h) != (width, height):
        raise fail(
            referenced_by,
            where,
            f"image {str(image)!r} is {w}x{h} (WxH), expected {width}x{height} as the camera states "
            "(intrinsics refer to the image on disk; point the camera at images of that size)",
        )


def list_images(folder: Path) -> list[Path]:
    """The image files directly in ``folder``, sorted by name."""
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def read_text(path: Path, what: str) -> str:
    try:
        return path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise fail(path, None, f"{what} does not exist") from None
    except (OSError, UnicodeDecodeError) as e:
        raise fail(path, None, f"cannot read {what}: {e}") from None


def number_rows(path: Path, what: str) -> list[tuple[int, list[float]]]:
    """The non-empty lines of a whitespace-separated text file as ``(line number, floats)``;
    a token that is not a number raises :class:`DataError` naming the line (NaN and Inf pass:
    the caller checks what it reads, e.g. :func:`~ne_jax.data.nerf_synthetic.check_rigid`)."""
    rows = []
    for lineno, line in enumerate(read_text(path, what).splitlines(), start=1):
        tokens = line.split()
        if not tokens:
            continue
        values = []
        for tok in tokens:
            try:
                v = float(tok)
            except ValueError:
                raise fail(path, f"line {lineno}", f"expected numbers, found {tok!r} in {line.strip()!r}") from None
            values.append(v)
        rows.append((lineno, values))
    return rows


def matrix_4x4(path: Path, what: str) -> np.ndarray:
    """A 4x4 matrix written as 4 lines of 4 numbers (a 3x4 matrix gets the row ``0 0 0 1``)."""
    rows = number_rows(path, what)
    shape = [len(r) for _, r in rows]
    if not (shape == [4, 4, 4, 4] or shape == [4, 4, 4]):
        raise fail(path, None, f"expected a 4x4 matrix (4 lines of 4 numbers), found lines of {shape} numbers")
    m = np.array([r for _, r in rows], dtype=np.float64)
    if m.shape[0] == 3:
        m = np.concatenate([m, [[0.0, 0.0, 0.0, 1.0]]])
    return m


__all__ = [
    "DataError",
    "IMAGE_SUFFIXES",
    "check_size",
    "image_size",
    "list_images",
    "matrix_4x4",
    "number",
    "number_rows",
    "positive",
    "read_text",
    "zero_is_none",
]

"""PNG images as float32 straight RGBA: reading (any bit depth) and writing (8 or 16 bit).

16-bit PNGs are decoded and encoded by a small numpy/zlib codec here, because Pillow truncates
16-bit colour PNGs to 8 bits; 8-bit and lower-depth PNGs are decoded by Pillow. Every PNG is checked
chunk by chunk (CRC, truncation) before decoding, so a broken file raises :class:`DataError` naming it.
"""

from __future__ import annotations

import dataclasses
import io
import os
import struct
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from ne_jax.atomic import atomic_write_bytes


class DataError(ValueError):
    """Bad scene data: the message names the file (and field or frame), the expectation and the
    value found."""


def fail(path: Any, where: str | None, message: str) -> DataError:
    """A :class:`DataError` reading ``"<path> [<where>]: <message>"``."""
    loc = f"{path}" + (f" [{where}]" if where else "")
    return DataError(f"{loc}: {message}")


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_CHANNELS = {0: 1, 2: 3, 4: 2, 6: 4}  # colour type -> samples per pixel (3 = palette: Pillow)
_COLOR_TYPE = {1: 0, 2: 4, 3: 2, 4: 6}  # channels -> colour type


@dataclasses.dataclass(frozen=True)
class _PngInfo:
    width: int
    height: int
    bit_depth: int
    color_type: int
    interlace: int
    idat: bytes
    trns: bytes | None


def _png_chunks(data: bytes, path: Any) -> _PngInfo:
    """Walk and verify every chunk (lengths, CRCs, IHDR first, IEND present)."""
    if not data.startswith(_PNG_SIGNATURE):
        raise fail(path, None, f"not a PNG file: expected the PNG signature, found {data[:8]!r}")
    pos, n = len(_PNG_SIGNATURE), len(data)
    ihdr, idat, trns, seen_iend = None, [], None, False
    while pos < n:
        if pos + 8 > n:
            raise fail(path, None, f"truncated PNG: chunk header cut at byte {pos} of {n}")
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        ctype = data[pos + 4 : pos + 8]
        end = pos + 12 + length
        if end > n:
            raise fail(path, None, f"truncated PNG: chunk {ctype!r} needs {length} bytes, file ends at {n}")
        body = data[pos + 8 : pos + 8 + length]
        (crc,) = struct.unpack(">I", data[pos + 8 + length : end])
        if zlib.crc32(ctype + body) & 0xFFFFFFFF != crc:
            raise fail(path, None, f"corrupt PNG: CRC mismatch in chunk {ctype!r} at byte {pos}")
        if ihdr is None and ctype != b"IHDR":
            raise fail(path, None, f"corrupt PNG: first chunk must be IHDR, found {ctype!r}")
        if ctype == b"IHDR":
            if length != 13:
                raise fail(path, None, f"corrupt PNG: IHDR must be 13 bytes, found {length}")
            ihdr = struct.unpack(">IIBBBBB", body)
        elif ctype == b"IDAT":
            idat.append(body)
        elif ctype == b"tRNS":
            trns = body
        elif ctype == b"IEND":
            seen_iend = True
            break
        pos = end
    if ihdr is None:
        raise fail(path, None, "truncated PNG: no IHDR chunk")
    if not seen_iend:
        raise fail(path, None, "truncated PNG: no IEND chunk (the file ends early)")
    if not idat:
        raise fail(path, None, "corrupt PNG: no IDAT (image data) chunk")
    width, height, bit_depth, color_type, _comp, _filt, interlace = ihdr
    if width == 0 or height == 0:
        raise fail(path, None, f"corrupt PNG: image size {width}x{height}")
    return _PngInfo(width, height, bit_depth, color_type, interlace, b"".join(idat), trns)


def _paeth(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    p = a + b - c
    pa, pb, pc = np.abs(p - a), np.abs(p - b), np.abs(p - c)
    return np.where((pa <= pb) & (pa <= pc), a, np.where(pb <= pc, b, c))


def _unfilter(rows: np.ndarray, bpp: int, path: Any) -> np.ndarray:
    """Undo PNG scanline filters. ``rows`` ``[H, 1 + stride]`` uint8 -> ``[H, stride]`` uint8."""
    height, stride = rows.shape[0], rows.shape[1] - 1
    out = np.empty((height, stride), np.uint8)
    prev = np.zeros(stride, np.uint8)
    for y in range(height):
        ftype, line = int(rows[y, 0]), rows[y, 1:]
        if ftype == 0:
            cur = line.copy()
        elif ftype == 1:
            cur = np.cumsum(line.reshape(-1, bpp), axis=0, dtype=np.uint8).reshape(-1)
        elif ftype == 2:
            cur = line + prev
        elif ftype in (3, 4):  # sequential along the row: plain Python on bytes
            cur_b, up = bytearray(line.tobytes()), prev.tobytes()
            for i in range(stride):
                a = cur_b[i - bpp] if i >= bpp else 0
                b = up[i]
                if ftype == 3:
                    pred = (a + b) >> 1
                else:
                    c = up[i - bpp] if i >= bpp else 0
                    p = a + b - c
                    pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                    pred = a if (pa <= pb and pa <= pc) else (b if pb <= pc else c)
                cur_b[i] = (cur_b[i] + pred) & 0xFF
            cur = np.frombuffer(bytes(cur_b), np.uint8)
        else:
            raise fail(path, None, f"corrupt PNG: row {y} has filter type {ftype}, expected 0..4")
        out[y] = cur
        prev = out[y]
    return out


def decode_png(data: bytes, path: Any = "<bytes>") -> np.ndarray:
    """Decode a non-interlaced 8- or 16-bit grey/grey+alpha/RGB/RGBA PNG.

    Returns ``[H, W, C]`` uint8 or uint16 (``C`` in 1..4; a ``tRNS`` colour key adds alpha)."""
    info = _png_chunks(data, path)
    if info.color_type not in _CHANNELS or info.bit_depth not in (8, 16):
        raise fail(
            path,
            None,
            f"unsupported PNG: colour type {info.color_type} with bit depth {info.bit_depth} "
            "(expected grey, grey+alpha, RGB or RGBA at 8 or 16 bits)",
        )
    if info.interlace != 0:
        raise fail(
            path, None, "unsupported PNG: interlaced (Adam7) 16-bit image; save it without interlacing"
        )
    channels, nbytes = _CHANNELS[info.color_type], info.bit_depth // 8
    bpp, stride = channels * nbytes, info.width * channels * nbytes
    try:
        raw = zlib.decompress(info.idat)
    except zlib.error as e:
        raise fail(path, None, f"corrupt PNG: image data does not decompress ({e})") from None
    expected = info.height * (stride + 1)
    if len(raw) < expected:
        raise fail(path, None, f"truncated PNG: expected {expected} bytes of pixel data, found {len(raw)}")
    rows = np.frombuffer(raw[:expected], np.uint8).reshape(info.height, stride + 1)
    flat = _unfilter(rows, bpp, path)
    dtype = np.dtype(">u2") if nbytes == 2 else np.dtype(np.uint8)
    img = flat.view(dtype).reshape(info.height, info.width, channels).astype(dtype.newbyteorder("="))
    if info.trns is not None and channels in (1, 3):
        key = np.frombuffer(info.trns, ">u2").astype(np.int64)
        if key.size == channels:
            opaque = np.any(img != key, axis=-1)
            maxv = np.iinfo(img.dtype).max
            img = np.concatenate([img, (opaque * maxv).astype(img.dtype)[..., None]], axis=-1)
    return img


def encode_png(img: np.ndarray, filter_type: int = 2, level: int = 6) -> bytes:
    """Encode ``[H, W, C]`` uint8/uint16 (``C`` in 1..4) as a PNG using one filter type for all
    rows (default 2 = Up: fast to decode and compresses renders well). Deterministic bytes."""
    if img.ndim == 2:
        img = img[..., None]
    height, width, channels = img.shape
    if img.dtype == np.uint8:
        bit_depth, raw = 8, np.ascontiguousarray(img)
    elif img.dtype == np.uint16:
        bit_depth, raw = 16, np.ascontiguousarray(img.astype(">u2"))
    else:
        raise ValueError(f"PNG encoder: expected uint8 or uint16 pixels, found {img.dtype}")
    if channels not in _COLOR_TYPE:
        raise ValueError(f"PNG encoder: expected 1..4 channels, found {channels}")
    x = raw.view(np.uint8).reshape(height, -1).astype(np.int16)
    bpp = channels * bit_depth // 8
    left = np.zeros_like(x)
    left[:, bpp:] = x[:, :-bpp]
    up = np.zeros_like(x)
    up[1:] = x[:-1]
    upleft = np.zeros_like(x)
    upleft[1:, bpp:] = x[:-1, :-bpp]
    pred = {0: 0, 1: left, 2: up, 3: (left + up) >> 1, 4: _paeth(left, up, upleft)}[filter_type]
    filtered = ((x - pred) & 0xFF).astype(np.uint8)
    body = np.concatenate([np.full((height, 1), filter_type, np.uint8), filtered], axis=1)

    def chunk(ctype: bytes, payload: bytes) -> bytes:
        crc = zlib.crc32(ctype + payload) & 0xFFFFFFFF
        return struct.pack(">I", len(payload)) + ctype + payload + struct.pack(">I", crc)

    ihdr = struct.pack(">IIBBBBB", width, height, bit_depth, _COLOR_TYPE[channels], 0, 0, 0)
    return (
        _PNG_SIGNATURE
        + chunk(b"IHDR", ihdr)
        + chunk(b"IDAT", zlib.compress(body.tobytes(), level))
        + chunk(b"IEND", b"")
    )


def to_rgba_float(img: np.ndarray, path: Any) -> np.ndarray:
    """Integer image ``[H, W]`` or ``[H, W, C]`` (grey, grey+alpha, RGB, RGBA) -> float32 RGBA."""
    if img.dtype == np.uint8:
        scale = 255.0
    elif img.dtype == np.uint16:
        scale = 65535.0
    else:
        raise fail(path, None, f"unsupported pixel type: expected 8- or 16-bit integers, found {img.dtype}")
    if img.ndim == 2:
        img = img[..., None]
    if img.ndim != 3 or img.shape[-1] not in (1, 2, 3, 4):
        raise fail(
            path,
            None,
            f"unsupported channels: expected 1 (grey), 2, 3 (RGB) or 4 (RGBA), found shape {img.shape}",
        )
    x = img.astype(np.float32) / np.float32(scale)
    c = x.shape[-1]
    if c in (1, 2):
        x = np.concatenate([x[..., :1]] * 3 + ([x[..., 1:2]] if c == 2 else []), axis=-1)
    if x.shape[-1] == 3:
        x = np.concatenate([x, np.ones_like(x[..., :1])], axis=-1)
    return np.ascontiguousarray(x)


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Read an image as float32 straight RGBA ``[H, W, 4]`` in ``[0, 1]`` (alpha = 1 if absent).

    PNGs are verified chunk by chunk (truncation and CRC errors raise :class:`DataError`). Other
    formats are read with imageio."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise fail(path, None, "image file does not exist") from None
    except OSError as e:
        raise fail(path, None, f"cannot read image: {e}") from None
    if path.suffix.lower() == ".png" or data.startswith(_PNG_SIGNATURE):
        info = _png_chunks(data, path)
        if info.bit_depth == 16:
            return to_rgba_float(decode_png(data, path), path)
        from PIL import Image  # Pillow ships with imageio

        try:
            with Image.open(io.BytesIO(data)) as im:
                if im.mode in ("P", "PA", "1") or (im.mode in ("L", "RGB") and "transparency" in im.info):
                    im = im.convert("RGBA")
                arr = np.asarray(im)
        except Exception as e:  # Pillow raises several types for broken data
            raise fail(path, None, f"corrupt PNG: cannot decode ({type(e).__name__}: {e})") from None
        return to_rgba_float(arr, path)
    import imageio.v3 as iio

    try:
        arr = np.asarray(iio.imread(data, extension=path.suffix or None))
    except Exception as e:
        raise fail(path, None, f"cannot decode image ({type(e).__name__}: {e})") from None
    return to_rgba_float(arr, path)


def quantise(images: np.ndarray, bit_depth: int, what: str) -> np.ndarray:
    """Float ``[..., C]`` in [0, 1] (or integers of the matching width) -> uint8/uint16."""
    if bit_depth not in (8, 16):
        raise DataError(f"{what}: bit_depth must be 8 or 16, found {bit_depth!r}")
    dtype = np.uint8 if bit_depth == 8 else np.uint16
    images = np.asarray(images)
    if np.issubdtype(images.dtype, np.integer):
        if images.dtype != dtype:
            raise DataError(
                f"{what}: integer pixels must be {np.dtype(dtype)} for bit_depth={bit_depth}, "
                f"found {images.dtype}"
            )
        return images
    if not np.issubdtype(images.dtype, np.floating):
        raise DataError(f"{what}: expected float pixels in [0, 1], found dtype {images.dtype}")
    if not np.all(np.isfinite(images)):
        raise DataError(f"{what}: pixels contain NaN or Inf")
    lo, hi = float(images.min(initial=0.0)), float(images.max(initial=0.0))
    if lo < 0.0 or hi > 1.0:
        raise DataError(f"{what}: expected pixels in [0, 1], found range [{lo:g}, {hi:g}] (clip first)")
    maxv = np.iinfo(dtype).max
    return np.round(images.astype(np.float64) * maxv).astype(dtype)


def write_image(path: str | os.PathLike, image: np.ndarray, bit_depth: int = 8) -> Path:
    """Write ``image`` ``[H, W, C]`` (C in 1..4; floats in [0, 1], straight alpha) as a PNG of
    ``bit_depth`` 8 or 16, atomically. Rounds to the nearest level."""
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[-1] not in (1, 2, 3, 4):
        raise DataError(f"{path}: expected an image [H, W, C] with C in 1..4, found shape {image.shape}")
    return atomic_write_bytes(path, encode_png(quantise(image, bit_depth, str(path))))

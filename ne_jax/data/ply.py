"""Minimal PLY point-cloud I/O (one ``vertex`` element, any scalar properties).

Binary little-endian on write; binary (either endianness) and ASCII on read. Used for surface
samples with normals, colours and an ``index`` property (indexed edits), which Open3D's reader drops.
"""

from __future__ import annotations

import io
import os

import numpy as np

from ne_jax.atomic import atomic_write_bytes

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_NUMPY_TO_PLY = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int", "u4": "uint",
                 "f4": "float", "f8": "double"}


class PlyError(ValueError):
    """A PLY file that cannot be read; the message names the file."""


def write_ply(path, properties: dict[str, np.ndarray]) -> None:
    """Write ``{name: [N] array}`` as the vertex properties of a binary PLY, atomically."""
    names = list(properties)
    if not names:
        raise ValueError("write_ply: no properties given")
    n = len(properties[names[0]])
    cols = []
    for name in names:
        a = np.asarray(properties[name])
        if a.shape != (n,):
            raise ValueError(f"write_ply({path}): property {name!r} has shape {a.shape}, expected ({n},)")
        code = a.dtype.str.lstrip("<>|=")
        if code == "b1":
            a, code = a.astype(np.uint8), "u1"
        if code == "i8":
            a, code = a.astype(np.int32), "i4"
        if code not in _NUMPY_TO_PLY:
            raise ValueError(f"write_ply({path}): property {name!r} has unsupported dtype {a.dtype}")
        cols.append((name, "<" + code, a))
    table = np.empty(n, dtype=[(name, code) for name, code, _ in cols])
    for name, _, a in cols:
        table[name] = a
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
    header += [f"property {_NUMPY_TO_PLY[code[1:]]} {name}" for name, code, _ in cols]
    header.append("end_header\n")
    atomic_write_bytes(path, "\n".join(header).encode("ascii") + table.tobytes())


def read_ply(path) -> dict[str, np.ndarray]:
    """Read the vertex properties of a PLY file as ``{name: [N] array}``."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise PlyError(f"PLY file not found: {path}")
    with open(path, "rb") as f:
        data = f.read()
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise PlyError(f"{path}: not a PLY file (expected a 'ply' header ending in 'end_header')")
    body_start = data.index(b"\n", end) + 1
    fmt, count, props, element = None, None, [], None
    for line in data[:end].decode("ascii", "replace").splitlines()[1:]:
        parts = line.split()
        if not parts or parts[0] in ("comment", "obj_info"):
            continue
        if parts[0] == "format":
            fmt = parts[1]
        elif parts[0] == "element":
            element = parts[1]
            if element == "vertex":
                count = int(parts[2])
            elif count is not None:
                break  # properties of later elements are not read
        elif parts[0] == "property" and element == "vertex":
            if parts[1] == "list":
                raise PlyError(f"{path}: list property {parts[-1]!r} in the vertex element is not supported")
            if parts[1] not in _PLY_TYPES:
                raise PlyError(f"{path}: property {parts[2]!r} has unknown type {parts[1]!r}")
            props.append((parts[2], _PLY_TYPES[parts[1]]))
    if count is None or not props:
        raise PlyError(f"{path}: no vertex element with properties in the header")
    body = data[body_start:]
    if fmt == "ascii":
        try:
            rows = np.loadtxt(io.StringIO(body.decode("ascii")), ndmin=2, max_rows=count)
        except ValueError as e:
            raise PlyError(f"{path}: malformed ASCII body ({e})") from None
        if rows.shape != (count, len(props)):
            raise PlyError(f"{path}: expected {count} rows of {len(props)} values, found {rows.shape}")
        return {name: rows[:, i].astype(code) for i, (name, code) in enumerate(props)}
    if fmt not in ("binary_little_endian", "binary_big_endian"):
        raise PlyError(f"{path}: unsupported PLY format {fmt!r}")
    order = "<" if fmt == "binary_little_endian" else ">"
    dtype = np.dtype([(name, order + code) for name, code in props])
    if len(body) < count * dtype.itemsize:
        raise PlyError(f"{path}: truncated: header declares {count} vertices ({count * dtype.itemsize} bytes), "
                       f"file holds {len(body)} bytes")
    table = np.frombuffer(body, dtype=dtype, count=count)
    return {name: table[name].astype(table[name].dtype.newbyteorder("=")) for name, _ in props}

"""Atomic writes: a file or directory is either fully there (new content) or not touched at all.

Files are written to a temporary sibling in the same directory, flushed and ``fsync``-ed, then
moved into place with ``os.replace`` (atomic on POSIX within one file system). A directory is
built in a temporary sibling and renamed into place only when the ``with`` block succeeds.

Temporary names start with ``.`` and end in ``.tmp`` so that they are easy to recognise should a
process be killed mid-write (an exception never leaves them behind).
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np


def _umask() -> int:
    """The process umask, read without changing it (Linux ``/proc``; 0o022 elsewhere)."""
    with contextlib.suppress(OSError):
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    return 0o022


def _fsync_dir(path: Path) -> None:
    """Make a rename inside ``path`` durable (best effort: not every OS can open a directory)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        with contextlib.suppress(OSError):
            os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically; parent directories are created. Returns the path.

    On any error the previous content of ``path`` (if any) is left untouched and no temporary
    file remains."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    view = memoryview(data)  # raises TypeError for non-bytes before anything is created
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            os.fchmod(f.fileno(), 0o666 & ~_umask())
            f.write(view)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    _fsync_dir(path.parent)
    return path


def atomic_write_text(path: str | os.PathLike, text: str, encoding: str = "utf-8") -> Path:
    """Write ``text`` to ``path`` atomically (see :func:`atomic_write_bytes`)."""
    return atomic_write_bytes(path, text.encode(encoding))


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    raise TypeError(f"object of type {type(obj).__name__} is not JSON serialisable")


def atomic_write_json(path: str | os.PathLike, obj: Any, indent: int | None = 2, **kwargs) -> Path:
    """Serialise ``obj`` (numpy arrays and scalars allowed) and write it atomically.

    Strict JSON: NaN/Inf raise ``ValueError`` (``allow_nan=False``) before anything is written.
    Extra ``kwargs`` go to :func:`json.dumps`."""
    kwargs.setdefault("allow_nan", False)
    kwargs.setdefault("default", _json_default)
    text = json.dumps(obj, indent=indent, **kwargs) + "\n"
    return atomic_write_text(path, text)


def _fsync_tree(root: Path) -> None:
    for dirpath, _dirnames, filenames in os.walk(root):
        for name in filenames:
            p = os.path.join(dirpath, name)
            if os.path.islink(p):
                continue
            fd = os.open(p, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)
        _fsync_dir(Path(dirpath))


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        with contextlib.suppress(OSError):
            path.unlink()


@contextlib.contextmanager
def atomic_directory(final_path: str | os.PathLike, fsync: bool = True) -> Iterator[Path]:
    """Yield an empty temporary sibling directory of ``final_path``; on success rename it to
    ``final_path``, on an exception delete it and re-raise.

    An existing ``final_path`` (file or directory) is replaced only after the block succeeded: it
    is first renamed aside, the new directory is renamed in, then the old one is deleted. A crash
    in between leaves the old content intact under a ``.<name>.old-*.tmp`` sibling, never a mix.
    With ``fsync`` every file written inside is flushed to disk before the rename."""
    final = Path(final_path)
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=final.parent, prefix=f".{final.name}.", suffix=".tmp"))
    try:
        os.chmod(tmp, 0o777 & ~_umask())
        yield tmp
        if fsync:
            _fsync_tree(tmp)
        if final.exists() or final.is_symlink():
            trash = Path(tempfile.mkdtemp(dir=final.parent, prefix=f".{final.name}.old-", suffix=".tmp"))
            os.rmdir(trash)  # only the unique name is wanted
            os.rename(final, trash)
            try:
                os.rename(tmp, final)
            except BaseException:
                os.rename(trash, final)
                raise
            _remove(trash)
        else:
            os.rename(tmp, final)
    except BaseException:
        _remove(tmp)
        raise
    _fsync_dir(final.parent)

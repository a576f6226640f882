"""Atomic writes: an error at any step leaves the old content intact and no temporary files."""

from __future__ import annotations

import json
import os
import stat

import numpy as np
import pytest

from ne_jax import atomic
from ne_jax.atomic import atomic_directory, atomic_write_bytes, atomic_write_json, atomic_write_text


def _listing(path):
    return sorted(os.listdir(path))


def test_write_bytes_creates_and_replaces(tmp_path):
    p = tmp_path / "sub" / "f.bin"
    atomic_write_bytes(p, b"one")
    assert p.read_bytes() == b"one"
    atomic_write_bytes(p, b"two!")
    assert p.read_bytes() == b"two!"
    assert _listing(p.parent) == ["f.bin"]


def test_written_file_has_umask_permissions_not_mkstemp_0600(tmp_path):
    p = atomic_write_text(tmp_path / "f.txt", "x")
    mode = stat.S_IMODE(p.stat().st_mode)
    assert mode == 0o666 & ~atomic._umask()


@pytest.mark.parametrize("failing", ["fsync", "replace"])
def test_failure_mid_write_keeps_old_content_and_leaves_no_temp(tmp_path, monkeypatch, failing):
    p = tmp_path / "f.txt"
    p.write_text("old")

    def boom(*args, **kwargs):
        raise OSError("disk full (simulated)")

    monkeypatch.setattr(atomic.os, failing, boom)
    with pytest.raises(OSError, match="simulated"):
        atomic_write_text(p, "new content")
    monkeypatch.undo()
    assert p.read_text() == "old"
    assert _listing(tmp_path) == ["f.txt"]


def test_non_bytes_data_raises_before_anything_is_created(tmp_path):
    with pytest.raises(TypeError):
        atomic_write_bytes(tmp_path / "f.bin", 12345)
    assert _listing(tmp_path) == []


def test_json_numpy_values_and_strictness(tmp_path):
    p = tmp_path / "a.json"
    atomic_write_json(p, {"m": np.eye(2, dtype=np.float32), "k": np.int64(3)})
    assert json.loads(p.read_text()) == {"m": [[1.0, 0.0], [0.0, 1.0]], "k": 3}
    # NaN is not JSON: refused before the old file is touched.
    with pytest.raises(ValueError):
        atomic_write_json(p, {"x": float("nan")})
    with pytest.raises(TypeError):
        atomic_write_json(p, {"x": object()})
    assert json.loads(p.read_text())["k"] == 3
    assert _listing(tmp_path) == ["a.json"]


def test_directory_success_creates(tmp_path):
    final = tmp_path / "out"
    with atomic_directory(final) as d:
        assert d != final and d.parent == tmp_path and not final.exists()
        (d / "a.txt").write_text("a")
        (d / "nested").mkdir()
        (d / "nested" / "b.txt").write_text("b")
    assert (final / "a.txt").read_text() == "a"
    assert (final / "nested" / "b.txt").read_text() == "b"
    assert _listing(tmp_path) == ["out"]


def test_directory_success_replaces_existing(tmp_path):
    final = tmp_path / "out"
    final.mkdir()
    (final / "old.txt").write_text("old")
    with atomic_directory(final) as d:
        (d / "new.txt").write_text("new")
        # the old content is still in place while the block runs
        assert (final / "old.txt").read_text() == "old"
    assert _listing(final) == ["new.txt"]
    assert _listing(tmp_path) == ["out"]


def test_directory_error_removes_temp_and_keeps_old(tmp_path):
    final = tmp_path / "out"
    final.mkdir()
    (final / "old.txt").write_text("old")
    with pytest.raises(RuntimeError, match="halfway"):
        with atomic_directory(final) as d:
            (d / "new.txt").write_text("new")
            raise RuntimeError("halfway")
    assert _listing(final) == ["old.txt"]
    assert (final / "old.txt").read_text() == "old"
    assert _listing(tmp_path) == ["out"]


def test_directory_error_without_previous_leaves_nothing(tmp_path):
    with pytest.raises(KeyboardInterrupt):
        with atomic_directory(tmp_path / "out") as d:
            (d / "partial.bin").write_bytes(b"\0" * 10)
            raise KeyboardInterrupt
    assert _listing(tmp_path) == []


def test_directory_failed_swap_restores_old(tmp_path, monkeypatch):
    final = tmp_path / "out"
    final.mkdir()
    (final / "old.txt").write_text("old")
    real_rename = os.rename

    def rename(src, dst):
        # let "final -> trash" and "trash -> final" through, fail "tmp -> final"
        if str(dst) == str(final) and ".old-" not in str(src):
            raise OSError("rename failed (simulated)")
        return real_rename(src, dst)

    monkeypatch.setattr(atomic.os, "rename", rename)
    with pytest.raises(OSError, match="simulated"):
        with atomic_directory(final) as d:
            (d / "new.txt").write_text("new")
    monkeypatch.undo()
    assert _listing(final) == ["old.txt"]
    assert _listing(tmp_path) == ["out"]

"""Checkpoints: exact resume (2 + 2 steps == 4 steps), round trips, clear refusals, atomic writes."""

from __future__ import annotations

import io
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import ne_jax.train.checkpoint as ckpt
from ne_jax.render.renderer import PointScene
from ne_jax.train import init_train_state, sample_batch
from ne_jax.train.checkpoint import (
    CheckpointError,
    CheckpointNotFoundError,
    latest_checkpoint,
    load_checkpoint,
    save_checkpoint,
)

from .test_step import RCFG, SCFG, SCHEDULE_STEPS, TCFG

REPO = Path(__file__).resolve().parents[2]

# A small run without a scene: both this module and the killed subprocess build it from this source.
SMALL_RUN_SRC = """
import jax, jax.numpy as jnp, numpy as np
from ne_jax.geometry.points import PointState
from ne_jax.geometry.kdtree import KDTreeConfig
from ne_jax.render.quadrature import QuadratureConfig
from ne_jax.render.renderer import RenderConfig
from ne_jax.train import TrainConfig, init_train_state

SMALL_RCFG = RenderConfig(kdtree=KDTreeConfig(candidate_min=16, knn_k=8, num_render_levels=2),
                          quadrature=QuadratureConfig(samples_per_level=(4, 6, 8)), chunk=1024)
SMALL_TCFG = TrainConfig()

def small_run(step=0):
    '''(state, points) with every leaf non-trivial: 40 slots, 30 alive, random arrays everywhere.'''
    rng = np.random.default_rng(0)
    pts = PointState.from_numpy(rng.uniform(-1, 1, (30, 3)), capacity=40, feature_dim=32,
                                normal=rng.normal(size=(30, 3)), key=jax.random.key(0))
    pts = pts.replace(ist=jnp.asarray(rng.normal(size=(40, 3, 3)), jnp.float32), alive=pts.alive.at[3].set(False))
    state = init_train_state(SMALL_TCFG, SMALL_RCFG, pts, jax.random.key(1), total_steps=50)
    leaves, treedef = jax.tree_util.tree_flatten(state.replace(key=jnp.zeros((), jnp.int32)))
    leaves = [jnp.asarray(rng.normal(size=x.shape), x.dtype) if jnp.issubdtype(x.dtype, jnp.floating) else x
              for x in leaves]
    state = jax.tree_util.tree_unflatten(treedef, leaves).replace(
        key=jax.random.key(7 + step), step=jnp.asarray(step, jnp.int32), skipped=jnp.asarray(step % 3, jnp.int32))
    return state, pts
"""
_ns: dict = {}
exec(SMALL_RUN_SRC, _ns)  # noqa: S102  (the same source the subprocess runs)
small_run, SMALL_RCFG, SMALL_TCFG = _ns["small_run"], _ns["SMALL_RCFG"], _ns["SMALL_TCFG"]


def _host(tree):
    """Leaves as numpy arrays (PRNG keys as their key data)."""
    return [np.asarray(jax.random.key_data(x) if jnp.issubdtype(x.dtype, jax.dtypes.prng_key) else x)
            for x in jax.tree_util.tree_leaves(tree)]


def assert_trees_equal(a, b):
    """Same structure, and every leaf equal bit for bit with the same dtype (keys: same type and data)."""
    assert jax.tree_util.tree_structure(a) == jax.tree_util.tree_structure(b)
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        assert x.dtype == y.dtype and x.shape == y.shape
    for x, y in zip(_host(a), _host(b)):
        np.testing.assert_array_equal(x, y, strict=True)


# ---------------------------------------------------------------- exact resume


def _train(step_fn, state, scene, pool, n):
    """``n`` steps; the batch of step ``s`` is drawn with ``fold_in(key(2), s)`` so a resumed run sees
    the same batches."""
    for _ in range(n):
        batch = sample_batch(SCFG, pool, jax.random.fold_in(jax.random.key(2), int(state.step)))
        state, m = step_fn(state, scene, batch)
        assert bool(m["ok"])
    return state


def test_resume_is_exact_two_plus_two_equals_four(world, tmp_path):
    step_fn, pool, scene, points = world["step_fn"], world["pool"], world["scene"], world["points"]
    fresh = init_train_state(TCFG, RCFG, points, jax.random.key(1), total_steps=SCHEDULE_STEPS)
    four = _train(step_fn, fresh, scene, pool, 4)
    two = _train(step_fn, fresh, scene, pool, 2)
    save_checkpoint(tmp_path, two, points, TCFG, RCFG, extra={"epoch": 0})
    del two
    cache = step_fn._cache_size()

    # a fresh process would have only the configs and the directory: no template state, no scene
    state, pts, meta = load_checkpoint(tmp_path, TCFG, RCFG)
    assert meta["step"] == 2 and int(state.step) == 2 and meta["extra"] == {"epoch": 0}
    assert_trees_equal(pts, points)
    resumed = _train(step_fn, state, PointScene.build(pts, RCFG), pool, 2)
    assert step_fn._cache_size() == cache  # the loaded state has the exact types: no recompilation

    assert int(resumed.step) == 4 and int(resumed.skipped) == 0
    assert_trees_equal(resumed, four)  # params, points, Adam moments and counts, key, step: bit for bit
    # the test can fail: two steps less is a different state
    assert not np.array_equal(np.asarray(state.points["feature"]), np.asarray(four.points["feature"]))


# ---------------------------------------------------------------- round trip, latest, keep


def test_round_trip_every_array_latest_and_keep(tmp_path):
    assert latest_checkpoint(tmp_path) is None
    for step in (1, 2, 3, 4, 5):
        state, pts = small_run(step)
        path = save_checkpoint(tmp_path, state, pts, SMALL_TCFG, SMALL_RCFG, keep=3)
        assert latest_checkpoint(tmp_path) == path
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ckpt_00000003", "ckpt_00000004", "ckpt_00000005", "latest"]

    for step in (3, 5):
        state, pts = small_run(step)
        got_state, got_pts, meta = load_checkpoint(tmp_path / f"ckpt_{step:08d}", SMALL_TCFG, SMALL_RCFG,
                                                   like_state=small_run(0)[0])
        assert_trees_equal(got_state, state)
        assert_trees_equal(got_pts, pts)
        assert meta["train_config"] == SMALL_TCFG and meta["render_config"] == SMALL_RCFG
        assert meta["format"] == ckpt.FORMAT_VERSION and meta["step"] == step
    assert not np.asarray(got_pts.alive)[3] and np.asarray(got_pts.alive)[:30].sum() == 29
    assert load_checkpoint(tmp_path, SMALL_TCFG, SMALL_RCFG)[2]["step"] == 5  # a run directory loads latest
    # saving an existing step again replaces it atomically
    state, pts = small_run(5)
    save_checkpoint(tmp_path, state.replace(skipped=jnp.asarray(9, jnp.int32)), pts, SMALL_TCFG, SMALL_RCFG)
    assert int(load_checkpoint(tmp_path, SMALL_TCFG, SMALL_RCFG)[0].skipped) == 9


# ---------------------------------------------------------------- refusals


@pytest.fixture
def saved(tmp_path):
    state, pts = small_run(4)
    return save_checkpoint(tmp_path / "run", state, pts, SMALL_TCFG, SMALL_RCFG)


def test_missing_path_is_named(tmp_path, saved):
    with pytest.raises(CheckpointNotFoundError, match="nope.*found nothing"):
        load_checkpoint(tmp_path / "nope", SMALL_TCFG, SMALL_RCFG)
    (saved / "meta.json").unlink()
    with pytest.raises(FileNotFoundError, match=r"meta\.json"):
        load_checkpoint(saved, SMALL_TCFG, SMALL_RCFG)


@pytest.mark.parametrize("field, value, match", [
    ("format", 2, r"another version: expected format 1, found format 2"),
    ("ne_jax_version", "7.0.0", r"another version: expected ne_jax 0\.x, found ne_jax '7\.0\.0'"),
])
def test_another_version_is_refused(saved, field, value, match):
    meta = json.loads((saved / "meta.json").read_text())
    meta[field] = value
    (saved / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(CheckpointError, match=match) as e:
        load_checkpoint(saved, SMALL_TCFG, SMALL_RCFG)
    assert str(saved / "meta.json") in str(e.value)


def test_another_config_names_the_fields(saved):
    with pytest.raises(CheckpointError, match=r"train_config\.lr: checkpoint 0\.002, run 0\.001") as e:
        load_checkpoint(saved, SMALL_TCFG.replace(lr=1e-3), SMALL_RCFG)
    assert "1 field(s)" in str(e.value)
    with pytest.raises(CheckpointError, match=r"2 field\(s\).*quadrature\.samples_per_level: checkpoint \(4, 6, 8\), "
                                              r"run \(4, 6, 9\).*shading\.effects\.ist: checkpoint False, run True"):
        load_checkpoint(saved, SMALL_TCFG, SMALL_RCFG.replace(
            quadrature=SMALL_RCFG.quadrature.__class__(samples_per_level=(4, 6, 9))).with_effects(ist=True))


def test_truncated_or_altered_arrays_are_refused(saved):
    npz = saved / "arrays.npz"
    data = npz.read_bytes()
    npz.write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match=r"arrays\.npz: expected a complete \.npz archive, found a corrupt or "
                                              r"truncated file"):
        load_checkpoint(saved, SMALL_TCFG, SMALL_RCFG)
    # a well-formed archive whose content changed: caught by the digest
    with np.load(io.BytesIO(data)) as z:
        arrays = {k: z[k] for k in z.files}
    arrays["state/params/shader/density/bias"] = arrays["state/params/shader/density/bias"] + 1.0
    np.savez(npz, **arrays)
    with pytest.raises(CheckpointError, match=r"corrupt checkpoint: expected array digest [0-9a-f]{64}, found"):
        load_checkpoint(saved, SMALL_TCFG, SMALL_RCFG)


def test_shape_mismatch_names_the_array(saved):
    good, pts = small_run(0)
    grown = pts.replace(**{k: jnp.concatenate([v, v[:8]]) for k, v in vars(pts).items()})  # capacity 40 -> 48
    bigger = init_train_state(SMALL_TCFG, SMALL_RCFG, grown, jax.random.key(0), total_steps=50)
    with pytest.raises(CheckpointError, match=r"state/points/conf_logit: expected shape \(48,\) dtype float32, "
                                              r"found shape \(40,\) dtype float32"):
        load_checkpoint(saved, SMALL_TCFG, SMALL_RCFG, like_state=bigger)
    f64 = good.replace(skipped=np.zeros((), np.int64))
    with pytest.raises(CheckpointError,
                       match=r"state/skipped: expected shape \(\) dtype int64, found shape \(\) dtype int32"):
        load_checkpoint(saved, SMALL_TCFG, SMALL_RCFG, like_state=f64)


# ---------------------------------------------------------------- atomicity


def test_exception_mid_write_leaves_previous_checkpoint_and_latest(tmp_path, monkeypatch):
    state, pts = small_run(1)
    first = save_checkpoint(tmp_path, state, pts, SMALL_TCFG, SMALL_RCFG)
    before = {p.name: p.stat().st_mtime_ns for p in first.iterdir()}

    def half_then_fail(directory, arrays):
        (directory / "arrays.npz").write_bytes(b"PK\x03\x04 half an archive")
        raise RuntimeError("disk full (injected)")

    monkeypatch.setattr(ckpt, "_write_arrays", half_then_fail)
    state2, pts2 = small_run(2)
    with pytest.raises(RuntimeError, match="injected"):
        save_checkpoint(tmp_path, state2, pts2, SMALL_TCFG, SMALL_RCFG)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ckpt_00000001", "latest"]  # no temporary left
    assert latest_checkpoint(tmp_path) == first
    assert {p.name: p.stat().st_mtime_ns for p in first.iterdir()} == before
    assert_trees_equal(load_checkpoint(tmp_path, SMALL_TCFG, SMALL_RCFG)[0], state)

    # failing while writing ``latest``: the new directory is complete but not yet the latest, nothing deleted
    monkeypatch.undo()

    def no_pointer(path, data):
        raise OSError("injected")

    monkeypatch.setattr(ckpt, "atomic_write_bytes", no_pointer)
    with pytest.raises(OSError, match="injected"):
        save_checkpoint(tmp_path, state2, pts2, SMALL_TCFG, SMALL_RCFG, keep=1)
    assert latest_checkpoint(tmp_path) == first and first.is_dir()
    assert_trees_equal(load_checkpoint(tmp_path, SMALL_TCFG, SMALL_RCFG)[0], state)


KILLED_WRITER = SMALL_RUN_SRC + """
import sys, time
from pathlib import Path
import ne_jax.train.checkpoint as ckpt

run_dir, marker = Path(sys.argv[1]), Path(sys.argv[2])
real_write = ckpt._write_arrays

def slow_write(directory, arrays):
    real_write(directory, arrays)
    with open(directory / "arrays.npz", "r+b") as f:  # leave the archive half-written, then hang
        f.truncate(f.seek(0, 2) // 2)
    marker.write_text(str(directory))
    time.sleep(600)

for step in range(1, 100):
    if step == 4:
        ckpt._write_arrays = slow_write
    state, pts = small_run(step)
    ckpt.save_checkpoint(run_dir, state, pts, SMALL_TCFG, SMALL_RCFG, keep=2)
"""


def test_sigkill_mid_write_resumes_from_the_last_complete_checkpoint(tmp_path):
    script, marker, run_dir = tmp_path / "writer.py", tmp_path / "marker", tmp_path / "run"
    script.write_text(KILLED_WRITER)
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    proc = subprocess.Popen([sys.executable, str(script), str(run_dir), str(marker)], cwd=REPO, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 120
        while not marker.exists():
            assert proc.poll() is None, proc.stdout.read().decode()
            assert time.monotonic() < deadline, "the writer never reached its fourth checkpoint"
            time.sleep(0.05)
        os.kill(proc.pid, signal.SIGKILL)  # inside the fourth save, its archive half-written
    finally:
        proc.kill()
        proc.wait()
    assert proc.returncode == -signal.SIGKILL

    half = Path(marker.read_text())
    assert half.exists() and half.parent == run_dir  # the half-written temporary is there ...
    assert sorted(p.name for p in run_dir.iterdir() if not p.name.startswith(".")) == [
        "ckpt_00000002", "ckpt_00000003", "latest"]  # ... but no checkpoint directory shows it
    path = latest_checkpoint(run_dir)
    assert path == run_dir / "ckpt_00000003"
    state, pts, _ = load_checkpoint(path, SMALL_TCFG, SMALL_RCFG)
    want_state, want_pts = small_run(3)
    assert_trees_equal(state, want_state)
    assert_trees_equal(pts, want_pts)

    # the resumed run's next save clears the leftover
    save_checkpoint(run_dir, *small_run(4), SMALL_TCFG, SMALL_RCFG, keep=2)
    assert sorted(p.name for p in run_dir.iterdir()) == ["ckpt_00000003", "ckpt_00000004", "latest"]

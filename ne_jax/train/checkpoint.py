"""Checkpoints: save and resume a training run exactly.

A run directory holds one directory per checkpoint and a ``latest`` pointer::

    run_dir/
        ckpt_00000200/
            arrays.npz   every array: model params, per-point arrays, optimiser state, step, key, skipped
            meta.json    format version, ne_jax version, configs (typed), array digest, user ``extra``
        ckpt_00000400/
        latest           the name of the newest complete checkpoint directory (text, one line)

Array names in ``arrays.npz`` are the pytree key paths joined by ``/``, e.g.
``state/params/shader/trunk/in/kernel``, ``state/opt_state/0/mu/points/feature``, ``points/xyz``.
PRNG keys are stored as their ``jax.random.key_data`` (``uint32``) with the key implementation's
name in ``meta.json``.

Nothing is ever half-written: a checkpoint directory is built in a temporary sibling and renamed
into place (:func:`~ne_jax.atomic.atomic_directory`); ``latest`` is rewritten atomically only after
that rename, and older checkpoints are deleted only after ``latest`` names the new one. A process
killed at any moment leaves ``latest`` naming a complete checkpoint (or absent, before the first);
the temporary leftovers (``.ckpt_*.tmp``) are removed by the next :func:`save_checkpoint`.

:func:`load_checkpoint` rebuilds the pytrees with the exact structure of a freshly initialised state
and refuses, naming the file, the expectation and what was found, a checkpoint that is missing, of
another format or ne_jax major version, of another config (listing the differing fields), with
arrays of other shapes/dtypes, or whose arrays do not match their digest (corrupt or truncated).
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import re
import shutil
import zipfile
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

import ne_jax
from ne_jax.atomic import atomic_directory, atomic_write_bytes, atomic_write_text
from ne_jax.config_json import ConfigError, config_diff, config_from_json, config_to_json
from ne_jax.geometry.points import PointState
from ne_jax.render.renderer import RenderConfig
from ne_jax.train.state import TrainConfig, TrainState, init_train_state

FORMAT_VERSION = 1
"""Version of the on-disk layout; a checkpoint of another version is refused."""
ARRAYS_FILE = "arrays.npz"
META_FILE = "meta.json"
LATEST_FILE = "latest"
_CKPT_RE = re.compile(r"^ckpt_(\d+)$")
_TMP_RE = re.compile(r"^\.ckpt_\d+\..*\.tmp$")


class CheckpointError(ValueError):
    """A checkpoint that cannot be used by this run (message: file, expectation, what was found)."""


class CheckpointNotFoundError(CheckpointError, FileNotFoundError):
    """The checkpoint path (or a file inside it) does not exist."""


# ---------------------------------------------------------------- pytrees <-> named arrays


def _key_name(k: Any) -> str:
    if isinstance(k, jax.tree_util.DictKey):
        return str(k.key)
    if isinstance(k, jax.tree_util.SequenceKey):
        return str(k.idx)
    if isinstance(k, jax.tree_util.GetAttrKey):
        return k.name
    if isinstance(k, jax.tree_util.FlattenedIndexKey):
        return str(k.key)
    return str(k)


def _is_prng_key(x: Any) -> bool:
    return jnp.issubdtype(getattr(x, "dtype", np.float32), jax.dtypes.prng_key)


def _flatten(prefix: str, tree: Any) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """``({name: host array}, {name: key impl})`` of ``tree``'s leaves; typed PRNG keys as key data."""
    arrays, keys = {}, {}
    for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]:
        name = "/".join([prefix, *(_key_name(k) for k in path)])
        if name in arrays:
            raise ValueError(f"pytree leaf name {name!r} is not unique")
        if _is_prng_key(leaf):
            keys[name] = str(jax.random.key_impl(leaf))
            leaf = jax.random.key_data(leaf)
        arrays[name] = np.asarray(leaf)
    return arrays, keys


def _digest(arrays: dict[str, np.ndarray]) -> str:
    """SHA-256 over every array's name, dtype, shape and bytes, in name order."""
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(f"{name}\0{a.dtype.str}\0{a.shape}\0".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _unflatten(prefix: str, like: Any, arrays: dict[str, np.ndarray], keys: dict[str, str], file: Path) -> Any:
    """A tree of ``like``'s structure from ``arrays``; shapes and dtypes must match ``like``'s leaves
    (``like`` may hold arrays or ``jax.ShapeDtypeStruct``)."""
    leaves_with_path, treedef = jax.tree_util.tree_flatten_with_path(like)
    leaves = []
    for path, tmpl in leaves_with_path:
        name = "/".join([prefix, *(_key_name(k) for k in path)])
        if name not in arrays:
            raise CheckpointError(f"{file}: expected an array named {name!r} (shape {tuple(tmpl.shape)}, "
                                  f"dtype {tmpl.dtype}), found none")
        a = arrays[name]
        if _is_prng_key(tmpl):
            impl = keys.get(name)
            try:
                leaf = None if impl is None else jax.random.wrap_key_data(jnp.asarray(a), impl=impl)
            except (ValueError, TypeError):
                leaf = None
            if leaf is None or leaf.dtype != tmpl.dtype or leaf.shape != tuple(tmpl.shape):
                raise CheckpointError(f"{file}: {name}: expected a PRNG key of type {tmpl.dtype} and shape "
                                      f"{tuple(tmpl.shape)}, found key data of shape {a.shape} dtype {a.dtype} "
                                      f"(implementation {impl or 'not recorded'})")
        else:
            if a.shape != tuple(tmpl.shape) or a.dtype != np.dtype(tmpl.dtype):
                raise CheckpointError(f"{file}: {name}: expected shape {tuple(tmpl.shape)} dtype "
                                      f"{np.dtype(tmpl.dtype)}, found shape {a.shape} dtype {a.dtype}")
            leaf = jnp.asarray(a)
        leaves.append(leaf)
    return jax.tree_util.tree_unflatten(treedef, leaves)


# ---------------------------------------------------------------- save


def _checkpoint_dirs(run_dir: Path) -> list[tuple[int, Path]]:
    """``[(step, path)]`` of the complete-looking checkpoint directories, oldest first."""
    if not run_dir.is_dir():
        return []
    out = []
    for p in run_dir.iterdir():
        m = _CKPT_RE.match(p.name)
        if m and p.is_dir():
            out.append((int(m.group(1)), p))
    return sorted(out)


def _write_arrays(directory: Path, arrays: dict[str, np.ndarray]) -> None:
    """Write ``arrays`` as an uncompressed ``.npz`` inside ``directory`` (a hook the tests patch)."""
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    with open(directory / ARRAYS_FILE, "wb") as f:
        f.write(buf.getvalue())


def save_checkpoint(run_dir: str | os.PathLike, train_state: TrainState, points: PointState,
                    train_cfg: TrainConfig, render_cfg: RenderConfig, extra: dict | None = None,
                    keep: int = 3) -> Path:
    """Write ``run_dir/ckpt_<step>`` atomically, point ``latest`` at it, keep the newest ``keep``.

    Args:
        run_dir: the run's checkpoint directory (created if needed).
        train_state: the :class:`TrainState` (params, ``points`` ``{"feature": [C, F],
            "conf_logit": [C]}``, optimiser state, ``step`` ``[]`` int32, ``key``, ``skipped``).
        points: the full :class:`PointState` of the run (``xyz [C, 3]``, ``alive [C]``,
            ``feature [C, F]``, ``conf_logit [C]``, ``normal [C, 3]``, ``ist [C, 3, 3]``), stored as given.
        train_cfg, render_cfg: the run's configs, stored typed (:func:`config_to_json`) and checked
            on load.
        extra: JSON-serialisable data stored in ``meta.json`` under ``"extra"`` (e.g. epoch, metrics).
        keep: how many checkpoints to keep (>= 1); older ones are deleted after ``latest`` is written.

    Returns:
        The checkpoint directory. A checkpoint of the same step is replaced atomically.
    """
    if int(keep) < 1:
        raise ValueError(f"keep: expected an integer >= 1, found {keep}")
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    for p in run_dir.iterdir():  # leftovers of a killed save (single writer per run directory)
        if _TMP_RE.match(p.name):
            shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink(missing_ok=True)

    state_arrays, state_keys = _flatten("state", train_state)
    point_arrays, point_keys = _flatten("points", points)
    arrays = {**state_arrays, **point_arrays}
    step = int(np.asarray(train_state.step))
    meta = {
        "format": FORMAT_VERSION,
        "ne_jax_version": ne_jax.__version__,
        "step": step,
        "train_config": config_to_json(train_cfg),
        "render_config": config_to_json(render_cfg),
        "prng_keys": {**state_keys, **point_keys},
        "arrays": {k: {"shape": list(v.shape), "dtype": v.dtype.str} for k, v in sorted(arrays.items())},
        "digest": {"algorithm": "sha256", "value": _digest(arrays)},
        "extra": extra if extra is not None else {},
    }
    meta_text = json.dumps(meta, indent=2, allow_nan=False) + "\n"  # fails before anything is written

    name = f"ckpt_{step:08d}"
    final = run_dir / name
    with atomic_directory(final) as tmp:
        _write_arrays(tmp, arrays)
        atomic_write_text(tmp / META_FILE, meta_text)
    atomic_write_bytes(run_dir / LATEST_FILE, (name + "\n").encode())
    for _, old in _checkpoint_dirs(run_dir)[:-int(keep)]:
        if old.name != name:
            shutil.rmtree(old, ignore_errors=True)
    return final


# ---------------------------------------------------------------- find and load


def latest_checkpoint(run_dir: str | os.PathLike) -> Path | None:
    """The checkpoint ``run_dir/latest`` names, or ``None`` when there is no ``latest`` yet.

    Raises:
        CheckpointNotFoundError: ``latest`` names a directory that does not exist."""
    run_dir = Path(run_dir)
    pointer = run_dir / LATEST_FILE
    if not pointer.is_file():
        return None
    name = pointer.read_text(encoding="utf-8").strip()
    path = run_dir / name
    if not _CKPT_RE.match(name) or not path.is_dir():
        raise CheckpointNotFoundError(f"{pointer}: expected the name of a checkpoint directory in {run_dir}, "
                                      f"found {name!r} ({'missing' if not path.exists() else 'not a checkpoint'})")
    return path


def _major(version: str) -> str:
    return str(version).split(".")[0]


def _template(train_cfg: TrainConfig, render_cfg: RenderConfig, like_state: TrainState | None,
              arrays: dict[str, np.ndarray], file: Path) -> tuple[Any, PointState]:
    """Shape/dtype templates ``(train_state, points)`` of a freshly initialised run.

    The capacity ``C`` is ``like_state``'s when given, else the checkpoint's (``points/alive``), so a
    run whose capacity grew resumes at its grown size."""
    if like_state is not None:
        capacity = like_state.points["conf_logit"].shape[0]
    elif "points/alive" in arrays and arrays["points/alive"].ndim == 1:
        capacity = arrays["points/alive"].shape[0]
    else:
        raise CheckpointError(f"{file}: expected an array 'points/alive' of shape [C], found "
                              f"{arrays['points/alive'].shape if 'points/alive' in arrays else 'none'}")
    f = render_cfg.shading.feature_dim
    points_like = PointState(
        xyz=jax.ShapeDtypeStruct((capacity, 3), jnp.float32), alive=jax.ShapeDtypeStruct((capacity,), jnp.bool_),
        feature=jax.ShapeDtypeStruct((capacity, f), jnp.float32),
        conf_logit=jax.ShapeDtypeStruct((capacity,), jnp.float32),
        normal=jax.ShapeDtypeStruct((capacity, 3), jnp.float32),
        ist=jax.ShapeDtypeStruct((capacity, 3, 3), jnp.float32))
    if like_state is None:
        # shapes only: the optimiser state's structure does not depend on the schedule's length
        like_state = jax.eval_shape(lambda p: init_train_state(train_cfg, render_cfg, p, jax.random.key(0),
                                                               total_steps=1), points_like)
    return like_state, points_like


def load_checkpoint(path: str | os.PathLike, train_cfg: TrainConfig, render_cfg: RenderConfig,
                    like_state: TrainState | None = None) -> tuple[TrainState, PointState, dict]:
    """Load a checkpoint saved by :func:`save_checkpoint` for a run with these configs.

    Args:
        path: a checkpoint directory, or a run directory (its :func:`latest_checkpoint` is loaded).
        train_cfg, render_cfg: the run's configs; the checkpoint's must be equal.
        like_state: template for the state's structure, shapes and dtypes (e.g. a fresh
            :func:`init_train_state`); default: the structure :func:`init_train_state` gives at the
            checkpoint's capacity ``C``.

    Returns:
        ``(train_state, points, meta)``: the state and :class:`PointState` as saved (same pytree
        structure, shapes and dtypes as a fresh state; PRNG keys re-wrapped) and the ``meta.json``
        dict with ``"train_config"``/``"render_config"`` rebuilt as config objects.

    Raises:
        CheckpointNotFoundError: the path, ``arrays.npz`` or ``meta.json`` is missing.
        CheckpointError: another format or ne_jax major version, other configs (the differing fields
            are listed), arrays of other names/shapes/dtypes, or a digest mismatch (corrupt/truncated).
    """
    path = Path(path)
    if not path.exists():
        raise CheckpointNotFoundError(f"{path}: expected a checkpoint or run directory, found nothing")
    if not (path / META_FILE).exists() and (path / LATEST_FILE).exists():
        found = latest_checkpoint(path)
        path = found if found is not None else path
    meta_file, arrays_file = path / META_FILE, path / ARRAYS_FILE
    for f in (meta_file, arrays_file):
        if not f.is_file():
            raise CheckpointNotFoundError(f"{f}: expected a file of the checkpoint {path}, found nothing")

    try:
        meta = json.loads(meta_file.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise CheckpointError(f"{meta_file}: expected checkpoint metadata (JSON), "
                              f"found unreadable data ({e})") from None
    if not isinstance(meta, dict):
        raise CheckpointError(f"{meta_file}: expected a JSON object, found {type(meta).__name__}")
    if meta.get("format") != FORMAT_VERSION:
        raise CheckpointError(f"{meta_file}: checkpoint from another version: expected format {FORMAT_VERSION}, "
                              f"found format {meta.get('format')!r} (ne_jax {meta.get('ne_jax_version')!r})")
    if _major(meta.get("ne_jax_version", "")) != _major(ne_jax.__version__):
        raise CheckpointError(f"{meta_file}: checkpoint from another version: expected ne_jax "
                              f"{_major(ne_jax.__version__)}.x, found ne_jax {meta.get('ne_jax_version')!r}")

    diffs = []
    for label, cfg in (("train_config", train_cfg), ("render_config", render_cfg)):
        diffs += [f"{label}.{d}" for d in config_diff(meta.get(label), config_to_json(cfg))]
    if diffs:
        raise CheckpointError(f"{meta_file}: the checkpoint's config differs from this run's in "
                              f"{len(diffs)} field(s): " + "; ".join(diffs))

    try:
        with np.load(arrays_file, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (zipfile.BadZipFile, EOFError, ValueError, OSError, KeyError) as e:  # a damaged archive
        raise CheckpointError(f"{arrays_file}: expected a complete .npz archive, found a corrupt or truncated "
                              f"file ({type(e).__name__}: {e})") from None
    expected_digest = meta.get("digest", {}).get("value")
    found_digest = _digest(arrays)
    if found_digest != expected_digest:
        raise CheckpointError(f"{arrays_file}: corrupt checkpoint: expected array digest {expected_digest}, "
                              f"found {found_digest}")

    keys = meta.get("prng_keys", {})
    like_state, points_like = _template(train_cfg, render_cfg, like_state, arrays, arrays_file)
    state = _unflatten("state", like_state, arrays, keys, arrays_file)
    points = _unflatten("points", points_like, arrays, keys, arrays_file)
    expected_names = set(_names("state", like_state)) | set(_names("points", points_like))
    unknown = sorted(set(arrays) - expected_names)
    if unknown:
        raise CheckpointError(f"{arrays_file}: expected only the arrays of this run's state, found extra arrays "
                              f"{unknown[:5]}{' ...' if len(unknown) > 5 else ''}")
    try:
        meta = {**meta, "train_config": config_from_json(meta["train_config"]),
                "render_config": config_from_json(meta["render_config"]), "path": str(path)}
    except ConfigError as e:
        raise CheckpointError(f"{path / META_FILE}: {e}") from None
    return state, points, meta


def _names(prefix: str, tree: Any) -> list[str]:
    return ["/".join([prefix, *(_key_name(k) for k in path)])
            for path, _ in jax.tree_util.tree_flatten_with_path(tree)[0]]


__all__ = [
    "FORMAT_VERSION",
    "CheckpointError",
    "CheckpointNotFoundError",
    "latest_checkpoint",
    "load_checkpoint",
    "save_checkpoint",
]

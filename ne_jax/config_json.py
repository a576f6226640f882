"""Configs as typed JSON: a frozen config dataclass written as nested JSON with the type of every
node (so it is rebuilt exactly), a stable key of a config (the name of its cached runs), and the
dotted names of the fields where two configs differ (what a refused checkpoint reports)."""

from __future__ import annotations

import dataclasses
import hashlib
import importlib
import json
from typing import Any


class ConfigError(ValueError):
    """A stored config that names a type outside ``ne_jax`` or one this version does not have."""


BUFFER_SIZES = "buffer_sizes"
"""Metadata flag of a config field that holds buffer sizes, not settings (``dataclasses.field(
metadata={BUFFER_SIZES: True})``, e.g. ``RunConfig.capacities``): written to ``config.json`` but left
out of :func:`config_key` and of :func:`config_diff`, since it changes only what is lost to a full
buffer, which is counted."""


def config_to_json(cfg: Any, _for_key: bool = False) -> Any:
    """A frozen config dataclass as nested JSON data with the type information to rebuild it.

    Dataclasses become ``{"__type__": "module:QualName", **fields}`` (fields as
    ``dataclasses.asdict`` would give them, recursively encoded), tuples ``{"__tuple__": [...]}``;
    ``None``, bools, ints, floats and strings are kept."""
    if dataclasses.is_dataclass(cfg) and not isinstance(cfg, type):
        out = {"__type__": f"{type(cfg).__module__}:{type(cfg).__qualname__}"}
        for f in dataclasses.fields(cfg):
            value = getattr(cfg, f.name)
            if _for_key and f.metadata.get(BUFFER_SIZES):
                continue
            out[f.name] = config_to_json(value, _for_key)
        return out
    if isinstance(cfg, tuple):
        return {"__tuple__": [config_to_json(v, _for_key) for v in cfg]}
    if isinstance(cfg, list):
        return [config_to_json(v, _for_key) for v in cfg]
    if cfg is None or isinstance(cfg, (bool, int, float, str)):
        return cfg
    raise TypeError(f"config value of type {type(cfg).__name__} cannot be stored as typed JSON: {cfg!r}")


def _config_type(name: str) -> type:
    """The ``ne_jax`` dataclass named ``"module:QualName"`` (as :func:`config_to_json` writes it).

    Raises:
        ConfigError: for a type outside ``ne_jax`` or one that no longer exists."""
    module, _, qualname = name.partition(":")
    if not (module == "ne_jax" or module.startswith("ne_jax.")):
        raise ConfigError(f"config type: expected an ne_jax dataclass, found {name!r}")
    try:
        obj = importlib.import_module(module)
        for part in qualname.split("."):
            obj = getattr(obj, part)
    except (ImportError, AttributeError) as e:
        raise ConfigError(f"config type {name!r} does not exist in this ne_jax ({e})") from None
    return obj


def config_key(cfg: Any) -> str:
    """A short hash (12 hex digits) of a whole config: equal for equal configs, different when any
    field differs (e.g. the cache key of a study's run directory; fields flagged
    :data:`BUFFER_SIZES` do not count)."""
    text = json.dumps(config_to_json(cfg, _for_key=True), sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def config_from_json(data: Any) -> Any:
    """Inverse of :func:`config_to_json`; only ``ne_jax`` dataclasses are rebuilt.

    Raises:
        ConfigError: for a type outside ``ne_jax``, one that does not exist, or a field the type does
            not have (a config written by another version of ne_jax)."""
    return _from_json(data)


def _from_json(data: Any) -> Any:
    if isinstance(data, dict) and "__tuple__" in data:
        return tuple(_from_json(v) for v in data["__tuple__"])
    if isinstance(data, dict) and "__type__" in data:
        kind = _config_type(data["__type__"])
        fields = {k: _from_json(v) for k, v in data.items() if k != "__type__"}
        unknown = sorted(set(fields) - {f.name for f in dataclasses.fields(kind)})
        if unknown:
            raise ConfigError(f"config type {data['__type__']!r}: this ne_jax has no field(s) {unknown} (a config "
                              "written by another version of ne_jax)")
        return kind(**fields)
    if isinstance(data, list):
        return [_from_json(v) for v in data]
    return data


def _field(node: dict, name: str):
    """The dataclass field ``name`` of the encoded dataclass ``node`` (``None`` if unknown)."""
    try:
        return {f.name: f for f in dataclasses.fields(_config_type(node["__type__"]))}.get(name)
    except (KeyError, TypeError, ConfigError):
        return None


def _is_buffer_sizes(node: Any, name: str) -> bool:
    field = _field(node, name) if isinstance(node, dict) else None
    return bool(field is not None and field.metadata.get(BUFFER_SIZES))


def config_diff(found: Any, expected: Any, prefix: str = "") -> list[str]:
    """Dotted names of the fields where two :func:`config_to_json` trees differ, with both values."""
    def is_node(x):
        return isinstance(x, dict) and "__tuple__" not in x

    if is_node(found) and is_node(expected):
        out = []
        for k in sorted(set(found) | set(expected), key=str):
            name = f"{prefix}.{k}" if prefix else str(k)
            if _is_buffer_sizes(expected, k):
                continue
            if k not in found:
                out.append(f"{name} (missing in checkpoint; run has {expected[k]!r})")
            elif k not in expected:
                out.append(f"{name} (unknown to this run; checkpoint has {found[k]!r})")
            else:
                out.extend(config_diff(found[k], expected[k], name))
        return out
    if found != expected or type(found) is not type(expected):
        return [f"{prefix or '<root>'}: checkpoint {_show(found)}, run {_show(expected)}"]
    return []


def _show(v: Any) -> str:
    if isinstance(v, dict) and "__tuple__" in v:
        return repr(tuple(v["__tuple__"]))
    return repr(v)


def config_set(cfg: Any, *assignments: str) -> Any:
    """``cfg`` with nested fields set from ``"dotted.path=VALUE"`` assignments, in order (``VALUE``
    read as JSON: ``1.0``, ``null``, ``true``, ``"text"``; a bare word is a string), e.g.
    ``config_set(run, "render.kdtree.density_falloff=1.0", "train.confidence_lr=10")``. The config's
    own checks run on every new value.

    Raises:
        ValueError: naming the assignment, for a missing ``=``, an unknown field (listing the known
            ones) or a value the field refuses."""
    for assignment in assignments:
        cfg = _set_one(cfg, assignment)
    return cfg


def _tuples(value: Any) -> Any:
    """JSON lists as tuples, nested ones too: configs are hashable."""
    return tuple(_tuples(v) for v in value) if isinstance(value, list) else value


def _set_one(cfg: Any, assignment: str) -> Any:
    path, sep, text = assignment.partition("=")
    if not sep or not path:
        raise ValueError(f"config assignment {assignment!r}: expected FIELD.PATH=VALUE")
    try:
        value = json.loads(text)
    except json.JSONDecodeError:
        value = text

    def put(node: Any, names: list[str]) -> Any:
        fields = {f.name for f in dataclasses.fields(node)} if dataclasses.is_dataclass(node) else set()
        if names[0] not in fields:
            raise ValueError(f"config assignment {assignment!r}: {type(node).__name__} has no field {names[0]!r} "
                             f"(known: {', '.join(sorted(fields)) or 'none'})")
        current = getattr(node, names[0])
        inner = _tuples(value) if len(names) == 1 else put(current, names[1:])
        if isinstance(current, float) and isinstance(inner, int) and not isinstance(inner, bool):
            inner = float(inner)  # ``lr=10`` keys as the preset's ``10.0`` does
        return dataclasses.replace(node, **{names[0]: inner})

    return put(cfg, path.split("."))

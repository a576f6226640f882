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


ADDED_LATER = "added_later"
"""Metadata flag of a config field added after runs were keyed (``dataclasses.field(metadata=
{ADDED_LATER: True})``): at its default it is left out of :func:`config_key`, so the keys of runs
made before it existed stay valid."""


def config_to_json(cfg: Any, _for_key: bool = False) -> Any:
    """A frozen config dataclass as nested JSON data with the type information to rebuild it.

    Dataclasses become ``{"__type__": "module:QualName", **fields}`` (fields as
    ``dataclasses.asdict`` would give them, recursively encoded), tuples ``{"__tuple__": [...]}``;
    ``None``, bools, ints, floats and strings are kept."""
    if dataclasses.is_dataclass(cfg) and not isinstance(cfg, type):
        out = {"__type__": f"{type(cfg).__module__}:{type(cfg).__qualname__}"}
        for f in dataclasses.fields(cfg):
            value = getattr(cfg, f.name)
            if _for_key and f.metadata.get(ADDED_LATER) and value == f.default:
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


MOVED = {
    "ne_jax.train.loop:RunConfig": "ne_jax.train.run:RunConfig",
    "ne_jax.train.loop:InitConfig": "ne_jax.train.run:InitConfig",
}
"""Config types stored under an older module path -> where they live now (read side only: a run
directory written before a move still loads and resumes)."""


def _upgrade(data: Any) -> Any:
    """``data`` with the type names of :data:`MOVED` replaced by the current ones."""
    if isinstance(data, dict):
        return {k: MOVED.get(v, v) if k == "__type__" else _upgrade(v) for k, v in data.items()}
    if isinstance(data, list):
        return [_upgrade(v) for v in data]
    return data


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
    field differs (e.g. the cache key of a study's run directory; fields flagged :data:`ADDED_LATER`
    count only away from their default)."""
    text = json.dumps(config_to_json(cfg, _for_key=True), sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def config_from_json(data: Any) -> Any:
    """Inverse of :func:`config_to_json`; only ``ne_jax`` dataclasses are rebuilt.

    Raises:
        ConfigError: for a type outside ``ne_jax`` or one that no longer exists."""
    if isinstance(data, dict) and "__tuple__" in data:
        return tuple(config_from_json(v) for v in data["__tuple__"])
    if isinstance(data, dict) and "__type__" in data:
        fields = {k: config_from_json(v) for k, v in data.items() if k != "__type__"}
        return _config_type(MOVED.get(data["__type__"], data["__type__"]))(**fields)
    if isinstance(data, list):
        return [config_from_json(v) for v in data]
    return data


def _is_default(node: dict, name: str) -> bool:
    """Whether field ``name`` of the encoded dataclass ``node`` holds the dataclass's default."""
    try:
        field = {f.name: f for f in dataclasses.fields(_config_type(node["__type__"]))}[name]
    except (KeyError, TypeError, ConfigError):
        return False
    if field.default is not dataclasses.MISSING:
        default = field.default
    elif field.default_factory is not dataclasses.MISSING:
        default = field.default_factory()
    else:
        return False
    return config_to_json(default) == node[name]


def config_diff(found: Any, expected: Any, prefix: str = "") -> list[str]:
    """Dotted names of the fields where two :func:`config_to_json` trees differ, with both values."""
    def is_node(x):
        return isinstance(x, dict) and "__tuple__" not in x

    if not prefix:
        found = _upgrade(found)
    if is_node(found) and is_node(expected):
        out = []
        for k in sorted(set(found) | set(expected), key=str):
            name = f"{prefix}.{k}" if prefix else str(k)
            if k not in found:
                if _is_default(expected, k):  # a field added later, at its default: same config
                    continue
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

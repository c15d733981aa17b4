"""Typed configuration: dataclasses built from plain dicts, where unknown keys are errors.

``from_dict(Cls, data, where)`` builds ``Cls`` from a mapping, recursing into nested dataclass fields,
checking primitive types and refusing unknown keys. ``where`` names the source (a file, a field path) so the
message points the user at the faulty entry.
"""
from __future__ import annotations

import dataclasses
import types
import typing
from typing import Any, Mapping, TypeVar

from .errors import ConfigError

T = TypeVar("T")


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")


def _convert(tp: Any, value: Any, where: str) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if tp is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for a in args:
            if a is type(None):
                continue
            try:
                return _convert(a, value, where)
            except ConfigError as e:
                errors.append(str(e))
        raise ConfigError(f"{where}: expected {_type_name(tp)}, got {value!r}")
    if origin is typing.Literal:
        if value not in args:
            raise ConfigError(f"{where}: expected one of {list(args)}, got {value!r}")
        return value
    if dataclasses.is_dataclass(tp):
        if isinstance(value, tp):
            return value
        return from_dict(tp, value, where)
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {type(value).__name__} {value!r}")
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                raise ConfigError(f"{where}: expected {len(args)} values, got {len(value)}")
            return tuple(_convert(a, v, f"{where}[{i}]") for i, (a, v) in enumerate(zip(args, value)))
        inner = args[0] if args else Any
        out = [_convert(inner, v, f"{where}[{i}]") for i, v in enumerate(value)]
        return tuple(out) if origin is tuple else out
    if origin is dict:
        if not isinstance(value, Mapping):
            raise ConfigError(f"{where}: expected a mapping, got {type(value).__name__}")
        kt, vt = args if args else (Any, Any)
        return {_convert(kt, k, _join(where, str(k))): _convert(vt, v, _join(where, str(k))) for k, v in value.items()}
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: expected a number, got {type(value).__name__} {value!r}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            if isinstance(value, float) and value.is_integer():
                return int(value)
            raise ConfigError(f"{where}: expected an integer, got {type(value).__name__} {value!r}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true or false, got {type(value).__name__} {value!r}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {type(value).__name__} {value!r}")
        return value
    if isinstance(tp, type) and not isinstance(value, tp):
        raise ConfigError(f"{where}: expected {_type_name(tp)}, got {type(value).__name__} {value!r}")
    return value


def _join(where: str, name: str) -> str:
    """``file.yaml: a.b`` style field paths: a ``where`` ending in ':' starts the path."""
    return f"{where} {name}" if where.endswith(":") else f"{where}.{name}"


def from_dict(cls: type[T], data: Any, where: str = "config") -> T:
    """Build dataclass ``cls`` from ``data``; unknown keys, missing required keys and wrong types raise."""
    if not isinstance(data, Mapping):
        raise ConfigError(f"{where.rstrip(':')}: expected a mapping of {cls.__name__} fields, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(f"{where.rstrip(':')}: unknown key(s) {unknown}; known keys are {sorted(fields)}")
    kwargs = {}
    for name, f in fields.items():
        if name in data:
            kwargs[name] = _convert(hints[name], data[name], _join(where, name))
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise ConfigError(f"{where.rstrip(':')}: missing required key '{name}'")
    try:
        return cls(**kwargs)
    except ConfigError as e:  # raised by __post_init__ as "field: problem"
        raise ConfigError(_join(where, str(e))) from e
    except (TypeError, ValueError) as e:
        raise ConfigError(f"{where.rstrip(':')}: {e}") from e


def added_field(default: Any, before: Any = dataclasses.MISSING, **kw: Any) -> Any:
    """A dataclass field added after configurations were stored as keys (stage stamps, cache keys,
    recordings): :func:`to_dict` with ``stamp=True`` leaves it out while it holds ``before``, the value the
    versions without the field behaved as (by default ``default``), so a key stored before still matches
    where it means the same thing, and a new default (``default`` other than ``before``) is written out, so it
    never matches a key made without it. Plain :func:`to_dict` writes it like any field (so that
    :func:`from_dict` of it gives it back, an explicit ``before`` included); :func:`from_dict` gives it
    ``default`` where a configuration lacks it."""
    return dataclasses.field(default=default, metadata={"added": True,
                                                        "before": default if before is dataclasses.MISSING else before},
                             **kw)


def to_dict(obj: Any, runtime: bool = True, stamp: bool = False) -> Any:
    """Plain (JSON/YAML-ready) dict of a dataclass, tuples turned into lists.

    ``runtime=False`` leaves out the fields marked ``metadata={"runtime": True}`` (at any depth): settings of
    how a stage runs, not of what it makes (e.g. :func:`satloc.device.device_field`), which the keys of
    cached stages must not depend on. ``stamp=True`` (a key to compare with stored ones) leaves out a field made
    with :func:`added_field` while it holds the value the versions before it behaved as."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_dict(getattr(obj, f.name), runtime, stamp) for f in dataclasses.fields(obj)
                if (runtime or not f.metadata.get("runtime"))
                and not (stamp and f.metadata.get("added")
                         and getattr(obj, f.name) == f.metadata.get("before", f.default))}
    if isinstance(obj, (list, tuple)):
        return [to_dict(v, runtime, stamp) for v in obj]
    if isinstance(obj, dict):
        return {k: to_dict(v, runtime, stamp) for k, v in obj.items()}
    return obj


def override(obj: T, changes: Mapping[str, Any] | None, where: str = "config") -> T:
    """A copy of dataclass ``obj`` with ``changes`` applied (nested dicts merge); unknown keys raise."""
    if not changes:
        return obj
    merged = _merge(to_dict(obj), dict(changes), where, type(obj))
    return from_dict(type(obj), merged, where)


def _merge(base: dict, changes: Mapping[str, Any], where: str, cls: type) -> dict:
    hints = typing.get_type_hints(cls)
    out = dict(base)
    for k, v in changes.items():
        if k not in base:
            raise ConfigError(f"{where}: unknown key '{k}'; known keys are {sorted(base)}")
        tp = hints.get(k)
        if isinstance(v, Mapping) and isinstance(base[k], dict) and dataclasses.is_dataclass(tp):
            out[k] = _merge(base[k], v, f"{where}.{k}", tp)
        else:
            out[k] = v
    return out

"""Strict conversion of plain data (msgpack or TOML output) into typed dataclasses.

One routine serves both the message codec and the TOML config loader, so a field means the
same thing on the wire and in a file: unknown keys are errors, numbers must be finite, bools
are not numbers, and every error names the offending field by its dotted path.
"""
from __future__ import annotations

import dataclasses
import math
import types
import typing
from functools import lru_cache
from typing import Any, Literal, Union


class TypeCheckError(ValueError):
    """Raised with a message of the form '<dotted.path>: <reason>'."""


@lru_cache(maxsize=None)
def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


@lru_cache(maxsize=None)
def field_names(cls: type) -> tuple[str, ...]:
    return tuple(f.name for f in dataclasses.fields(cls))


def _fail(where: str, reason: str) -> typing.NoReturn:
    raise TypeCheckError(f"{where or '<root>'}: {reason}")


def _describe(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def coerce(tp: Any, value: Any, where: str = "", *, require_all: bool = False) -> Any:
    """Return `value` converted to type `tp`, or raise TypeCheckError.

    require_all: dataclass fields with defaults must still be present (wire messages);
    config files leave it False so that defaults apply.
    """
    origin = typing.get_origin(tp)
    if tp is Any:
        return value
    if origin is Literal:
        allowed = typing.get_args(tp)
        if value not in allowed or isinstance(value, bool) != any(isinstance(a, bool) for a in allowed):
            _fail(where, f"must be one of {list(allowed)}, got {_describe(value)}")
        return value
    if origin is Union or origin is types.UnionType:
        args = typing.get_args(tp)
        if value is None:
            if type(None) in args:
                return None
            _fail(where, "must not be null")
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return coerce(arg, value, where, require_all=require_all)
            except TypeCheckError as exc:
                errors.append(str(exc))
        raise TypeCheckError(errors[0] if len(errors) == 1 else f"{where}: no alternative matched ({'; '.join(errors)})")
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            _fail(where, f"expected a number, got {_describe(value)}")
        out = float(value)
        if not math.isfinite(out):
            _fail(where, f"must be finite, got {out}")
        return out
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            _fail(where, f"expected an integer, got {_describe(value)}")
        return int(value)
    if tp is bool:
        if not isinstance(value, bool):
            _fail(where, f"expected true/false, got {_describe(value)}")
        return value
    if tp is str:
        if not isinstance(value, str):
            _fail(where, f"expected a string, got {_describe(value)}")
        return value
    if tp is bytes:
        if not isinstance(value, (bytes, bytearray)):
            _fail(where, f"expected bytes, got {type(value).__name__}")
        return bytes(value)
    if origin in (list, tuple, dict):
        return _coerce_container(origin, tp, value, where, require_all)
    if dataclasses.is_dataclass(tp):
        if isinstance(value, tp):
            return value
        return from_dict(tp, value, where, require_all=require_all)
    raise TypeError(f"{where}: unsupported annotation {tp!r}")


def _coerce_container(origin: Any, tp: Any, value: Any, where: str, require_all: bool) -> Any:
    """coerce() for list[...], tuple[...] and dict[...]."""
    if origin is list:
        (item_tp,) = typing.get_args(tp)
        if not isinstance(value, (list, tuple)):
            _fail(where, f"expected a list, got {_describe(value)}")
        fast = _plain_numbers(item_tp, value)
        if fast is not None:
            return fast
        return [coerce(item_tp, v, f"{where}[{i}]", require_all=require_all) for i, v in enumerate(value)]
    if origin is tuple:
        args = typing.get_args(tp)
        if not isinstance(value, (list, tuple)):
            _fail(where, f"expected a list, got {_describe(value)}")
        if len(args) == 2 and args[1] is Ellipsis:
            fast = _plain_numbers(args[0], value)
            if fast is not None:
                return tuple(fast)
            return tuple(coerce(args[0], v, f"{where}[{i}]", require_all=require_all) for i, v in enumerate(value))
        if len(value) != len(args):
            _fail(where, f"expected {len(args)} elements, got {len(value)}")
        return tuple(coerce(a, v, f"{where}[{i}]", require_all=require_all) for i, (a, v) in enumerate(zip(args, value)))
    if origin is dict:
        key_tp, val_tp = typing.get_args(tp)
        if not isinstance(value, dict):
            _fail(where, f"expected a table/map, got {_describe(value)}")
        return {coerce(key_tp, k, f"{where}.<key>"): coerce(val_tp, v, f"{where}.{k}", require_all=require_all)
                for k, v in value.items()}


def _plain_numbers(item_tp: Any, value: list | tuple) -> list | None:
    """A list of plain finite numbers checked in one pass (wire vectors are long, and element by element
    the check cost more than the message's decoding); None: anything else, for the element-wise path
    to accept or to name the offending element."""
    kinds = set(map(type, value))
    if item_tp is int:
        return list(value) if kinds <= {int} else None
    if item_tp is not float or not kinds <= {float, int}:
        return None
    return list(map(float, value)) if all(map(math.isfinite, value)) else None


def from_dict(cls: type, data: Any, where: str = "", *, require_all: bool = False) -> Any:
    """Build dataclass `cls` from a mapping; unknown keys and missing required keys are errors."""
    if not isinstance(data, dict):
        _fail(where, f"expected a table/map, got {_describe(data)}")
    hints = _hints(cls)
    names = field_names(cls)
    unknown = [k for k in data if k not in names]
    if unknown:
        _fail(where, f"unknown key(s) {sorted(map(str, unknown))}; allowed: {list(names)}")
    kwargs = {}
    for f in dataclasses.fields(cls):
        sub = f"{where}.{f.name}" if where else f.name
        if f.name in data:
            kwargs[f.name] = coerce(hints[f.name], data[f.name], sub, require_all=require_all)
        elif require_all or (f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING):
            _fail(sub, "missing")
    try:
        return cls(**kwargs)
    except (ValueError, TypeError) as exc:  # __post_init__ validation
        _fail(where, str(exc))


_SCALARS = {float, int, str, bool, bytes, type(None)}


def to_dict(obj: Any) -> Any:
    """Dataclass -> plain dict/list tree (tuples become lists), ready for msgpack or JSON."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {name: to_dict(getattr(obj, name)) for name in field_names(type(obj))}
    if isinstance(obj, (list, tuple)):
        if set(map(type, obj)) <= _SCALARS:
            return list(obj)
        return [to_dict(v) for v in obj]
    if isinstance(obj, dict):
        return {k: to_dict(v) for k, v in obj.items()}
    return obj

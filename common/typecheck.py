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
from typing import Any, Callable, Literal, Union


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


Converter = Callable[[Any, str], Any]     # (value, dotted path for errors) -> converted value


def coerce(tp: Any, value: Any, where: str = "", *, require_all: bool = False) -> Any:
    """Return `value` converted to type `tp`, or raise TypeCheckError.

    require_all: dataclass fields with defaults must still be present (wire messages);
    config files leave it False so that defaults apply.
    """
    return converter(tp, require_all)(value, where)


def from_dict(cls: type, data: Any, where: str = "", *, require_all: bool = False) -> Any:
    """Build dataclass `cls` from a mapping; unknown keys and missing required keys are errors."""
    if not isinstance(data, dict):
        _fail(where, f"expected a table/map, got {_describe(data)}")
    return converter(cls, require_all)(data, where)


@lru_cache(maxsize=None)
def converter(tp: Any, require_all: bool = False) -> Converter:
    """The checking conversion for annotation `tp`, built once per type: every bus message is decoded
    through it, and walking the annotations anew per message cost more than the msgpack decoding."""
    origin = typing.get_origin(tp)
    if tp is Any:
        return lambda value, where: value
    if origin is Literal:
        return _literal(typing.get_args(tp))
    if origin is Union or origin is types.UnionType:
        return _union(typing.get_args(tp), require_all)
    scalar = _SCALAR_CONVERTERS.get(tp)
    if scalar is not None:
        return scalar
    if origin is list:
        return _list(typing.get_args(tp)[0], require_all)
    if origin is tuple:
        return _tuple(typing.get_args(tp), require_all)
    if origin is dict:
        return _dict(*typing.get_args(tp), require_all)
    if dataclasses.is_dataclass(tp):
        return _dataclass(tp, require_all)

    def unsupported(value: Any, where: str) -> Any:
        raise TypeError(f"{where}: unsupported annotation {tp!r}")
    return unsupported


def _literal(allowed: tuple) -> Converter:
    wants_bool = any(isinstance(a, bool) for a in allowed)

    def conv(value: Any, where: str) -> Any:
        if value not in allowed or isinstance(value, bool) != wants_bool:
            _fail(where, f"must be one of {list(allowed)}, got {_describe(value)}")
        return value
    return conv


def _union(args: tuple, require_all: bool) -> Converter:
    nullable = type(None) in args
    alternatives = [converter(a, require_all) for a in args if a is not type(None)]

    def conv(value: Any, where: str) -> Any:
        if value is None:
            if nullable:
                return None
            _fail(where, "must not be null")
        errors = []
        for alt in alternatives:
            try:
                return alt(value, where)
            except TypeCheckError as exc:
                errors.append(str(exc))
        raise TypeCheckError(errors[0] if len(errors) == 1 else f"{where}: no alternative matched ({'; '.join(errors)})")
    return conv


def _float(value: Any, where: str) -> float:
    if type(value) is not float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            _fail(where, f"expected a number, got {_describe(value)}")
        value = float(value)
    if not math.isfinite(value):
        _fail(where, f"must be finite, got {value}")
    return value


def _int(value: Any, where: str) -> int:
    if type(value) is int:
        return value
    if isinstance(value, bool) or not isinstance(value, int):
        _fail(where, f"expected an integer, got {_describe(value)}")
    return int(value)


def _bool(value: Any, where: str) -> bool:
    if not isinstance(value, bool):
        _fail(where, f"expected true/false, got {_describe(value)}")
    return value


def _str(value: Any, where: str) -> str:
    if not isinstance(value, str):
        _fail(where, f"expected a string, got {_describe(value)}")
    return value


def _bytes(value: Any, where: str) -> bytes:
    if not isinstance(value, (bytes, bytearray)):
        _fail(where, f"expected bytes, got {type(value).__name__}")
    return bytes(value)


_SCALAR_CONVERTERS: dict[Any, Converter] = {float: _float, int: _int, bool: _bool, str: _str, bytes: _bytes}


def _list(item_tp: Any, require_all: bool) -> Converter:
    item = converter(item_tp, require_all)

    def conv(value: Any, where: str) -> list:
        if not isinstance(value, (list, tuple)):
            _fail(where, f"expected a list, got {_describe(value)}")
        fast = _plain_numbers(item_tp, value)
        if fast is not None:
            return fast
        return [item(v, f"{where}[{i}]") for i, v in enumerate(value)]
    return conv


def _tuple(args: tuple, require_all: bool) -> Converter:
    if len(args) == 2 and args[1] is Ellipsis:
        as_list = _list(args[0], require_all)
        return lambda value, where: tuple(as_list(value, where))
    items = [converter(a, require_all) for a in args]

    def conv(value: Any, where: str) -> tuple:
        if not isinstance(value, (list, tuple)):
            _fail(where, f"expected a list, got {_describe(value)}")
        if len(value) != len(items):
            _fail(where, f"expected {len(items)} elements, got {len(value)}")
        return tuple(c(v, f"{where}[{i}]") for i, (c, v) in enumerate(zip(items, value)))
    return conv


def _dict(key_tp: Any, val_tp: Any, require_all: bool) -> Converter:
    key, val = converter(key_tp), converter(val_tp, require_all)

    def conv(value: Any, where: str) -> dict:
        if not isinstance(value, dict):
            _fail(where, f"expected a table/map, got {_describe(value)}")
        return {key(k, f"{where}.<key>"): val(v, f"{where}.{k}") for k, v in value.items()}
    return conv


def _dataclass(cls: type, require_all: bool) -> Converter:
    fields: list[tuple[str, Converter, bool]] = []     # name, converter, must be present; built at first use
    names = frozenset(field_names(cls))

    def conv(value: Any, where: str) -> Any:
        if isinstance(value, cls):
            return value
        if not isinstance(value, dict):
            _fail(where, f"expected a table/map, got {_describe(value)}")
        if not fields:       # not at build time: a field's type may name a class defined later
            hints = _hints(cls)
            fields[:] = [(f.name, converter(hints[f.name], require_all), require_all or (
                f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING))
                for f in dataclasses.fields(cls)]     # one assignment: two first decodes on two threads agree
        if not names.issuperset(value):
            unknown = [k for k in value if k not in names]
            _fail(where, f"unknown key(s) {sorted(map(str, unknown))}; allowed: {list(field_names(cls))}")
        kwargs = {}
        for name, c, needed in fields:
            if name in value:
                kwargs[name] = c(value[name], f"{where}.{name}" if where else name)
            elif needed:
                _fail(f"{where}.{name}" if where else name, "missing")
        try:
            return cls(**kwargs)
        except (ValueError, TypeError) as exc:  # __post_init__ validation
            _fail(where, str(exc))
    return conv


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


_SCALARS = {float, int, str, bool, bytes, type(None)}


def to_dict(obj: Any) -> Any:
    """Dataclass -> plain dict/list tree (tuples become lists), ready for msgpack or JSON."""
    kind = type(obj)
    if kind in _SCALARS:
        return obj
    names = _dataclass_fields(kind)
    if names is not None:
        return {name: to_dict(getattr(obj, name)) for name in names}
    if isinstance(obj, (list, tuple)):
        if set(map(type, obj)) <= _SCALARS:
            return list(obj)
        return [to_dict(v) for v in obj]
    if isinstance(obj, dict):
        return {k: to_dict(v) for k, v in obj.items()}
    return obj


@lru_cache(maxsize=None)
def _dataclass_fields(kind: type) -> tuple[str, ...] | None:
    """The field names of instances of `kind` if it is a dataclass (not of a dataclass's class object)."""
    return field_names(kind) if dataclasses.is_dataclass(kind) else None

"""A JSON Schema of a bus message dataclass: the schema the run recorder gives each project channel
(message encoding msgpack), so that a reader of the MCAP learns every field, its type and the schema
version without this code. Bytes fields are msgpack bin (a JSON Schema has no such type: described
by `contentEncoding`)."""
from __future__ import annotations

import dataclasses
import types
import typing
from typing import Any, Literal

from common.codec import VERSION_FIELD

_SIMPLE = {float: {"type": "number"}, int: {"type": "integer"}, bool: {"type": "boolean"}, str: {"type": "string"},
           bytes: {"type": "string", "contentEncoding": "msgpack-bin"}}


def _schema_of(tp: Any) -> dict:
    if tp in _SIMPLE:
        return dict(_SIMPLE[tp])
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is Literal:
        return {"enum": list(args)}
    if origin in (typing.Union, types.UnionType):
        return {"anyOf": [{"type": "null"} if a is type(None) else _schema_of(a) for a in args]}
    if origin in (list, tuple):
        items = [a for a in args if a is not Ellipsis]
        out: dict = {"type": "array"}
        if origin is tuple and items and Ellipsis not in args:
            out.update(prefixItems=[_schema_of(a) for a in items], minItems=len(items), maxItems=len(items))
        elif items:
            out["items"] = _schema_of(items[0])
        return out
    if dataclasses.is_dataclass(tp):
        return _object(tp, versioned=False)
    return {}


def _object(cls: type, versioned: bool) -> dict:
    hints = typing.get_type_hints(cls)
    fields = [f for f in dataclasses.fields(cls)]
    props = {f.name: _schema_of(hints[f.name]) for f in fields}
    required = [f.name for f in fields]
    if versioned:
        props[VERSION_FIELD] = {"const": cls.SCHEMA_VERSION, "description": "schema version"}
        required.append(VERSION_FIELD)
    out = {"type": "object", "title": cls.__name__, "properties": props, "required": required}
    if cls.__doc__:
        out["description"] = " ".join(cls.__doc__.split())
    return out


def json_schema(cls: type) -> dict:
    """The JSON Schema of a message class as it travels (a msgpack map with its schema version)."""
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", **_object(cls, versioned=True)}

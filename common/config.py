"""TOML configuration into typed dataclasses. Unknown keys are errors, named by their dotted path."""
from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any, TypeVar

from common.typecheck import TypeCheckError, from_dict, to_dict

C = TypeVar("C")


class ConfigError(ValueError):
    pass


def read_toml(path: str | Path) -> dict[str, Any]:
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such file") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: invalid TOML: {exc}") from None


def load_config(cls: type[C], source: str | Path | dict[str, Any]) -> C:
    """Load `cls` from a TOML file path or an already-parsed dict."""
    where = "<dict>" if isinstance(source, dict) else str(source)
    data = source if isinstance(source, dict) else read_toml(source)
    try:
        return from_dict(cls, data)
    except TypeCheckError as exc:
        raise ConfigError(f"{where}: {exc}") from None


def dump_toml(obj: Any) -> str:
    """Write a config dataclass back as TOML (the subset our configs use: tables, arrays, scalars)."""
    return _dump_table(to_dict(obj), [])


def _scalar(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, list):
        return "[" + ", ".join(_scalar(v) for v in value) + "]"
    raise TypeError(f"cannot write {type(value).__name__} to TOML")


def _dump_table(table: dict[str, Any], prefix: list[str]) -> str:
    lines, subtables, arrays = [], [], []
    for key, value in table.items():
        if value is None:
            continue  # TOML has no null: an absent key means the default (None)
        if isinstance(value, dict):
            subtables.append((key, value))
        elif isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
            arrays.append((key, value))
        else:
            lines.append(f"{key} = {_scalar(value)}")
    out = "\n".join(lines) + ("\n" if lines else "")
    for key, value in subtables:
        name = ".".join(prefix + [key])
        out += f"\n[{name}]\n" + _dump_table(value, prefix + [key])
    for key, items in arrays:
        name = ".".join(prefix + [key])
        for item in items:
            out += f"\n[[{name}]]\n" + _dump_table(item, prefix + [key])
    return out

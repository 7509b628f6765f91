"""The one msgpack codec for every bus message.

Wire format: a msgpack map holding every dataclass field by name plus `v`, the schema version of
the message type. Decoding is strict: oversized payloads, bad msgpack, a wrong version, missing,
unknown, wrongly typed or non-finite fields are rejected with a reason. `Decoder` wraps that for
services: it logs the reason (rate-limited), counts rejections per key and never raises.
"""
from __future__ import annotations

import dataclasses
import logging
import time
from collections import Counter
from typing import Any, ClassVar, TypeVar

import msgpack

from common.typecheck import TypeCheckError, from_dict, to_dict

VERSION_FIELD = "v"
DEFAULT_MAX_BYTES = 64 * 1024

M = TypeVar("M")


class DecodeError(ValueError):
    pass


class Message:
    """Mixin for bus messages. Subclasses are dataclasses and set SCHEMA_VERSION."""

    SCHEMA_VERSION: ClassVar[int] = 1
    MAX_BYTES: ClassVar[int] = DEFAULT_MAX_BYTES


def encode(msg: Message) -> bytes:
    if not dataclasses.is_dataclass(msg):
        raise TypeError(f"{type(msg).__name__} is not a message dataclass")
    body = to_dict(msg)
    body[VERSION_FIELD] = type(msg).SCHEMA_VERSION
    data = msgpack.packb(body, use_bin_type=True)
    if len(data) > type(msg).MAX_BYTES:
        raise ValueError(f"{type(msg).__name__} encodes to {len(data)} bytes > limit {type(msg).MAX_BYTES}")
    return data


def decode(cls: type[M], data: bytes | bytearray | memoryview) -> M:
    """Decode one payload into `cls` or raise DecodeError with a human-readable reason."""
    limit = getattr(cls, "MAX_BYTES", DEFAULT_MAX_BYTES)
    if len(data) > limit:
        raise DecodeError(f"payload of {len(data)} bytes exceeds the {limit}-byte limit for {cls.__name__}")
    try:
        body = msgpack.unpackb(bytes(data), raw=False, strict_map_key=True, use_list=True)
    except Exception as exc:  # msgpack raises several unrelated types
        raise DecodeError(f"not valid msgpack: {type(exc).__name__}: {exc}") from None
    if not isinstance(body, dict):
        raise DecodeError(f"expected a msgpack map, got {type(body).__name__}")
    version = body.pop(VERSION_FIELD, None)
    if version != cls.SCHEMA_VERSION:
        raise DecodeError(f"schema version {version!r} != {cls.SCHEMA_VERSION} expected for {cls.__name__}")
    try:
        return from_dict(cls, body, require_all=True)
    except TypeCheckError as exc:
        raise DecodeError(f"{cls.__name__}.{exc}") from None


class Decoder:
    """Decode-or-reject for services: logs a reason, counts rejections per key, never raises.

    Logging is limited to `burst` lines per key every `window_s` seconds, so a flood of garbage
    cannot flood the log; the counters see everything."""

    def __init__(self, logger: logging.Logger, window_s: float = 5.0, burst: int = 10):
        self._log = logger
        self._window_s = window_s
        self._burst = burst
        self._windows: dict[str, tuple[float, int]] = {}
        self.rejected: Counter[str] = Counter()

    @property
    def rejected_total(self) -> int:
        return sum(self.rejected.values())

    def __call__(self, cls: type[M], data: Any, key: str) -> M | None:
        try:
            return decode(cls, data)
        except DecodeError as exc:
            self.rejected[key] += 1
            now = time.monotonic()
            start, logged = self._windows.get(key, (now, 0))
            if now - start >= self._window_s:
                start, logged = now, 0
            if logged < self._burst:
                self._log.warning("rejected message on %s (%d so far): %s", key, self.rejected[key], exc)
            elif logged == self._burst:
                self._log.warning("more rejected messages on %s; logging at most %d every %.0f s", key,
                                  self._burst, self._window_s)
            self._windows[key] = (start, logged + 1)
            return None

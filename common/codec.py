"""The one msgpack codec for every bus message.

Wire format: a msgpack map holding every dataclass field by name plus `v`, the schema version of
the message type. Decoding is strict: oversized payloads, bad msgpack, a wrong version, missing,
unknown, wrongly typed or non-finite fields are rejected with a reason. `Decoder` wraps that for
services: it logs the reason (rate-limited), counts rejections per key and never raises.
"""
from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections import Counter
from typing import Any, Callable, ClassVar, TypeVar

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

    A flood of garbage must not flood the log or the memory, on one key or on a hundred thousand:
    every `window_s` seconds at most `burst` lines per key and `total_burst` lines in all are logged
    (a window that suppressed lines ends with one line saying how many), and counts are kept for at
    most `max_keys` keys, the rest under OTHER_KEYS. The total sees everything."""

    OTHER_KEYS = "(other keys)"

    def __init__(self, logger: logging.Logger, window_s: float = 5.0, burst: int = 10, total_burst: int = 50,
                 max_keys: int = 1000, clock: Callable[[], float] = time.monotonic):
        self._log = logger
        self._clock = clock
        self._window_s = window_s
        self._burst = burst
        self._total_burst = total_burst
        self._max_keys = max_keys
        self._window_start = -math.inf
        self._logged: Counter[str] = Counter()    # lines per key in this window (only keys that logged)
        self._suppressed: Counter[str] = Counter()
        self.rejected: Counter[str] = Counter()
        self.rejected_total = 0

    def __call__(self, cls: type[M], data: Any, key: str) -> M | None:
        try:
            return decode(cls, data)
        except DecodeError as exc:
            self.reject(key, str(exc))
            return None

    def reject(self, key: str, reason: str = "") -> None:
        """Count one unusable message on `key` (logging `reason` within the rate limits if given)."""
        self.rejected_total += 1
        self.rejected[key if key in self.rejected or len(self.rejected) < self._max_keys else self.OTHER_KEYS] += 1
        if not reason:
            return
        now = self._clock()
        if now - self._window_start >= self._window_s:
            self._end_window()
            self._window_start = now
        if self._logged[key] < self._burst and self._logged.total() < self._total_burst:
            self._logged[key] += 1
            self._log.warning("rejected message on %s (%d so far): %s", key,
                              self.rejected[key] if key in self.rejected else self.rejected_total, reason)
        else:
            if not self._suppressed:
                self._log.warning("more rejected messages; logging at most %d per key and %d in all every %.0f s",
                                  self._burst, self._total_burst, self._window_s)
            self._suppressed[key if key in self._suppressed or len(self._suppressed) < 5 else self.OTHER_KEYS] += 1

    def _end_window(self) -> None:
        if self._suppressed:
            self._log.warning("%d rejected messages not logged in the last %.0f s (%s)", self._suppressed.total(),
                              self._window_s, ", ".join(f"{k}: {n}" for k, n in self._suppressed.most_common()))
        self._logged.clear()
        self._suppressed.clear()

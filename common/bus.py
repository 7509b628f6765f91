"""Thin helpers around zenoh-python 1.x shared by every service node and the tools.

Callbacks run on Zenoh's threads and a slow callback stalls the session, so subscriptions here only
decode (cheap, and rejects bad payloads at the edge) and hand the message to a queue or a latest-value
slot; nodes do their work on their own thread.
"""
from __future__ import annotations

import argparse
import json
import logging
import math
import queue
import re
import signal
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, Iterable, TypeVar

import zenoh

from common import keys
from common.codec import Decoder, Message, decode, encode
from common.messages import LARGEST_MESSAGE_BYTES

M = TypeVar("M")
log = logging.getLogger(__name__)

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")
SLOW_CONNECT_WARN_S = 5.0      # a router that takes longer than this to answer is worth a warning
# Zenoh retries a lost link after 1, 2, 4, 4 ... s, so a router restarted in 3.5 s was rejoined after 7 s;
# retrying every second at most puts a robot's services back on the bus within 1 s of their router
RECONNECT_RETRY = {"period_init_ms": 250, "period_max_ms": 1000, "period_increase_factor": 2}
_RUST_LOCATION = re.compile(r"\s+at\s+\S+\.rs:\d+(?::\d+)?\.?")
_JSON5_MESSAGE = re.compile(r'Json5Err\(Message \{ msg: "(.*?)", location.*\}\)', re.S)
_zenoh_log_started = False


def zenoh_config(mode: str, *, connect: Iterable[str] = (), listen: Iterable[str] = (),
                 connect_timeout_ms: int = -1, base: str | dict | None = None) -> zenoh.Config:
    """A session's config: `base` (a Zenoh JSON5 config file, or the same as a dict: TLS, access
    control, limits) with the mode and endpoints set on top of it, and RECONNECT_RETRY unless `base`
    sets its own `connect/retry`."""
    if isinstance(base, dict):
        conf = zenoh.Config.from_json5(json.dumps(base))
    elif base:
        conf = zenoh.Config.from_file(base)
    else:
        conf = zenoh.Config()
        # Zenoh's default reassembles fragments up to 1 GiB: a flood of huge payloads would take that
        # much memory before the codec's size check ever sees them
        conf.insert_json5("transport/link/rx/max_message_size", json.dumps(LARGEST_MESSAGE_BYTES))
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    listen = list(listen)
    connect = list(connect)
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(listen))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(connect))
        conf.insert_json5("connect/timeout_ms", json.dumps(connect_timeout_ms))
    if json.loads(conf.get_json("connect"))["retry"] is None:
        conf.insert_json5("connect/retry", json.dumps(RECONNECT_RETRY))
    return conf


def zenoh_error(exc: BaseException | str) -> str:
    """Zenoh's error text without the Rust source locations it appends (`at .../tcp.rs:61.`), which
    mean nothing to a user; a JSON5 configuration error is reduced to its message."""
    text = _RUST_LOCATION.sub("", str(exc))
    m = _JSON5_MESSAGE.search(text)
    return (m.group(1) if m else text).strip()


def open_session(endpoint: str = DEFAULT_ENDPOINT, mode: str = "client", stop: threading.Event | None = None,
                 timeout_s: float | None = None, zenoh_conf: str | dict | None = None) -> zenoh.Session:
    """Connect to the router, waiting for it if it is still starting.

    The wait happens in 1 s attempts so that SIGTERM/Ctrl-C (and `stop`) are honoured meanwhile: a
    single open() with an infinite timeout would block signal handling forever. A router started a
    moment ago is the normal case, so waiting is logged at INFO and only becomes a warning after
    SLOW_CONNECT_WARN_S. `zenoh_conf` is a Zenoh JSON5 config file or dict (TLS certificates for a
    secured deployment). Raises ValueError for a malformed endpoint or config, ConnectionError after
    `timeout_s` (None: keep trying) or when `stop` is set.
    """
    global _zenoh_log_started
    if not _zenoh_log_started:
        zenoh.init_log_from_env_or("error")
        _zenoh_log_started = True
    listen = ["tcp/127.0.0.1:0"] if mode == "peer" else []

    def config() -> zenoh.Config:
        return zenoh_config(mode, connect=[endpoint], listen=listen, connect_timeout_ms=1000,
                            base=zenoh_conf)
    try:
        config()   # a malformed endpoint or config never starts working: say so at once
    except zenoh.ZError as exc:
        what = "Zenoh config" + (f" {zenoh_conf}" if isinstance(zenoh_conf, str) else "") if zenoh_conf \
            else f"Zenoh endpoint {endpoint!r}"
        raise ValueError(f"invalid {what}: {zenoh_error(exc)}") from None
    t0 = time.monotonic()
    last_error, informed, warned = "", False, False
    while True:
        if stop is not None and stop.is_set():
            raise ConnectionError(f"stopped while connecting to {endpoint}")
        try:
            return zenoh.open(config())
        except zenoh.ZError as exc:
            last_error = zenoh_error(exc)
        waited = time.monotonic() - t0
        if timeout_s is not None and waited > timeout_s:
            raise ConnectionError(f"no Zenoh router at {endpoint} within {timeout_s:.0f} s ({last_error})")
        if not informed:
            log.info("waiting for a Zenoh router at %s ...", endpoint)
            informed = True
        if not warned and waited >= SLOW_CONNECT_WARN_S:
            log.warning("still no Zenoh router at %s after %.0f s; is it running?", endpoint, waited)
            warned = True


class Latest:
    """Latest-value slot written from a Zenoh callback thread, read from the node's thread."""

    def __init__(self):
        self._lock = threading.Lock()
        self._value = None
        self._seq = 0

    def set(self, value) -> None:
        with self._lock:
            self._value = value
            self._seq += 1

    def get(self) -> tuple[Any, int]:
        with self._lock:
            return self._value, self._seq


@dataclass
class Reply:
    key: str
    payload: bytes | None
    error: str | None


class Node:
    """One Zenoh client session with typed publish/subscribe/query helpers and a liveliness token."""

    def __init__(self, service: str, robot: str, endpoint: str = DEFAULT_ENDPOINT, logger: logging.Logger | None = None,
                 stop: threading.Event | None = None, zenoh_conf: str | dict | None = None):
        self.service = service
        self.robot = robot
        self.log = logger or logging.getLogger(service)
        self.decoder = Decoder(self.log)
        self.session = open_session(endpoint, stop=stop, zenoh_conf=zenoh_conf)
        self._decls: list[Any] = []
        self._pubs: dict[str, Any] = {}
        self._token = None

    # --- lifecycle -------------------------------------------------------------------------
    def declare_alive(self) -> None:
        self._token = self.session.liveliness().declare_token(keys.alive(self.robot, self.service))

    def close(self) -> None:
        for decl in reversed(self._decls):
            try:
                decl.undeclare()
            except Exception:  # already gone with the session; nothing left to release
                pass
        self._decls.clear()
        if self._token is not None:
            try:
                self._token.undeclare()
            except Exception:
                pass
            self._token = None
        if not self.session.is_closed():
            self.session.close()

    def __enter__(self) -> "Node":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # --- pub/sub ---------------------------------------------------------------------------
    def publish(self, key: str, msg: Message, droppable: bool = False) -> None:
        """Publish reliably: under congestion wait rather than drop (Zenoh's default is to drop),
        because commands, estimates, trial events and experiences must not silently vanish.
        Only streams where the newest sample supersedes the rest (camera frames) are droppable."""
        self._publisher(key, droppable).put(encode(msg))

    def _publisher(self, key: str, droppable: bool = False) -> zenoh.Publisher:
        pub = self._pubs.get(key)
        if pub is None:
            cc = zenoh.CongestionControl.DROP if droppable else zenoh.CongestionControl.BLOCK
            pub = self._pubs[key] = self.session.declare_publisher(key, congestion_control=cc)
            self._decls.append(pub)
        return pub

    def wait_matching(self, key: str, timeout_s: float, droppable: bool = False) -> bool:
        """Declare the publisher of `key` and wait until Zenoh knows a subscriber for it: samples put
        by a brand-new publisher before that may not reach anyone."""
        pub = self._publisher(key, droppable)
        deadline = time.monotonic() + timeout_s
        while not pub.matching_status.matching:
            if time.monotonic() > deadline:
                return False
            time.sleep(0.01)
        return True

    def subscribe(self, key: str, cls: type[M], handler: Callable[[M, str], None]) -> None:
        """Decode on the Zenoh thread and call `handler(msg, key)`; rejected payloads are logged and
        counted, never delivered."""
        def on_sample(sample: zenoh.Sample) -> None:
            k = str(sample.key_expr)
            msg = self.decoder(cls, sample.payload.to_bytes(), k)
            if msg is not None:
                handler(msg, k)
        self._decls.append(self.session.declare_subscriber(key, on_sample))

    def subscribe_queue(self, key: str, cls: type[M], inbox: "queue.Queue[tuple[str, Any]]") -> None:
        self.subscribe(key, cls, lambda msg, k: inbox.put((k, msg)))

    def subscribe_latest(self, key: str, cls: type[M]) -> Latest:
        slot = Latest()
        self.subscribe(key, cls, lambda msg, _k: slot.set(msg))
        return slot

    # --- queries ---------------------------------------------------------------------------
    def queryable(self, key: str, handler: Callable[[zenoh.Query], None]) -> None:
        self._decls.append(self.session.declare_queryable(key, handler))

    def liveliness_subscriber(self, key: str, handler: Callable[[str, bool], None]) -> None:
        def on_sample(sample: zenoh.Sample) -> None:
            handler(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)
        self._decls.append(self.session.liveliness().declare_subscriber(key, on_sample, history=True))


def query(session: zenoh.Session, selector: str, payload: bytes | None = None, timeout_s: float = 5.0,
          all_replies: bool = True) -> list[Reply]:
    """Blocking query; with all_replies every replier answers (no consolidation)."""
    kwargs: dict[str, Any] = {"timeout": timeout_s}
    if payload is not None:
        kwargs["payload"] = payload
    if all_replies:
        kwargs["consolidation"] = zenoh.QueryConsolidation(zenoh.ConsolidationMode.NONE)
        kwargs["target"] = zenoh.QueryTarget.ALL
    out = []
    for rep in session.get(selector, **kwargs):
        if rep.ok is not None:
            out.append(Reply(str(rep.ok.key_expr), rep.ok.payload.to_bytes(), None))
        else:
            out.append(Reply("", None, rep.err.payload.to_bytes().decode("utf-8", "replace")))
    return out


def query_one(session: zenoh.Session, selector: str, cls: type[M], payload: bytes | None = None,
              timeout_s: float = 5.0) -> M:
    """Query expecting one typed answer; raises LookupError with the reason otherwise."""
    replies = query(session, selector, payload, timeout_s, all_replies=False)
    for rep in replies:
        if rep.error is not None:
            raise LookupError(f"{selector}: {rep.error}")
        return decode(cls, rep.payload)
    raise LookupError(f"{selector}: no reply within {timeout_s:.1f} s")


def query_params(query_obj: zenoh.Query) -> dict[str, str]:
    """Selector parameters as a dict. Zenoh 1.x separates them with ';'; DESIGN.md and people write
    'vertex=3&speed=0.5', so both separators are accepted."""
    out = {}
    for part in str(query_obj.parameters).replace("&", ";").split(";"):
        if part:
            key, _, value = part.partition("=")
            out[key] = value
    return out


def int_param(params: dict[str, str], name: str, lo: int, hi: int, default: int | None = None) -> int | None:
    """A whole-number selector parameter within [lo, hi] (None if absent and no default): anything else
    is a ValueError naming the parameter, so a query like vertex=1e30 is answered with a reason."""
    if name not in params:
        return default
    text = params[name]
    if not re.fullmatch(r"[+-]?\d{1,18}", text) or not lo <= int(text) <= hi:
        raise ValueError(f"{name} must be a whole number in [{lo}, {hi}], got {text[:40]!r}")
    return int(text)


def float_param(params: dict[str, str], name: str, lo: float, hi: float) -> float:
    """A required finite number selector parameter within [lo, hi]."""
    text = params.get(name)
    try:
        value = float(text) if text is not None else math.nan
    except ValueError:
        value = math.nan
    if not lo <= value <= hi:
        raise ValueError(f"{name} must be a number in [{lo:g}, {hi:g}], got {str(text)[:40]!r}")
    return value


def reply(query_obj: zenoh.Query, key: str, msg: Message) -> None:
    query_obj.reply(key, encode(msg))


class AliveWatcher:
    """Tracks liveliness tokens under a key pattern; waits on events, never on fixed sleeps."""

    def __init__(self, session: zenoh.Session, pattern: str):
        self._cond = threading.Condition()
        self.alive: set[str] = set()
        self._sub = session.liveliness().declare_subscriber(pattern, self._on, history=True)

    def _on(self, sample: zenoh.Sample) -> None:
        with self._cond:
            key = str(sample.key_expr)
            if sample.kind == zenoh.SampleKind.PUT:
                self.alive.add(key)
            else:
                self.alive.discard(key)
            self._cond.notify_all()

    def wait_for(self, predicate: Callable[[set[str]], bool], timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while not predicate(self.alive):
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
            return True

    def is_alive(self, key: str) -> bool:
        with self._cond:
            return key in self.alive

    def close(self) -> None:
        try:
            self._sub.undeclare()
        except Exception:
            pass


def install_stop_handlers(stop: threading.Event) -> None:
    """SIGTERM and SIGINT set `stop` so the node leaves its loop and closes its session."""
    def handler(signum, _frame):
        log.info("signal %d received, stopping", signum)
        stop.set()
    signal.signal(signal.SIGTERM, handler)
    signal.signal(signal.SIGINT, handler)


def add_log_level_argument(parser: argparse.ArgumentParser, default: str = "INFO") -> None:
    """--log-level for every entry point; a misspelt level is an error, not silently INFO."""
    parser.add_argument("--log-level", default=default, type=str.upper, choices=LOG_LEVELS, metavar="LEVEL",
                        help=f"one of {', '.join(LOG_LEVELS)} (default {default})")


def setup_logging(service: str, level: str = "INFO") -> logging.Logger:
    # force: the `lbc` command line may already have configured logging for itself
    logging.basicConfig(level=getattr(logging, level.upper(), logging.INFO), force=True,
                        format=f"%(asctime)s %(levelname)s {service} %(name)s: %(message)s")
    return logging.getLogger(service)

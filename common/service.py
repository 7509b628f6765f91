"""What every service process shares: command line, config, session, liveliness, trial-control
queryable, one inbox drained by the service's own thread, clean shutdown on SIGTERM/SIGINT.

Zenoh callbacks only decode and enqueue; the service's thread does the work and answers control
queries itself (a query may be answered after its callback returned).
"""
from __future__ import annotations

import argparse
import logging
import queue
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, TypeVar

import zenoh

from common import keys
from common.bus import DEFAULT_ENDPOINT, Node, add_log_level_argument, install_stop_handlers, setup_logging
from common.codec import DecodeError, decode, encode
from common.config import ConfigError, load_config
from common.lifecycle import die_with_parent
from common.messages import ControlReply, ControlRequest

C = TypeVar("C")


@dataclass
class Control:
    """A trial-control request waiting for its answer."""
    request: ControlRequest
    query: zenoh.Query
    key: str

    def answer(self, ok: bool, detail: str = "", service: str = "") -> None:
        msg = ControlReply(stamp_s=time.time(), service=service, ok=ok, detail=detail)
        try:
            self.query.reply(self.key, encode(msg))
        finally:
            self.query.drop()


class Service:
    """Base class: subclasses subscribe in __init__ and implement on_message/on_control/on_idle."""

    name = "service"

    def __init__(self, node: Node):
        self.node = node
        self.log = node.log
        self.inbox: queue.Queue[tuple[str, Any]] = queue.Queue()
        self._control_key = keys.control(node.robot, self.name)
        node.queryable(self._control_key, self._on_control_query)

    def _on_control_query(self, query: zenoh.Query) -> None:
        payload = query.payload
        try:
            if payload is None:
                raise DecodeError("empty control request")
            req = decode(ControlRequest, payload.to_bytes())
        except DecodeError as exc:
            self.node.decoder.reject(self._control_key, f"control request: {exc}")
            try:
                query.reply_err(f"rejected: {exc}".encode())
            finally:
                query.drop()
            return
        self.inbox.put(("__control__", Control(req, query, self._control_key)))

    def reply(self, ctl: Control, ok: bool, detail: str = "") -> None:
        (self.log.info if ok else self.log.warning)("control %s/%s trial %d: %s%s", ctl.request.action,
                                                    ctl.request.mode, ctl.request.trial,
                                                    "ok" if ok else "refused", f" ({detail})" if detail else "")
        ctl.answer(ok, detail, self.name)

    # --- hooks -------------------------------------------------------------------------------
    def on_message(self, key: str, msg: Any) -> None:
        raise NotImplementedError

    def on_control(self, ctl: Control) -> None:
        raise NotImplementedError

    def on_idle(self) -> None:
        """Called when the inbox stays empty for `idle_timeout_s`."""

    idle_timeout_s = 0.1

    def dispatch(self, key: str, item: Any) -> None:
        if key == "__control__":
            try:
                self.on_control(item)
            except Exception as exc:  # a bad request must not kill the service
                self.log.exception("control request failed")
                item.answer(False, f"{type(exc).__name__}: {exc}", self.name)
            return
        try:
            self.on_message(key, item)
        except Exception as exc:  # well-formed but unusable input: log and count it, keep running
            # rate-limited like malformed input (a flood of these must not flood the log); the traceback
            # at DEBUG
            self.node.decoder.reject(key, f"could not be handled: {type(exc).__name__}: {exc}")
            self.log.debug("message on %s could not be handled", key, exc_info=True)

    def run(self, stop: threading.Event) -> None:
        while not stop.is_set():
            try:
                key, item = self.inbox.get(timeout=self.idle_timeout_s)
            except queue.Empty:
                self.on_idle()
                continue
            self.dispatch(key, item)

    def close(self) -> None:
        """Release anything beyond the session (files, workers)."""


def service_main(name: str, config_cls: type[C], build: Callable[[C, Node], Service],
                 robot_of: Callable[[C], str], argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog=f"python -m services.{name}", description=f"lbc {name} service")
    parser.add_argument("--config", required=True, help="service configuration (TOML)")
    parser.add_argument("--connect", default=DEFAULT_ENDPOINT, help="Zenoh router endpoint")
    parser.add_argument("--zenoh-config", default=None, metavar="FILE",
                        help="Zenoh JSON5 config for the session (TLS certificates of a secured deployment)")
    add_log_level_argument(parser)
    args = parser.parse_args(argv)
    die_with_parent()
    log = setup_logging(name, args.log_level)
    try:
        cfg = load_config(config_cls, args.config)
    except ConfigError as exc:
        log.error("bad configuration: %s", exc)
        return 2
    stop = threading.Event()
    install_stop_handlers(stop)
    try:
        node = Node(name, robot_of(cfg), args.connect, log, stop=stop, zenoh_conf=args.zenoh_config)
    except ConnectionError as exc:
        log.info("%s stopped before connecting: %s", name, exc)
        return 0
    except ValueError as exc:   # a malformed --connect endpoint or --zenoh-config
        log.error("cannot connect: %s", exc)
        return 2
    service = None
    try:
        try:
            service = build(cfg, node)
        except ConfigError as exc:
            log.error("cannot start: %s", exc)
            return 2
        node.declare_alive()
        log.info("%s up for robot %s via %s", name, node.robot, args.connect)
        service.run(stop)
    except Exception:
        log.exception("%s crashed", name)
        return 1
    finally:
        if service is not None:
            service.close()
        node.close()
        log.info("%s stopped", name)
        logging.shutdown()
    return 0

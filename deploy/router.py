"""The Zenoh router: a Python session in `router` mode listening on tcp/127.0.0.1:<port> (or any
endpoint, e.g. tls/10.0.0.1:7447 with a JSON5 config holding certificates, links to other routers and
access control), multicast scouting off (no zenohd is needed). Runs until SIGTERM/SIGINT, then
closes cleanly."""
from __future__ import annotations

import argparse
import logging
import socket
import threading

import zenoh

from common.bus import add_log_level_argument, install_stop_handlers, setup_logging, zenoh_config, zenoh_error
from common.lifecycle import die_with_parent

READY_LINE = "router listening on"   # the launcher waits for this line in the router's log


def free_port() -> int:
    """A currently free TCP port on loopback (for tests and private experiment routers)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def open_router(port: int, host: str = "127.0.0.1", listen: str | None = None,
                zenoh_conf: str | None = None) -> zenoh.Session:
    zenoh.init_log_from_env_or("error")
    return zenoh.open(zenoh_config("router", listen=[listen or f"tcp/{host}:{port}"], base=zenoh_conf))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The router's options, shared by `python -m deploy.router` and `lbc router`."""
    parser.add_argument("--port", type=int, default=7447, help="TCP port to listen on (default 7447)")
    parser.add_argument("--host", default="127.0.0.1", help="interface to listen on (0.0.0.0 for a fleet)")
    parser.add_argument("--listen", default=None, metavar="ENDPOINT",
                        help="endpoint to listen on instead of tcp/HOST:PORT, e.g. tls/10.0.0.1:7447")
    parser.add_argument("--zenoh-config", default=None, metavar="FILE",
                        help="Zenoh JSON5 config (TLS, links to other routers, access control)")
    add_log_level_argument(parser)


def run(args: argparse.Namespace) -> int:
    """Listen until SIGTERM/SIGINT; says where it listens, or why it cannot."""
    die_with_parent()
    log = setup_logging("router", args.log_level)
    stop = threading.Event()
    install_stop_handlers(stop)
    endpoint = args.listen or f"tcp/{args.host}:{args.port}"
    try:
        session = open_router(args.port, args.host, args.listen, args.zenoh_config)
    except zenoh.ZError as exc:
        log.error("cannot listen on %s: %s", endpoint, zenoh_error(exc))
        return 1
    log.info(READY_LINE + " %s (zid %s)", endpoint, session.zid())
    try:
        stop.wait()
    finally:
        session.close()
        log.info("router stopped")
        logging.shutdown()
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="lbc router", description="run the local Zenoh router")
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    raise SystemExit(main())

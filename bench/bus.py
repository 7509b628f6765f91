"""`lbc bench bus`: Zenoh round-trip latency through a real local router.

Measures, from this process as a client, against a responder in another OS process:
- query RTT: `session.get()` on a queryable that replies at once (timed until the reply stream ends,
  i.e. what a `common.bus.query` caller waits);
- pub/sub ping-pong RTT: ping on `<prefix>/ping`, the responder republishes on `<prefix>/pong`.

The router (unless `--connect` names a running one) and the responder are child processes that are
always terminated in a `finally`. The last stdout line is one JSON object with the results.
"""
from __future__ import annotations

import argparse
import logging
import os
import queue
import statistics
import struct
import subprocess
import sys
import threading
import time
import uuid
from typing import Callable

import zenoh

from bench.report import run_and_print
from common.bus import AliveWatcher, install_stop_handlers, open_session, setup_logging, zenoh_config
from common.codec import encode
from common.lifecycle import PARENT_ENV
from common.messages import Clock

log = logging.getLogger("bench.bus")

READY_TIMEOUT_S = 30.0   # router up + responder declared
REPLY_TIMEOUT_S = 1.0    # one query / one pong


def _keys(prefix: str) -> dict[str, str]:
    return {k: f"{prefix}/{k}" for k in ("query", "ping", "pong", "alive")}


# --- responder (child process) --------------------------------------------------------------------
def _wait_eof(stop: threading.Event) -> None:
    try:
        while os.read(0, 4096):  # raw fd: a blocked buffered read would abort interpreter shutdown
            pass
    except OSError:
        pass
    stop.set()


def run_responder(endpoint: str, prefix: str) -> int:
    keys = _keys(prefix)
    stop = threading.Event()
    install_stop_handlers(stop)
    # the parent holds our stdin: EOF means it is gone, so never outlive it
    threading.Thread(target=_wait_eof, args=(stop,), daemon=True).start()
    session = open_session(endpoint)
    decls = []
    try:
        pong = session.declare_publisher(keys["pong"])
        decls.append(pong)
        decls.append(session.declare_subscriber(keys["ping"], lambda s: pong.put(s.payload)))
        decls.append(session.declare_queryable(
            keys["query"], lambda q: q.reply(keys["query"], q.payload.to_bytes() if q.payload else b"")))
        decls.append(session.liveliness().declare_token(keys["alive"]))
        log.info("responder ready on %s under %s", endpoint, prefix)
        stop.wait()
    finally:
        for d in reversed(decls):
            try:
                d.undeclare()
            except Exception:  # already gone with the session
                pass
        session.close()
    return 0


# --- measurement (main process) -------------------------------------------------------------------
def make_payload(seq: int, size: int | None) -> bytes:
    """An encoded Clock (fixed 66 B: the sequence rides in the float stamp) or `size` raw bytes."""
    if size is None:
        return encode(Clock(stamp_s=float(seq), tick=0, period_s=0.01, mode="realtime", trial=0))
    return struct.pack("<Q", seq).ljust(size, b"\0")


def query_rtt_ns(session: zenoh.Session, key: str, payload: bytes) -> int | None:
    t0 = time.perf_counter_ns()
    ok = False
    for rep in session.get(key, payload=payload, timeout=REPLY_TIMEOUT_S):
        ok = ok or rep.ok is not None
    return time.perf_counter_ns() - t0 if ok else None


class PingPong:
    def __init__(self, session: zenoh.Session, keys: dict[str, str]):
        self._inbox: queue.Queue[tuple[int, bytes]] = queue.Queue()
        self._sub = session.declare_subscriber(
            keys["pong"], lambda s: self._inbox.put((time.perf_counter_ns(), s.payload.to_bytes())))
        self._pub = session.declare_publisher(keys["ping"])

    def rtt_ns(self, payload: bytes) -> int | None:
        """One ping; None if its pong does not come back in time (stale pongs are discarded)."""
        deadline = time.monotonic() + REPLY_TIMEOUT_S
        t0 = time.perf_counter_ns()
        self._pub.put(payload)
        while (left := deadline - time.monotonic()) > 0:
            try:
                t1, data = self._inbox.get(timeout=left)
            except queue.Empty:
                break
            if data == payload:
                return t1 - t0
        return None

    def close(self) -> None:
        for d in (self._pub, self._sub):
            try:
                d.undeclare()
            except Exception:
                pass


def wait_until(check: Callable[[], bool], what: str, procs: list[subprocess.Popen]) -> None:
    """Retry `check` (which itself blocks on an event or a reply) until true; fail fast if a child dies."""
    deadline = time.monotonic() + READY_TIMEOUT_S
    while not check():
        for p in procs:
            if p.poll() is not None:
                raise RuntimeError(f"{what}: child {p.args} exited with {p.returncode}")
        if time.monotonic() > deadline:
            raise TimeoutError(f"{what}: not ready after {READY_TIMEOUT_S:.0f} s")


def measure(fn: Callable[[bytes], int | None], n: int, warmup: int, size: int | None) -> tuple[list[float], int]:
    rtts, lost = [], 0
    for seq in range(warmup + n):
        ns = fn(make_payload(seq, size))
        if seq < warmup:
            continue
        if ns is None:
            lost += 1
        else:
            rtts.append(ns / 1e6)
    if not rtts:
        raise RuntimeError("no round trip succeeded")
    return rtts, lost


def summary(name: str, rtts: list[float]) -> dict[str, float]:
    p99 = statistics.quantiles(rtts, n=100, method="inclusive")[98] if len(rtts) > 1 else rtts[0]
    return {f"{name}_rtt_ms_p50": round(statistics.median(rtts), 4), f"{name}_rtt_ms_p99": round(p99, 4),
            f"{name}_rtt_ms_mean": round(statistics.fmean(rtts), 4), f"{name}_rtt_ms_max": round(max(rtts), 4)}


def spawn(args: list[str]) -> subprocess.Popen:
    # LBC_PARENT_PID: the router also exits if this process is killed outright (common.lifecycle)
    env = dict(os.environ, **{PARENT_ENV: str(os.getpid())})
    return subprocess.Popen([sys.executable, "-m", *args], stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, env=env)


def stop_child(proc: subprocess.Popen | None, timeout_s: float = 5.0) -> None:
    if proc is None:
        return
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            log.warning("%s ignored SIGTERM for %.0f s, killing it", proc.args, timeout_s)
            proc.kill()
            proc.wait()
    if proc.stdin:
        proc.stdin.close()


def client_session(endpoint: str) -> zenoh.Session:
    conf = zenoh_config("client", connect=[endpoint])
    conf.insert_json5("connect/timeout_ms", str(int(READY_TIMEOUT_S * 1000)))  # fail, don't hang, if no router
    return zenoh.open(conf)


def run_bench(args: argparse.Namespace) -> dict:
    from deploy.router import free_port

    keys = _keys(prefix := f"lbc/bench/bus/{uuid.uuid4().hex[:12]}")
    router = responder = session = None
    try:
        endpoint = args.connect
        if endpoint is None:
            port = free_port()
            endpoint = f"tcp/127.0.0.1:{port}"
            router = spawn(["deploy.router", "--port", str(port), "--log-level", "WARNING"])
        responder = spawn(["bench.bus", "--responder", "--connect", endpoint, "--prefix", prefix,
                           "--log-level", "WARNING"])
        children = [p for p in (router, responder) if p]
        log.info("connecting to %s", endpoint)
        session = client_session(endpoint)
        watcher = AliveWatcher(session, keys["alive"])
        pingpong = PingPong(session, keys)
        try:
            wait_until(lambda: watcher.wait_for(lambda alive: keys["alive"] in alive, 0.5), "responder", children)
            # the token proves the responder's declarations reached the router; one full round trip of
            # each kind proves ours reached it too
            wait_until(lambda: query_rtt_ns(session, keys["query"], make_payload(0, args.payload_bytes)) is not None,
                       "query path", children)
            wait_until(lambda: pingpong.rtt_ns(make_payload(0, args.payload_bytes)) is not None,
                       "ping-pong path", children)
            log.info("measuring query RTT (%d + %d warmup)", args.n, args.warmup)
            q_rtts, q_lost = measure(lambda p: query_rtt_ns(session, keys["query"], p),
                                     args.n, args.warmup, args.payload_bytes)
            log.info("measuring ping-pong RTT (%d + %d warmup)", args.n, args.warmup)
            p_rtts, p_lost = measure(pingpong.rtt_ns, args.n, args.warmup, args.payload_bytes)
        finally:
            pingpong.close()
            watcher.close()
    finally:
        if session is not None:
            session.close()
        stop_child(responder)
        stop_child(router)
    return {"endpoint": endpoint, "n": args.n, "warmup": args.warmup,
            "payload": "clock" if args.payload_bytes is None else "raw",
            "payload_bytes": len(make_payload(0, args.payload_bytes)),
            **summary("query", q_rtts), "query_errors": q_lost,
            **summary("pingpong", p_rtts), "pingpong_timeouts": p_lost}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="lbc bench bus", description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=2000, help="round trips per measurement")
    parser.add_argument("--warmup", type=int, default=200, help="unrecorded round trips before each measurement")
    parser.add_argument("--payload-bytes", type=int, default=None,
                        help="raw payload size (>= 8); default: one encoded Clock message (66 B)")
    parser.add_argument("--connect", default=None, metavar="ENDPOINT",
                        help="use this running router instead of starting one")
    parser.add_argument("--log-level", default="INFO")
    parser.add_argument("--responder", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--prefix", default="lbc/bench/bus/manual", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    setup_logging("bench", args.log_level)
    if args.responder:
        if not args.connect:
            parser.error("--responder needs --connect")
        return run_responder(args.connect, args.prefix)
    if args.n < 1 or args.warmup < 0:
        parser.error("--n must be >= 1 and --warmup >= 0")
    if args.payload_bytes is not None and args.payload_bytes < 8:
        parser.error("--payload-bytes must be >= 8 (the sequence number)")

    return run_and_print(lambda: run_bench(args))


if __name__ == "__main__":
    raise SystemExit(main())

"""Starts the local router and every service as its own OS process, and stops them all cleanly.

Each child gets its own log file and LBC_PARENT_PID, so it also stops (SIGTERM) if the launcher is
killed outright. `stop()` sends SIGTERM to services first (their sessions close), then the router,
and SIGKILLs only what has not exited within the grace period.
"""
from __future__ import annotations

import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from common.bus import AliveWatcher
from common.lifecycle import PARENT_ENV
from deploy.router import READY_LINE

log = logging.getLogger(__name__)


class LaunchError(RuntimeError):
    """A child did not come up; the message says which and why (the last lines of its log)."""


def port_in_use(port: int, host: str = "127.0.0.1") -> bool:
    """Whether something already holds the TCP port. With SO_REUSEADDR, so that a port left in
    TIME_WAIT by a router that just stopped does not count as taken; a listener still does."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError:
            return True
    return False


@dataclass
class Child:
    name: str
    proc: subprocess.Popen
    log_path: Path
    log_offset: int = 0     # where this child's output starts: log files are appended to across runs
    args: tuple[str, ...] = ()
    started_s: float = 0.0  # monotonic

    def output(self) -> str:
        try:
            with open(self.log_path, "rb") as fh:
                fh.seek(self.log_offset)
                return fh.read().decode(errors="replace")
        except OSError:
            return ""

    def tail(self, lines: int = 15) -> str:
        return "\n".join(self.output().splitlines()[-lines:])


class Launcher:
    def __init__(self, endpoint: str, log_dir: str | Path):
        self.endpoint = endpoint
        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.children: list[Child] = []

    def _spawn(self, name: str, args: list[str]) -> Child:
        log_path = self.log_dir / f"{name}.log"
        env = dict(os.environ, **{PARENT_ENV: str(os.getpid()), "PYTHONUNBUFFERED": "1"})
        # one BLAS thread per process: several services share few cores, and a multi-threaded BLAS
        # fighting over them makes small solves 5-100x slower (set them yourself to override)
        for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
            env.setdefault(var, "1")
        with open(log_path, "ab") as fh:
            offset = fh.tell()
            proc = subprocess.Popen([sys.executable, *args], stdout=fh, stderr=subprocess.STDOUT,
                                    stdin=subprocess.DEVNULL, env=env)
        child = Child(name, proc, log_path, offset, tuple(args), time.monotonic())
        self.children.append(child)
        log.debug("started %s (pid %d): %s", name, proc.pid, " ".join(args))
        return child

    def start_router(self, port: int, listen: str | None = None, zenoh_conf: str | Path | None = None) -> Child:
        args = ["-m", "deploy.router", "--port", str(port)]
        args += ["--listen", listen] if listen else []
        args += ["--zenoh-config", str(zenoh_conf)] if zenoh_conf else []
        return self._spawn("router", args)

    def start_service(self, service: str, config_path: str | Path, log_level: str = "INFO",
                      zenoh_conf: str | Path | None = None) -> Child:
        args = ["-m", f"services.{service}", "--config", str(config_path), "--connect", self.endpoint,
                "--log-level", log_level]
        args += ["--zenoh-config", str(zenoh_conf)] if zenoh_conf else []
        return self._spawn(service, args)

    def restart(self, child: Child) -> Child:
        """Start a child that exited again, with the same arguments, appending to its log."""
        self.children.remove(child)
        return self._spawn(child.name, list(child.args))

    def wait_router(self, timeout_s: float = 15.0) -> None:
        """Return once the router listens; raise LaunchError if it exits first (port taken, bad
        address) or stays silent, so that nothing claims a deployment that is not there."""
        router = next(c for c in self.children if c.name == "router")
        deadline = time.monotonic() + timeout_s
        while True:
            if router.proc.poll() is not None:
                raise LaunchError(f"the router exited ({router.proc.returncode}):\n{router.tail()}")
            if READY_LINE in router.output():
                return
            if time.monotonic() > deadline:
                raise LaunchError(f"the router did not listen within {timeout_s:.0f} s:\n{router.tail()}")
            time.sleep(0.02)  # its log file is the only signal a child process gives

    def wait_alive(self, session, expected: dict[str, str], timeout_s: float = 60.0,
                   stop: threading.Event | None = None) -> bool:
        """Wait until every service in `expected` (name -> liveliness key) has declared itself alive.
        Raises LaunchError when a child exits or time runs out; returns False if `stop` was set."""
        watcher = AliveWatcher(session, "lbc/alive/**")
        deadline = time.monotonic() + timeout_s
        try:
            while not watcher.wait_for(lambda alive: set(expected.values()) <= alive, 0.2):
                dead = self.exited()
                if dead:
                    raise LaunchError(f"{dead[0].name} exited ({dead[0].proc.returncode}):\n{dead[0].tail()}")
                if stop is not None and stop.is_set():
                    return False
                if time.monotonic() > deadline:
                    missing = [name for name, key in expected.items() if not watcher.is_alive(key)]
                    raise LaunchError(f"not up within {timeout_s:.0f} s: {', '.join(missing)}")
            return True
        finally:
            watcher.close()

    def exited(self) -> list[Child]:
        return [c for c in self.children if c.proc.poll() is not None]

    def kill(self, name: str, sig: int = signal.SIGKILL) -> None:
        for c in self.children:
            if c.name == name and c.proc.poll() is None:
                c.proc.send_signal(sig)

    def stop(self, grace_s: float = 5.0) -> None:
        services = [c for c in self.children if c.name != "router"]
        routers = [c for c in self.children if c.name == "router"]
        for group in (services, routers):  # services first: they close their sessions via the router
            for c in group:
                if c.proc.poll() is None:
                    c.proc.send_signal(signal.SIGTERM)
            deadline = time.monotonic() + grace_s
            for c in group:
                try:
                    c.proc.wait(timeout=max(0.0, deadline - time.monotonic()))
                except subprocess.TimeoutExpired:
                    log.warning("%s (pid %d) ignored SIGTERM for %.0f s; killing it", c.name, c.proc.pid, grace_s)
                    c.proc.kill()
                    c.proc.wait()
        self.children.clear()

    def __enter__(self) -> "Launcher":
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

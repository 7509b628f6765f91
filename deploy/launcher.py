"""Starts the local router and every service as its own OS process, and stops them all cleanly.

Each child gets its own log file and LBC_PARENT_PID, so it also stops (SIGTERM) if the launcher is
killed outright. `stop()` sends SIGTERM to services first (their sessions close), then the router,
and SIGKILLs only what has not exited within the grace period.
"""
from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from common.lifecycle import PARENT_ENV

log = logging.getLogger(__name__)


@dataclass
class Child:
    name: str
    proc: subprocess.Popen
    log_path: Path

    def tail(self, lines: int = 15) -> str:
        try:
            text = self.log_path.read_text(errors="replace").splitlines()
        except OSError:
            return ""
        return "\n".join(text[-lines:])


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
            proc = subprocess.Popen([sys.executable, *args], stdout=fh, stderr=subprocess.STDOUT,
                                    stdin=subprocess.DEVNULL, env=env)
        child = Child(name, proc, log_path)
        self.children.append(child)
        log.debug("started %s (pid %d): %s", name, proc.pid, " ".join(args))
        return child

    def start_router(self, port: int) -> Child:
        return self._spawn("router", ["-m", "deploy.router", "--port", str(port)])

    def start_service(self, service: str, config_path: str | Path, log_level: str = "INFO") -> Child:
        return self._spawn(service, ["-m", f"services.{service}", "--config", str(config_path),
                                     "--connect", self.endpoint, "--log-level", log_level])

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

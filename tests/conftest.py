"""Fixtures for integration tests: a real local Zenoh router and real service processes."""
from __future__ import annotations

import io
import os
import signal
import time
from pathlib import Path

# One BLAS thread per process, set before numpy loads (children inherit it): the suite runs service
# processes beside the test process on 2 cores, and OpenBLAS's spinning worker threads, oversubscribed,
# made one GP test take 742 s instead of 11 (124 s against 10 s with two busy loops beside it).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import pytest  # noqa: E402

from common.bus import open_session
from common.scenario import parse_scenario
from deploy.configs import service_configs, write_service_configs
from deploy.experiment import Experiment, Progress, services_of
from deploy.launcher import Launcher
from deploy.router import free_port

SHORT_SCENARIO = {
    "name": "itest", "seed": 4,
    "robot": {"preset": "husky", "name": "r1"},
    "path": {"waypoints": [[0, 0], [6, 0], [10, 3]], "teach_speed_mps": 0.8},
    "localization": {"source": "pose", "noise_m": 0.005, "delay_s": 0.1},
    "controller": {"algorithm": "fl"},
    "trials": {"count": 2, "speed": 0.8},
}


def ctrl_c_reaches_child() -> None:
    """preexec_fn for a child a test will send SIGINT: a test run started in the background (`nohup ...
    &`) ignores SIGINT, every child inherits that, and Python then never raises KeyboardInterrupt."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def wait_until(predicate, timeout_s: float, what: str, state=None) -> None:
    """Wait for a condition that an event outside our control makes true (e.g. a log line); `state`
    says, on a time-out, where things stood."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s:.0f} s waiting for {what}"
                                 + (f" ({state()})" if state else ""))
        time.sleep(0.05)


class Deployment:
    def __init__(self, base: Path, scenario: dict):
        self.base = base
        self.sc = parse_scenario(scenario)
        self.port = free_port()
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        self.paths = write_service_configs(service_configs(self.sc, base / "data"), base / "config")
        self.launcher = Launcher(self.endpoint, base / "logs")
        self.launcher.start_router(self.port)
        for s in services_of(self.sc):
            self.launcher.start_service(s, self.paths[s], "INFO")
        self.session = open_session(self.endpoint)
        self.exp = Experiment(self.sc, self.session, None, Progress(io.StringIO()), self.launcher)
        self.exp.wait_ready()

    def log(self, service: str) -> str:
        return (self.base / "logs" / f"{service}.log").read_text(errors="replace")

    def close(self) -> None:
        self.exp.close()
        self.session.close()
        self.launcher.stop()


@pytest.fixture
def deployment(tmp_path):
    dep = Deployment(tmp_path, SHORT_SCENARIO)
    try:
        yield dep
    finally:
        dep.close()


@pytest.fixture
def scenario_file(tmp_path):
    def write(data: dict = SHORT_SCENARIO) -> Path:
        path = tmp_path / f"{data['name']}.toml"
        path.write_text(dump_toml_dict(data))
        return path
    return write


def dump_toml_dict(data: dict) -> str:
    from common.config import _dump_table
    return _dump_table(data, [])

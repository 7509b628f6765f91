"""The `lbc` command line as a new user meets it (issue 17): run as a subprocess wherever that is what
the user does, waiting on its output, never on fixed sleeps."""
from __future__ import annotations

import json
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
from pathlib import Path

import pytest
import zenoh

from common import bus
from common.bus import AliveWatcher, open_session
from common.config import ConfigError
from common.messages import HyperMsg, HyperDim
from common.scenario import parse_scenario
from deploy.metrics import TrialRecord
from deploy.router import free_port, open_router
from tests.conftest import SHORT_SCENARIO, ctrl_c_reaches_child, wait_until
from tests.test_shutdown import alive, children_of

ROOT = Path(__file__).resolve().parents[1]
LBC = [sys.executable, "-m", "deploy.cli"]   # what the `lbc` script runs (deploy.cli:main)
RUST_LOCATION = ".rs:"


def lbc(*args: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
    return subprocess.run([*LBC, *args], cwd=ROOT, capture_output=True, text=True, timeout=timeout,
                          env=dict(os.environ, PYTHONPATH=str(ROOT)))


class Running:
    """A CLI process whose stderr is read line by line on a thread, so tests can wait for a line."""

    def __init__(self, *args: str, prefix: tuple[str, ...] = ()):
        self.proc = subprocess.Popen([*prefix, *LBC, *args], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                     text=True, env=dict(os.environ, PYTHONPATH=str(ROOT)),
                                     preexec_fn=ctrl_c_reaches_child)
        self.lines: list[str] = []
        self._cond = threading.Condition()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.proc.stderr:
            with self._cond:
                self.lines.append(line)
                self._cond.notify_all()
        with self._cond:
            self.lines.append(None)   # end of output
            self._cond.notify_all()

    def wait_for(self, text: str, timeout_s: float) -> str | None:
        """The first stderr line containing `text`; None if the output ended or time ran out first."""
        with self._cond:
            found = self._cond.wait_for(lambda: any(l is None or text in l for l in self.lines), timeout_s)
            return next((l for l in self.lines if l is not None and text in l), None) if found else None

    def finish(self, timeout_s: float = 30.0) -> tuple[int, str]:
        rc = self.proc.wait(timeout=timeout_s)
        self._reader.join(timeout_s)
        return rc, "".join(l for l in self.lines if l is not None)

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


@pytest.fixture
def busy_port():
    """A port held by a listening socket the test owns."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        yield s.getsockname()[1]


def write_scenario(tmp_path: Path, data: dict) -> Path:
    from tests.conftest import dump_toml_dict
    path = tmp_path / f"{data['name']}.toml"
    path.write_text(dump_toml_dict(data))
    return path


# --- help, version, options --------------------------------------------------------------------------
def test_lbc_alone_prints_help():
    r = lbc()
    assert r.returncode == 0, r.stderr
    assert "usage: lbc" in r.stdout and "experiment" in r.stdout and "launch" in r.stdout
    assert "error" not in r.stderr


def test_lbc_version_prints_the_version():
    from importlib.metadata import version
    r = lbc("--version")
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == f"lbc {version('lbc')}"


def test_an_unknown_log_level_is_refused(tmp_path):
    scenario = write_scenario(tmp_path, SHORT_SCENARIO)
    r = lbc("experiment", "run", str(scenario), "--out", str(tmp_path / "out"), "--log-level", "LOUD")
    assert r.returncode == 2
    assert "LOUD" in r.stderr and "INFO" in r.stderr   # names the bad value and the choices
    assert not (tmp_path / "out").exists()
    r = lbc("experiment", "run", str(scenario), "--out", str(tmp_path / "out"), "--log-level", "debug",
            "--connect", "tcp/127.0.0.1:1", "--connect-timeout", "0")
    assert "--log-level" not in r.stderr            # any case of a real level is fine


# --- the scenario's speeds against the robot's limit ---------------------------------------------------
@pytest.mark.parametrize("section, values, name", [
    ("trials", {"count": 1, "speed": 100.0}, "trials.speed = 100"),
    ("trials", {"count": 2, "speeds": [0.5, 1.5]}, "trials.speeds[1] = 1.5"),
    ("scheduler", {"enabled": True, "v_init": 1.2}, "scheduler.v_init = 1.2"),
])
def test_speeds_beyond_the_robot_limit_are_refused_at_load(section, values, name):
    with pytest.raises(ConfigError) as err:
        parse_scenario(dict(SHORT_SCENARIO, **{section: values}))
    assert name in str(err.value) and "v_max_mps = 1 m/s" in str(err.value) and "husky" in str(err.value)


def test_speeds_within_the_limit_and_a_scheduler_v_max_ceiling_are_accepted():
    parse_scenario(dict(SHORT_SCENARIO, trials={"count": 1, "speed": 1.0}))
    # the scheduler's v_max is a ceiling clamped to the robot's limit (DESIGN.md sets 2 m/s on a husky)
    parse_scenario(dict(SHORT_SCENARIO, scheduler={"enabled": True, "v_max": 2.0}))
    with pytest.raises(ConfigError, match="set in \\[robot\\]"):
        parse_scenario(dict(SHORT_SCENARIO, robot={"preset": "husky", "v_max_mps": 0.5}))


def test_lbc_experiment_refuses_a_speed_the_robot_cannot_drive(tmp_path):
    scenario = write_scenario(tmp_path, dict(SHORT_SCENARIO, trials={"count": 1, "speed": 100.0}))
    r = lbc("experiment", "run", str(scenario), "--out", str(tmp_path / "out"))
    assert r.returncode == 2
    assert "trials.speed = 100 m/s exceeds the robot's speed limit, v_max_mps = 1 m/s" in r.stderr
    assert not (tmp_path / "out").exists()


# --- errors without Rust source locations -------------------------------------------------------------
def test_zenoh_errors_lose_their_rust_source_locations(busy_port):
    from common.bus import zenoh_error
    with pytest.raises(zenoh.ZError) as err:
        open_router(busy_port)
    assert RUST_LOCATION in str(err.value)   # what Zenoh gives
    text = zenoh_error(err.value)
    assert RUST_LOCATION not in text and "Address already in use" in text
    with pytest.raises(ValueError) as bad:
        open_session("no-such-endpoint", timeout_s=1.0)
    assert RUST_LOCATION not in str(bad.value) and "no-such-endpoint" in str(bad.value)


def test_a_bad_connect_endpoint_is_reported_at_once_and_plainly(tmp_path):
    scenario = write_scenario(tmp_path, SHORT_SCENARIO)
    r = lbc("experiment", "run", str(scenario), "--out", str(tmp_path / "out"), "--connect", "bogus")
    assert r.returncode == 1
    assert "invalid Zenoh endpoint 'bogus'" in r.stderr and RUST_LOCATION not in r.stderr


@pytest.mark.integration
def test_lbc_router_on_a_busy_port_says_so_without_rust_locations(busy_port):
    r = lbc("router", "--port", str(busy_port))
    assert r.returncode == 1
    assert f"cannot listen on tcp/127.0.0.1:{busy_port}" in r.stderr and "Address already in use" in r.stderr
    assert RUST_LOCATION not in r.stderr


# --- waiting for the router ------------------------------------------------------------------------------
class _StartRouterWhenWaiting(logging.Handler):
    """Starts the router the moment open_session reports that it waits: the usual start-up race."""

    def __init__(self, port: int):
        super().__init__(logging.DEBUG)
        self.port = port
        self.router = None

    def emit(self, record: logging.LogRecord) -> None:
        if self.router is None and "waiting for a Zenoh router" in record.getMessage():
            self.router = open_router(self.port)


@pytest.mark.integration
def test_a_router_that_is_still_starting_is_no_warning(caplog):
    port = free_port()
    starter = _StartRouterWhenWaiting(port)
    logging.getLogger("common.bus").addHandler(starter)
    caplog.set_level(logging.DEBUG, logger="common.bus")
    try:
        session = open_session(f"tcp/127.0.0.1:{port}", timeout_s=20.0)
        session.close()
    finally:
        logging.getLogger("common.bus").removeHandler(starter)
        if starter.router is not None:
            starter.router.close()
    assert starter.router is not None, "open_session never said it was waiting"
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING], caplog.text


def test_a_router_that_does_not_come_is_warned_about(caplog, monkeypatch):
    monkeypatch.setattr(bus, "SLOW_CONNECT_WARN_S", 0.0)
    caplog.set_level(logging.INFO, logger="common.bus")
    with pytest.raises(ConnectionError) as err:
        open_session(f"tcp/127.0.0.1:{free_port()}", timeout_s=1.5)
    assert RUST_LOCATION not in str(err.value)
    assert any(r.levelno == logging.WARNING and "still no Zenoh router" in r.getMessage() for r in caplog.records)


# --- lbc router / lbc launch ------------------------------------------------------------------------------
@pytest.mark.integration
def test_lbc_router_port_says_where_it_listens_and_stops_on_ctrl_c():
    port = free_port()
    router = Running("router", "--port", str(port))
    try:
        assert router.wait_for(f"listening on tcp/127.0.0.1:{port}", 20.0), "".join(filter(None, router.lines))
        router.proc.send_signal(signal.SIGINT)
        rc, err = router.finish()
    finally:
        router.kill()
    assert rc == 0 and "router stopped" in err and "Traceback" not in err


@pytest.mark.integration
def test_lbc_launch_on_a_busy_port_fails_without_claiming_success(tmp_path, busy_port):
    scenario = write_scenario(tmp_path, SHORT_SCENARIO)
    r = lbc("launch", str(scenario), "--port", str(busy_port), "--dir", str(tmp_path / "dep"))
    assert r.returncode != 0
    assert "router on" not in r.stderr and "Run: lbc experiment" not in r.stderr
    assert f"port {busy_port}" in r.stderr and "already in use" in r.stderr


@pytest.mark.integration
def test_lbc_launch_says_it_is_up_only_once_every_service_is_alive(tmp_path):
    scenario = write_scenario(tmp_path, SHORT_SCENARIO)
    port = free_port()
    launch = Running("launch", str(scenario), "--port", str(port), "--dir", str(tmp_path / "dep"))
    try:
        assert launch.wait_for("router on", 90.0), "".join(filter(None, launch.lines))
        kids = children_of(launch.proc.pid)
        for service in ("localizer", "controller", "bridge", "gp_store"):
            # each logs this right after declaring itself alive (a moment's grace for that write)
            log = tmp_path / "dep" / "logs" / f"{service}.log"
            wait_until(lambda: " up for robot " in log.read_text(), 2.0, f"{service} to be up")
        session = open_session(f"tcp/127.0.0.1:{port}", timeout_s=5.0)
        watcher = AliveWatcher(session, "lbc/alive/**")
        try:   # alive already when the line was printed: the token history holds all four at once
            assert watcher.wait_for(lambda a: len(a) >= 4, 5.0), watcher.alive
            assert {k.rsplit("/", 1)[-1] for k in watcher.alive} == {"localizer", "controller", "bridge", "gp_store"}
        finally:
            watcher.close()
            session.close()
        launch.proc.send_signal(signal.SIGINT)
        rc, err = launch.finish()
    finally:
        launch.kill()
    assert rc == 0 and "Traceback" not in err
    assert len(kids) == 5 and not any(alive(k) for k in kids)


# --- Ctrl-C and failed runs ---------------------------------------------------------------------------------
def test_ctrl_c_in_lbc_bench_prints_no_traceback():
    bench = Running("bench", "gp", "--n", "3000")
    try:
        assert bench.wait_for("[bench.gp]", 60.0), "".join(filter(None, bench.lines))
        bench.proc.send_signal(signal.SIGINT)
        rc, err = bench.finish()
    finally:
        bench.kill()
    assert rc == 130 and "Traceback" not in err and "interrupted" in err, (rc, err)


def test_a_failed_connect_leaves_the_out_folder_reusable(tmp_path):
    scenario = write_scenario(tmp_path, SHORT_SCENARIO)
    out = tmp_path / "out"
    dead = f"tcp/127.0.0.1:{free_port()}"
    for _ in range(2):   # the second run must meet the same problem, not "already holds a run"
        r = lbc("experiment", "run", str(scenario), "--out", str(out), "--connect", dead, "--connect-timeout", "1")
        assert r.returncode == 1
        assert f"no Zenoh router at {dead}" in r.stderr and "already holds a run" not in r.stderr
        assert RUST_LOCATION not in r.stderr
        assert not (out / "summary.json").exists()


# --- what the console says about trials and fits ---------------------------------------------------------
def _hyper(n_used: int, n_total: int) -> HyperMsg:
    dim = HyperDim(lengthscales=[1.0] * 9, signal_std=1.0, noise_std=0.1)
    return HyperMsg(stamp_s=0.0, path_id="p", version=5, n_used=n_used, n_total=n_total, fit_s=1.0, lml=[0.0] * 3,
                    dims=[dim] * 3, model="unicycle-dt100ms")


def test_the_fit_line_names_what_each_count_counts():
    from deploy.experiment import fit_line
    line = fit_line(_hyper(825, 825), 1678, 2.0)
    assert "fitted on 825 of the 825 experiences retained of model unicycle-dt100ms" in line
    assert "1678 ingested on this route in all (experiences_total)" in line


def test_a_trial_that_did_not_complete_says_why():
    from deploy.experiment import trial_line
    m = {"max_lateral_m": 0.1, "rms_lateral_m": 0.05, "max_heading_rad": 0.1, "travel_time_s": 10.0,
         "constraint_violations": 0}
    rec = TrialRecord(trial=2, speed_mps=1.0)
    rec.end_reason = "time limit reached"
    assert "trial  2/3 NOT COMPLETED (time limit reached):" in trial_line(3, rec, m)
    rec.completed, rec.end_reason = True, "end of route"
    assert "trial  2/3 done:" in trial_line(3, rec, m)


def test_a_trial_ended_by_the_runner_keeps_what_happened_up_to_the_deciding_status():
    """The bridge runs a few more ticks until the runner's stop reaches it, as many as the wall clock
    lets: the record is cut at the status the runner decided on, so the summary does not depend on them."""
    from types import SimpleNamespace as At
    rec = TrialRecord(trial=1, speed_mps=1.0)
    rec.truth, rec.status, rec.loc = ([At(stamp_s=0.1 * k) for k in range(1, 40)] for _ in range(3))
    rec.cut_after(2.5)
    for kept in (rec.truth, rec.status, rec.loc):
        assert len(kept) == 25 and kept[-1].stamp_s == pytest.approx(2.5)


@pytest.mark.integration
def test_a_short_run_reports_why_a_trial_ended_and_what_the_counts_are(tmp_path):
    """One trial cut short by its time limit, through the real CLI: the console names the reason,
    the fit's counts and the store's total as summary.json has them, and no warning about waiting."""
    data = dict(SHORT_SCENARIO, trials={"count": 1, "speed": 0.8, "time_limit_factor": 0.05})
    scenario = write_scenario(tmp_path, data)
    out = tmp_path / "out"
    r = lbc("experiment", "run", str(scenario), "--out", str(out), timeout=180.0)
    assert r.returncode == 0, r.stderr
    assert "trial  1/1 NOT COMPLETED (time limit reached)" in r.stderr
    assert "WARNING" not in r.stderr, r.stderr
    trial = json.loads((out / "summary.json").read_text())["trials"][0]
    assert trial["completed"] is False and trial["end_reason"] == "time limit reached"
    fit = next(l for l in r.stderr.splitlines() if "hyperparameters" in l)
    assert f"{trial['experiences_total']} ingested on this route in all (experiences_total)" in fit
    assert f"of the {trial['experiences_fit_retained']} experiences retained" in fit

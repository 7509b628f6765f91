"""Ctrl-C / SIGTERM on a running experiment: every child stops, sessions close, outputs stay readable."""
from __future__ import annotations

import os
import signal
import subprocess
import sys

import pytest
from mcap.reader import make_reader

from tests.conftest import SHORT_SCENARIO, ctrl_c_reaches_child, wait_until

pytestmark = pytest.mark.integration


def children_of(pid: int) -> list[int]:
    out = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as fh:
                    fields = fh.read().rsplit(")", 1)[1].split()
                if int(fields[1]) == pid:
                    out.append(int(entry))
            except (OSError, IndexError):
                pass
    return out


def alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_interrupting_an_experiment_leaves_no_processes_and_a_readable_recording(tmp_path, scenario_file, sig):
    long_run = dict(SHORT_SCENARIO, trials={"count": 50, "speed": 0.8})
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "deploy.cli", "experiment", "run", str(scenario_file(long_run)),
                             "--out", str(out)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            preexec_fn=ctrl_c_reaches_child)
    try:
        wait_until(lambda: (out / "summary.json").exists() and '"trial": 1' in (out / "summary.json").read_text(),
                   60.0, "the first trial to finish")
        kids = children_of(proc.pid)
        assert len(kids) == 5  # router + four services
        proc.send_signal(sig)
        assert proc.wait(timeout=30) == 130
    finally:
        if proc.poll() is None:
            proc.kill()
    wait_until(lambda: not any(alive(k) for k in kids), 10.0, "all children to exit")
    for service in ("bridge", "localizer", "controller"):
        assert f"{service} stopped" in (out / "logs" / f"{service}.log").read_text()
    assert "router stopped" in (out / "logs" / "router.log").read_text()
    with open(out / "run.mcap", "rb") as fh:
        assert make_reader(fh).get_summary().statistics.message_count > 100

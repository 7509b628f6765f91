"""Two hosts for real (issue 19): a robot host and a learning host, each a network namespace with its
own stack, joined by a veth pair. Each runs `lbc launch --manifest FILE --host NAME` (its router with
mutual TLS and access control, its services); the experiment runs on the robot host with the
operator's certificate. Needs root (ip netns); skipped with the reason otherwise."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path

import pytest

from bench.deployment import kill_router
from deploy.certs import make_certs
from deploy.manifest import load_manifest
from deploy.netns import NetnsUnavailable, TwoHosts
from tests.conftest import SHORT_SCENARIO, dump_toml_dict, wait_until
from tests.test_cli import ROOT, Running

pytestmark = [pytest.mark.integration, pytest.mark.slow]

SCENARIO = dict(SHORT_SCENARIO, name="twohost", controller={"algorithm": "lb-nmpc"},
                scheduler={"enabled": True})
DELAY_MS = 50.0     # one way between the routers, through deploy.delay_proxy on the learning host


def write_deployment(net: TwoHosts, base: Path, scenario: dict, reach_port: int | None = None,
                     port: int = 7447) -> Path:
    (base / "scenario.toml").write_text(dump_toml_dict(scenario))
    manifest = base / "deployment.toml"
    reach = f'reach = "tls/{net.addr["learning"]}:{reach_port}"' if reach_port else ""
    manifest.write_text(f'''name = "twohost"
scenario = "scenario.toml"
[hosts.robot]
listen = "tls/{net.addr['robot']}:{port}"
services = ["bridge", "localizer", "controller"]
links = ["learning"]
[hosts.learning]
listen = "tls/{net.addr['learning']}:{port}"
services = ["gp_store", "scheduler"]
{reach}
''')
    make_certs(load_manifest(manifest))
    return manifest


@pytest.fixture(scope="module")
def net():
    try:
        with TwoHosts() as hosts:
            yield hosts
    except NetnsUnavailable as exc:
        pytest.skip(str(exc))


@contextmanager
def deployed(net: TwoHosts, base: Path, scenario: dict, delay_ms: float = 0.0, port: int = 7447,
             hosts: tuple[str, ...] = ("learning", "robot")):
    """`lbc launch --manifest ... --host` on each of `hosts`, until the block ends (Ctrl-C to each); with
    a delay, the robot's router reaches the learning host's through the delay proxy."""
    manifest = write_deployment(net, base, scenario, 7448 if delay_ms else None, port)
    launches = {}
    proxy = None
    try:
        if delay_ms:
            a = net.addr["learning"]
            proxy = subprocess.Popen([*net.prefix("learning"), sys.executable, "-m", "deploy.delay_proxy",
                                      "--listen", f"{a}:7448", "--to", f"{a}:7447", "--delay-ms", str(delay_ms)],
                                     cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        for host in hosts:
            launches[host] = Running("launch", "--manifest", str(manifest), "--host", host,
                                     "--dir", str(base / host), prefix=net.prefix(host))
        for host, launch in launches.items():
            assert launch.wait_for("router on", 120.0), "".join(filter(None, launch.lines))
        yield manifest
    finally:
        for launch in launches.values():
            if launch.proc.poll() is None:
                launch.proc.send_signal(signal.SIGINT)
        for launch in launches.values():
            try:
                launch.finish(30.0)
            except subprocess.TimeoutExpired:
                launch.kill()
        if proxy is not None:
            proxy.terminate()
            proxy.wait(10)


@pytest.fixture(scope="module")
def two_hosts(net, tmp_path_factory):
    base = tmp_path_factory.mktemp("twohost")
    with deployed(net, base, SCENARIO, DELAY_MS) as manifest:
        yield net, manifest, base


def run_in(net: TwoHosts, host: str, *args: str, timeout: float = 600.0) -> subprocess.CompletedProcess:
    return subprocess.run([*net.prefix(host), sys.executable, *args], cwd=ROOT, capture_output=True, text=True,
                          timeout=timeout, env=dict(os.environ, PYTHONPATH=str(ROOT)))


def test_an_experiment_runs_with_store_and_scheduler_on_the_learning_host(two_hosts, tmp_path):
    net, manifest, base = two_hosts
    out = tmp_path / "out"
    r = run_in(net, "robot", "-m", "deploy.cli", "experiment", "run", str(base / "scenario.toml"), "--out", str(out),
               "--manifest", str(manifest), "--host", "robot")
    assert r.returncode == 0, r.stderr[-3000:]
    summary = json.loads((out / "summary.json").read_text())
    assert [t["completed"] for t in summary["trials"]] == [True, True]
    assert all(t["constraint_violations"] == 0 for t in summary["trials"])
    # the store on the learning host fitted on the experiences, the scheduler there planned trial 2
    assert summary["trials"][1]["experiences_fit_used"] > 0 and summary["trials"][1]["schedule_version"] >= 2
    # the learning host's store file holds them
    assert (base / "learning" / "data" / "experiences.db").stat().st_size > 0
    # and the store's answers did cross the delayed link: a query's round trip takes two delays
    probe = ("import sys, time; from common.bus import open_session, query; from common import keys; "
             "from deploy import access; from deploy.manifest import load_manifest; "
             "m = load_manifest(sys.argv[1]); s = open_session(m.host('robot').listen, timeout_s=10, "
             "zenoh_conf=access.session_config(m, 'robot', 'operator')); t = time.monotonic(); "
             "n = len(query(s, keys.store_stats(), timeout_s=5)); print(n, (time.monotonic() - t) * 1e3)")
    r = run_in(net, "robot", "-c", probe, str(manifest), timeout=60.0)
    replies, rtt_ms = r.stdout.split()
    assert int(replies) == 1 and float(rtt_ms) >= 2 * DELAY_MS, r.stdout + r.stderr


def test_sessions_are_entitled_only_by_their_certificate(two_hosts):
    """From each host: no certificate is refused; a valid certificate of the wrong role delivers no
    commands, experiences, acknowledgements, corridor updates or schedules, and gets no answer to a
    control request; the right certificate does (so the observer is not blind)."""
    net, manifest, _ = two_hosts
    for host in ("robot", "learning"):
        r = run_in(net, host, "-m", "deploy.cli", "deploy", "check", "--manifest", str(manifest), "--host", host,
                   timeout=180.0)
        assert r.returncode == 0 and "access control holds" in r.stderr, r.stderr[-3000:]
        result = json.loads(r.stdout.strip().splitlines()[-1])
        assert result["unauthenticated_connect_refused"] is True
        assert result["rogue_puts_delivered"] == 0, result
        assert result["rogue_control_replies"] == 0, result
        assert result["entitled_puts_delivered"] > 0 and result["operator_control_replies"] > 0, result


def test_a_killed_router_on_either_host_is_restarted_and_rejoined(two_hosts):
    """SIGKILL each host's router in turn: its launcher restarts it, the services and the link between
    the routers come back by themselves (the store answers the robot host, the robot's services are alive)."""
    net, manifest, base = two_hosts
    for host in ("learning", "robot"):
        kill_router(base, host)
        r = run_in(net, "robot", "-m", "bench.deployment", "--probe", "robot-back", "--manifest", str(manifest),
                   timeout=120.0)
        assert r.returncode == 0, r.stderr[-3000:]
        back_s = json.loads(r.stdout.strip().splitlines()[-1])["back_after_s"]
        assert back_s < 10.0, (host, back_s)
    # and what runs there is still entitled as before
    r = run_in(net, "robot", "-m", "deploy.cli", "deploy", "check", "--manifest", str(manifest), "--host", "robot",
               timeout=180.0)
    assert r.returncode == 0 and json.loads(r.stdout.strip().splitlines()[-1])["rogue_puts_delivered"] == 0


REALTIME = dict(SCENARIO, name="linkdown", sim={"clock": "realtime"}, scheduler={"enabled": False},
                path={"waypoints": [[0, 0], [12, 0], [20, 4]], "teach_speed_mps": 1.0},
                trials={"count": 2, "speed": 0.8})
LINK_DOWN_S = 20.0


def test_the_link_to_the_learning_host_drops_for_20_s_mid_trial(net, tmp_path):
    """Realtime clock: the link goes down for 20 s once trial 2 is under way. The controller keeps its
    period on the route's snapshot (learning stays on), its experiences queue and are all acknowledged
    after the link returns, the runner carries on; nothing is restarted by hand."""
    # its own ports: the module's deployment is still up on 7447
    with deployed(net, tmp_path, REALTIME, port=7457) as manifest:
        controller_log = tmp_path / "robot" / "logs" / "controller.log"
        run = Running("experiment", "run", str(tmp_path / "scenario.toml"), "--out", str(tmp_path / "out"),
                      "--manifest", str(manifest), "--host", "robot", prefix=net.prefix("robot"))
        try:
            wait_until(lambda: "trial 2: store snapshot" in controller_log.read_text(), 300.0,
                       "trial 2 to be prepared")
            net.link(False)
            try:
                time.sleep(LINK_DOWN_S)     # the outage itself
            finally:
                net.link(True)
            rc, err = run.finish(300.0)
        finally:
            run.kill()
            net.link(True)
    assert rc == 0, err[-3000:]
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    trials = summary["trials"]
    assert [t["completed"] for t in trials] == [True, True], err[-3000:]
    second = trials[1]
    assert second["learning_off_since_s"] is None and second["learning_off_s"] == 0.0
    # every experience the controller produced was stored: the store's count of ingested experiences on
    # the route equals what the runner saw published, the teach pass's and trial by trial
    teach = summary["teach_learning"]["experiences_trial"]
    assert teach > 0 and second["experiences_total"] == teach + sum(t["experiences_trial"] for t in trials)
    assert second["deadline_misses"] == 0 and second["period_jitter_ms_p99"] < 50.0


def test_the_robot_host_alone_teaches_and_repeats_and_learns_once_the_learning_host_is_up(net, tmp_path):
    """The learning host is down when the experiment starts: the robot host teaches and runs trial 1 on
    its nominal model at the scenario's speed (no scheduler), its experiences queued; the learning host
    comes up after trial 1: every queued experience is stored and fitted on, nothing restarted by hand."""
    scenario = dict(REALTIME, name="alone", scheduler={"enabled": True}, trials={"count": 3, "speed": 0.8})
    with deployed(net, tmp_path, scenario, port=7467, hosts=("robot",)) as manifest:
        run = Running("experiment", "run", str(tmp_path / "scenario.toml"), "--out", str(tmp_path / "out"),
                      "--manifest", str(manifest), "--host", "robot", "--ready-timeout", "10",
                      prefix=net.prefix("robot"))
        learning = None
        try:
            assert run.wait_for("trial  1/3 done", 300.0), "".join(filter(None, run.lines))
            learning = Running("launch", "--manifest", str(manifest), "--host", "learning", "--dir",
                               str(tmp_path / "learning"), prefix=net.prefix("learning"))
            rc, err = run.finish(600.0)
        finally:
            run.kill()
            if learning is not None:
                learning.proc.send_signal(signal.SIGINT)
                learning.finish(30.0)
    assert rc == 0, err[-3000:]
    assert "not reachable (learning host down?)" in err and "no store reachable after trial 1" in err, err[-3000:]
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    trials = summary["trials"]
    assert [t["completed"] for t in trials] == [True, True, True], err[-3000:]
    assert "schedule_version" not in trials[0] and trials[0]["experiences_fit_used"] is None
    # nothing stored or fitted after the teach pass, the store being down
    assert summary["teach_learning"]["experiences_stored"] == 0 and summary["teach_learning"]["hyper_version"] is None
    # by the end the store has every experience of every trial, the teach pass's and trial 1's queued
    # ones included, once
    last = trials[-1]
    teach = summary["teach_learning"]["experiences_trial"]
    assert teach > 0 and last["experiences_total"] == teach + sum(t["experiences_trial"] for t in trials), err[-3000:]
    assert last["experiences_fit_used"] > 0

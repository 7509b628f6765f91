"""`lbc bench deployment`: a secured two-host deployment under faults, measured.

Two network namespaces joined by a veth pair (root needed): the robot host runs bridge, localizer and
controller, the learning host the store and the scheduler; each is started by `lbc launch --manifest
--host` with mutual TLS and access control, and the robot's router reaches the learning host's through
a delay proxy (`--delay-ms` one way). Then, in order:
1. the store query round trip from the robot host, halved: `one_way_latency_ms`;
2. a realtime experiment: the robot host's router is killed `--robot-router-kill-after-s` into trial 1
   (its launcher restarts it; `router_restart_recover_s_robot` until the robot's services and the store
   are reachable again, `trial_1_end_reason` what became of the trial), and the link is pulled for
   `--link-down-s` once trial 2 is under way: `deadline_misses` (all trials), `period_jitter_ms_p99`
   (worst trial), `experiences_produced` (what the runner saw published) and `experiences_acked` (what
   the store ingested);
3. the learning host's router killed: `router_restart_recover_s_learning`, until the store answers the
   robot host again (`router_restart_recover_s`: the slower of the two);
4. `lbc deploy check` from the robot host during trial 1 and from the learning host during trial 2
   (rogue sessions mid-trial): `rogue_puts_delivered` (puts and control requests that got through to
   certificates not entitled to them) and `unauthenticated_connect_refused`.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench.report import run_and_print
from common import keys
from common.bus import open_session, query, setup_logging
from common.scenario import parse_scenario
from deploy import access
from deploy.certs import OPERATOR, make_certs
from deploy.experiment import ROBOT_SERVICES
from deploy.manifest import load_manifest
from deploy.netns import NetnsUnavailable, TwoHosts

log = logging.getLogger("bench.deployment")
ROOT = Path(__file__).resolve().parents[1]
SCENARIO = {"name": "benchdep", "seed": 3, "robot": {"preset": "husky", "name": "r1"},
            "path": {"waypoints": [[0, 0], [12, 0], [20, 4]], "teach_speed_mps": 1.0},
            "localization": {"source": "pose", "noise_m": 0.005, "delay_s": 0.1},
            "controller": {"algorithm": "lb-nmpc"}, "scheduler": {"enabled": True},
            "sim": {"clock": "realtime"}, "trials": {"count": 2, "speed": 0.8}}


def _wait_text(path: Path, text: str, timeout_s: float, proc: subprocess.Popen | None = None) -> None:
    deadline = time.monotonic() + timeout_s
    while not (path.exists() and text in path.read_text(errors="replace")):
        if proc is not None and proc.poll() is not None:
            raise RuntimeError(f"{proc.args} exited ({proc.returncode}): {path.read_text()[-2000:]}")
        if time.monotonic() > deadline:
            raise TimeoutError(f"no {text!r} in {path} within {timeout_s:.0f} s")
        time.sleep(0.1)     # a child's log file is the only signal it gives


def _spawn(net: TwoHosts, host: str, args: list[str], log_path: Path) -> subprocess.Popen:
    with open(log_path, "ab") as fh:
        return subprocess.Popen([*net.prefix(host), sys.executable, *args], cwd=ROOT, stdout=fh,
                                stderr=subprocess.STDOUT, env=dict(os.environ, PYTHONPATH=str(ROOT)))


def _probe(net: TwoHosts, manifest: Path, what: str) -> dict:
    r = subprocess.run([*net.prefix("robot"), sys.executable, "-m", "bench.deployment", "--probe", what,
                        "--manifest", str(manifest)], cwd=ROOT, capture_output=True, text=True, timeout=120,
                       env=dict(os.environ, PYTHONPATH=str(ROOT)))
    if r.returncode != 0:
        raise RuntimeError(f"probe {what} failed: {r.stderr[-2000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def run_probe(what: str, manifest_path: str) -> int:
    """Inside the robot host: store round trips, or the time until the store answers again."""
    m = load_manifest(manifest_path)
    t0 = time.monotonic()
    s = open_session(m.host("robot").listen, timeout_s=30.0, zenoh_conf=access.session_config(m, "robot", OPERATOR))
    try:
        if what == "rtt":
            rtts = []
            for _ in range(21):
                t = time.monotonic()
                if query(s, keys.store_stats(), timeout_s=5.0):
                    rtts.append((time.monotonic() - t) * 1e3)
            out = {"rtt_ms_p50": statistics.median(rtts) if rtts else None, "n": len(rtts)}
        else:
            # the store answers the robot host again; after the robot's router: its services are back too
            robot = ROBOT_SERVICES if what == "robot-back" else ()
            while not (query(s, keys.store_stats(), timeout_s=1.0) and all(
                    any(r.ok is not None for r in s.liveliness().get(keys.alive("r1", name), timeout=1.0))
                    for name in robot)):
                if time.monotonic() - t0 > 60.0:
                    raise TimeoutError("the deployment did not come back within 60 s")
            out = {"back_after_s": time.monotonic() - t0}
    finally:
        s.close()
    print(json.dumps(out))
    return 0


def _deploy_check(net: TwoHosts, manifest: Path, host: str) -> dict:
    """`lbc deploy check` from a host: every certificate there against what it is not entitled to."""
    r = subprocess.run([*net.prefix(host), sys.executable, "-m", "deploy.cli", "deploy", "check", "--manifest",
                        str(manifest), "--host", host], cwd=ROOT, capture_output=True, text=True, timeout=300,
                       env=dict(os.environ, PYTHONPATH=str(ROOT)))
    if r.returncode not in (0, 1) or not r.stdout.strip():
        raise RuntimeError(f"deploy check on {host} failed: {r.stderr[-2000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def kill_router(base: Path, host: str) -> None:
    """SIGKILL a host's router (its launcher restarts it)."""
    pids = subprocess.run(["pgrep", "-f", str(base / host / "zenoh" / "router.json5")], capture_output=True,
                          text=True).stdout.split()
    if not pids:
        raise RuntimeError(f"no router process of host {host}")
    for pid in pids:
        os.kill(int(pid), signal.SIGKILL)


def _write(base: Path, net: TwoHosts) -> Path:
    parse_scenario(SCENARIO)        # fail here, not in a child, if the scenario is wrong
    (base / "scenario.toml").write_text(_toml(SCENARIO))
    manifest = base / "deployment.toml"
    la, ra = net.addr["learning"], net.addr["robot"]
    manifest.write_text(f'name = "benchdep"\nscenario = "scenario.toml"\n'
                        f'[hosts.robot]\nlisten = "tls/{ra}:7447"\nservices = ["bridge", "localizer", "controller"]\n'
                        f'links = ["learning"]\n[hosts.learning]\nlisten = "tls/{la}:7447"\n'
                        f'services = ["gp_store", "scheduler"]\nreach = "tls/{la}:7448"\n')
    make_certs(load_manifest(manifest))
    return manifest


def _toml(data: dict) -> str:
    from common.config import _dump_table
    return _dump_table(data, [])


def run_bench(args) -> dict:
    base = Path(tempfile.mkdtemp(prefix="lbc-bench-deployment-"))
    procs: list[subprocess.Popen] = []
    try:
        with TwoHosts() as net:
            manifest = _write(base, net)
            la = net.addr["learning"]
            procs.append(_spawn(net, "learning", ["-m", "deploy.delay_proxy", "--listen", f"{la}:7448", "--to",
                                                  f"{la}:7447", "--delay-ms", str(args.delay_ms)], base / "proxy.log"))
            for host in ("learning", "robot"):
                procs.append(_spawn(net, host, ["-m", "deploy.cli", "launch", "--manifest", str(manifest), "--host",
                                                 host, "--dir", str(base / host)], base / f"launch-{host}.log"))
            for host, proc in zip(("learning", "robot"), procs[1:]):
                _wait_text(base / f"launch-{host}.log", "router on", 120.0, proc)
            log.info("two hosts up (%s); measuring the store round trip", base)
            rtt = _probe(net, manifest, "rtt")["rtt_ms_p50"]
            log.info("store query round trip %.1f ms; realtime experiment with the link down %.0f s in trial 2",
                     rtt, args.link_down_s)
            exp = _spawn(net, "robot", ["-m", "deploy.cli", "experiment", "run", str(base / "scenario.toml"), "--out",
                                        str(base / "out"), "--manifest", str(manifest), "--host", "robot"],
                         base / "experiment.log")
            procs.append(exp)
            _wait_text(base / "robot" / "logs" / "controller.log", "prepare/repeat trial 1: ok", 600.0, exp)
            time.sleep(args.robot_router_kill_after_s)      # into trial 1, the robot moving
            log.info("killing the robot host's router in trial 1")
            kill_router(base, "robot")
            robot_recover = _probe(net, manifest, "robot-back")["back_after_s"]
            # rogue sessions from the robot host while trial 1 goes on: they must change nothing
            checks = [_deploy_check(net, manifest, "robot")]
            _wait_text(base / "robot" / "logs" / "controller.log", "trial 2: store snapshot", 600.0, exp)
            net.link(False)
            time.sleep(args.link_down_s)       # the outage itself
            net.link(True)
            checks.append(_deploy_check(net, manifest, "learning"))      # ... and from the learning host
            if exp.wait(timeout=600) != 0:
                raise RuntimeError(f"the experiment failed: {(base / 'experiment.log').read_text()[-3000:]}")
            summary = json.loads((base / "out" / "summary.json").read_text())
            trials = summary["trials"]
            teach_produced = summary.get("teach_learning", {}).get("experiences_trial", 0)
            log.info("killing the learning host's router")
            kill_router(base, "learning")
            recover = _probe(net, manifest, "back")["back_after_s"]
    finally:
        for p in reversed(procs):
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for p in procs:
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()
    return {"one_way_latency_ms": rtt / 2 if rtt is not None else None,
            "deadline_misses": sum(t.get("deadline_misses", 0) for t in trials),
            "period_jitter_ms_p99": max(t.get("period_jitter_ms_p99", 0.0) for t in trials),
            "link_down_s": args.link_down_s,
            "experiences_produced": teach_produced + sum(t["experiences_trial"] for t in trials),
            "experiences_acked": trials[-1]["experiences_total"],
            "router_restart_recover_s": max(recover, robot_recover),
            "router_restart_recover_s_learning": recover, "router_restart_recover_s_robot": robot_recover,
            "trial_1_end_reason": trials[0].get("end_reason", ""),
            "rogue_puts_delivered": sum(c["rogue_puts_delivered"] + c["rogue_control_replies"] for c in checks),
            "unauthenticated_connect_refused": all(c["unauthenticated_connect_refused"] for c in checks),
            "trials_completed": sum(bool(t["completed"]) for t in trials), "trials": len(trials),
            "delay_ms": args.delay_ms, "work_dir": str(base)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="lbc bench deployment", description=__doc__.splitlines()[0])
    parser.add_argument("--delay-ms", type=float, default=50.0, help="one-way delay between the routers")
    parser.add_argument("--robot-router-kill-after-s", type=float, default=8.0,
                        help="how far into trial 1 the robot host's router is killed")
    parser.add_argument("--link-down-s", type=float, default=20.0, help="how long the link is pulled in trial 2")
    parser.add_argument("--log-level", default="INFO")
    parser.add_argument("--probe", choices=("rtt", "back", "robot-back"), help=argparse.SUPPRESS)
    parser.add_argument("--manifest", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    setup_logging("bench", args.log_level)
    if args.probe:
        return run_probe(args.probe, args.manifest)
    return run_and_print(lambda: run_bench(args), failures=(NetnsUnavailable,))


if __name__ == "__main__":
    raise SystemExit(main())

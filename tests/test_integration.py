"""End to end through a real local Zenoh router and real service processes."""
from __future__ import annotations

import json
import os
import queue
import signal
import threading
from pathlib import Path

import msgpack
import numpy as np
import pytest
import zenoh
from mcap.reader import make_reader

from common import keys
from common.bus import query
from common.codec import decode, encode
from common.messages import BridgeStatus, ControlRequest, StoreStats, TruthPose, VelocityCommand
from deploy.experiment import run_experiment
from deploy.robot_logs import load_ros2_mcap, residuals
from tests.conftest import SHORT_SCENARIO, Deployment, wait_until
from tests.ros2_topics import check_standard_topics, layout_topics

pytestmark = pytest.mark.integration
ROOT = Path(__file__).resolve().parents[1]

SUMMARY_KEYS = {"trial", "completed", "max_lateral_m", "rms_lateral_m", "max_heading_rad", "rms_heading_rad",
                "travel_time_s", "mean_speed_mps", "constraint_violations", "mean_matched_features",
                "solve_ms_p50", "solve_ms_p99", "experiences_total"}


def test_experiment_with_two_trials_writes_its_outputs(tmp_path, scenario_file):
    out = tmp_path / "out"
    summary = run_experiment(scenario_file(), out, progress_stream=open(os.devnull, "w"))
    on_disk = json.loads((out / "summary.json").read_text())
    assert on_disk == json.loads(json.dumps(summary))
    assert on_disk["scenario"] == "itest" and on_disk["algorithm"] == "fl"
    assert [t["trial"] for t in on_disk["trials"]] == [1, 2]
    for t in on_disk["trials"]:
        assert SUMMARY_KEYS <= set(t)
        assert t["completed"] is True
        assert 0.0 < t["max_lateral_m"] < 0.1 and 0.0 < t["rms_lateral_m"] <= t["max_lateral_m"]
        assert t["travel_time_s"] > 0 and 0.5 < t["mean_speed_mps"] <= 0.85
        assert t["constraint_violations"] == 0 and t["mean_matched_features"] is None
        assert t["solve_ms_p99"] >= t["solve_ms_p50"] > 0
        # a route the robot turns along at the asked speed with room to spare: no cap from its turn
        assert t["turn_capped_steps"] == 0 and t["turn_cap_min_mps"] is None and t["turn_loss_per_mps2"] >= 0.0
    model = on_disk["identified_model"]           # the controller's nominal model, from the teach pass
    assert model["path_id"] == "itest" and model["model_tag"].startswith("unicycle-dt100ms-")
    assert 0.05 < model["actuator_tau_s"][1] < 0.3 and len(model["prior_std_base"]) == 3
    assert "itest" in (out / "report.html").read_text()
    # the recording is a finished, indexed MCAP holding every kind of bus message
    with open(out / "run.mcap", "rb") as fh:
        reader = make_reader(fh)
        stats = reader.get_summary().statistics
        topics = {c.topic for c in reader.get_summary().channels.values()}
        assert stats.message_count > 1000
        for key in (keys.truth("r1"), keys.cmd_vel("r1"), keys.loc_state("r1"), keys.ctrl_status("r1"),
                    keys.odom("r1"), keys.clock("r1"), keys.trial_event("r1"), keys.control("r1", "bridge"),
                    keys.ctrl_model("r1", "itest")):
            assert key in topics, key
        for _schema, channel, message in reader.iter_messages(topics=[keys.truth("r1")]):
            assert decode(TruthPose, message.data).trial in (0, 1, 2)
            break
    # and the standard ROS 2 topics, which an independent ROS 2 decoder reads
    topics = check_standard_topics(out / "run.mcap", "r1")
    assert "/controller/horizon" not in topics      # FL predicts nothing
    odom = topics["/odom"][-1]
    assert odom.header.frame_id == "odom" and odom.child_frame_id == "r1/base_link"
    # the tracker's errors as JSON with its schema; the Foxglove layout shows only what a run has
    with open(out / "run.mcap", "rb") as fh:
        reader = make_reader(fh)
        channels = {c.topic: c for c in reader.get_summary().channels.values()}
        tracking = [json.loads(m.data) for _, _, m in reader.iter_messages(topics=["/controller/tracking"])]
    assert channels["/controller/tracking"].message_encoding == "json"
    assert tracking and max(abs(t["lateral_m"]) for t in tracking) < 0.2 and {"heading_deg", "v_cmd_mps"} <= set(tracking[-1])
    # a run's MCAP is a ROS 2 log `lbc model fit-logs --format ros2-mcap` reads (wheel odometry and commands)
    drive = load_ros2_mcap(out / "run.mcap")
    a, g = residuals(drive)
    assert drive.travel_m > 15.0 and len(a) > 100 and np.isfinite(a).all() and np.isfinite(g).all()
    assert 0.5 < np.nanmedian(drive.y[drive.u[:, 0] > 0.5, 0]) / 0.8 < 1.2    # measured speed ~ commanded
    shown = layout_topics(ROOT / "deploy" / "foxglove" / "lbc-run.json")
    assert shown - set(channels) <= {"/controller/horizon", "/stereo/left/image_raw"}, shown - set(channels)


def test_killing_the_controller_mid_trial_stops_the_robot_within_half_a_second(deployment):
    dep = deployment
    dep.exp.teach()
    cmds: queue.Queue = queue.Queue()
    sub = dep.session.declare_subscriber(keys.cmd_vel("r1"), lambda s: cmds.put(decode(VelocityCommand, s.payload.to_bytes())))
    statuses: queue.Queue = queue.Queue()
    sub2 = dep.session.declare_subscriber(keys.bridge_status("r1"), lambda s: statuses.put(decode(BridgeStatus, s.payload.to_bytes())))
    try:
        for s in ("localizer", "controller", "bridge"):
            dep.exp.control(s, "prepare", "repeat", 1, 0.8, 120.0)
        dep.exp.control("bridge", "start", "repeat", 1)
        # drive until the robot is well under way
        t_start, v = None, 0.0
        while True:
            kind, msg = dep.exp._next_event(5.0)
            assert kind is not None, "no bus traffic"
            if kind == "truth" and msg.trial == 1:
                t_start = msg.stamp_s if t_start is None else t_start
                v = msg.v_mps
                if msg.stamp_s - t_start > 3.0:
                    break
        assert v > 0.6
        dep.launcher.kill("controller", signal.SIGKILL)
        # after the kill: follow truth until the robot is at rest
        stopped_at = None
        while stopped_at is None:
            kind, msg = dep.exp._next_event(5.0)
            assert kind is not None, "bridge stopped publishing"
            if kind == "truth" and msg.trial == 1 and abs(msg.v_mps) < 0.01 and msg.stamp_s > t_start + 3.0:
                stopped_at = msg.stamp_s
        last_cmd = None
        while not cmds.empty():
            last_cmd = cmds.get()
        assert last_cmd is not None
        assert stopped_at - last_cmd.stamp_s <= 0.5 + 1e-6, (stopped_at, last_cmd.stamp_s)
        seen_trip = False
        while not statuses.empty():
            seen_trip |= statuses.get().watchdog_tripped
        assert seen_trip
    finally:
        sub.undeclare()
        sub2.undeclare()


def test_a_paused_controller_is_stepped_past_after_the_lockstep_timeout_and_the_trial_counts_it(tmp_path):
    """A controller that stops answering while alive (here: SIGSTOP, as a machine too loaded to answer in
    time) is stepped past after `lockstep_timeout_s`, and the trial says how many ticks were: that run
    depended on the wall clock."""
    scenario = dict(SHORT_SCENARIO, sim={"lockstep_timeout_s": 0.3})
    dep = Deployment(tmp_path, scenario)
    truths: queue.Queue = queue.Queue()
    sub = dep.session.declare_subscriber(keys.truth("r1"), lambda s: truths.put(decode(TruthPose, s.payload.to_bytes())))

    def pause_once_under_way():
        while (t := truths.get(timeout=60.0)).trial != 1 or t.v_mps < 0.3:
            pass
        dep.launcher.kill("controller", signal.SIGSTOP)
        try:   # the bridge steps on without the answers: three more ticks
            for _ in range(3):
                truths.get(timeout=30.0)
        finally:
            dep.launcher.kill("controller", signal.SIGCONT)

    try:
        dep.exp.teach()
        pauser = threading.Thread(target=pause_once_under_way)
        pauser.start()
        rec = dep.exp.repeat(1, 0.8)
        pauser.join()
        assert rec.unanswered_ticks >= 3, rec.unanswered_ticks
        assert "not answered within 0.3 s" in dep.log("bridge")
        # the trial's count is logged just after its end event is out
        wait_until(lambda: "ticks stepped without their answer" in dep.log("bridge"), 10, "the bridge's count")
    finally:
        sub.undeclare()
        dep.close()


GARBAGE = [b"\xc1\xc1\xc1", b"", msgpack.packb([1, 2, 3]), msgpack.packb({"v": 1, "stamp_s": float("nan")}),
           b"\x00" * 70_000]


def test_malformed_messages_are_rejected_and_logged_while_services_keep_running(deployment):
    dep = deployment
    r = "r1"
    inputs = {  # input key -> services that subscribe to it
        keys.cmd_vel(r): ["bridge"], keys.loc_state(r): ["bridge", "controller"],
        keys.truth(r): ["localizer"], keys.clock(r): ["controller"],
    }
    block = zenoh.CongestionControl.BLOCK   # the garbage itself must arrive
    for key in inputs:
        for payload in GARBAGE:
            dep.session.put(key, payload, congestion_control=block)
        # a well-formed message of the wrong type is malformed too
        dep.session.put(key, encode(ControlRequest(stamp_s=0.0, action="ping", mode="idle", trial=0, path_id="x",
                                                   speed_mps=0.0, max_duration_s=0.0, learning=False, loop=False)),
                        congestion_control=block)
    for key, services in inputs.items():
        for svc in services:
            wait_until(lambda: f"rejected message on {key}" in dep.log(svc), 10.0, f"{svc} to reject {key}")
    # control queryables answer garbage with an error instead of dying
    for svc in ("bridge", "localizer", "controller"):
        replies = list(dep.session.get(keys.control(r, svc), payload=b"\x93\x01\x02", timeout=5.0))
        assert replies and replies[0].err is not None
        assert b"rejected" in replies[0].err.payload.to_bytes()
    replies = list(dep.session.get(keys.route("no_such_route"), timeout=5.0))
    assert replies and replies[0].err is not None
    # everyone is still alive and still works: teach and a full trial
    assert {"bridge", "localizer", "controller"} <= dep.exp.alive
    assert all(c.proc.poll() is None for c in dep.launcher.children)
    dep.exp.teach()
    rec = dep.exp.repeat(1, 0.8)
    assert rec.completed
    assert max(s.rejected_msgs for s in rec.status) >= len(GARBAGE)


def test_realtime_clock_runs_at_wall_clock_pace(tmp_path, scenario_file):
    data = dict(SHORT_SCENARIO, name="rt", path={"waypoints": [[0, 0], [3, 0]], "teach_speed_mps": 0.8},
                trials={"count": 1, "speed": 0.8}, sim={"clock": "realtime"})
    out = tmp_path / "rt"
    summary = run_experiment(scenario_file(data), out, progress_stream=open(os.devnull, "w"))
    t = summary["trials"][0]
    assert t["completed"] and t["max_lateral_m"] < 0.05
    # realtime: a trial takes about as long on the wall clock as in robot time
    assert 0.7 * t["travel_time_s"] <= t["wall_time_s"] <= 1.5 * t["travel_time_s"] + 1.0


def test_store_cli_stats_query_fit_export_import(deployment, tmp_path, capsys):
    from deploy.cli import main as lbc
    dep = deployment
    dep.exp.teach()
    dep.exp.repeat(1, 0.8)
    learned = dep.exp.learn(1)
    hyper, ingested = learned.hyper, learned.ingested
    assert hyper is not None and hyper.version == 1 and ingested > 50
    capsys.readouterr()
    ep = ["--connect", dep.endpoint]
    assert lbc(["store", "stats", *ep]) == 0
    out = capsys.readouterr().out
    assert "itest" in out and str(ingested) in out and "v1" in out
    assert lbc(["store", "query", "--path", "itest", "--vertex", "10", "--speed", "0.8", *ep]) == 0
    out = capsys.readouterr().out
    assert "experiences in vertices 5..15" in out and "g.dy_body_m" in out
    assert lbc(["store", "fit", "--path", "itest", *ep]) == 0
    assert "hyperparameters v2" in capsys.readouterr().out
    f = tmp_path / "exp.mcap"
    assert lbc(["store", "export", "--path", "itest", "--out", str(f), *ep]) == 0
    n = int(capsys.readouterr().out.split()[1])
    stats = [decode(StoreStats, r.payload) for r in query(dep.session, keys.store_stats())]
    assert n == sum(p.retained for s in stats for p in s.paths if p.path_id == "itest") > 0
    # importing what the store already holds stores nothing twice
    assert lbc(["store", "import", str(f), *ep]) == 0
    assert f"imported {n} experiences (0 rejected)" in capsys.readouterr().out
    assert dep.exp.ingested() == ingested
    assert lbc(["store", "fit", "--path", "nope", *ep]) == 1

"""The speed scheduler as a real process: it collects a robot's per-vertex passes from the bus, proposes
the next schedule after the trial (eq. 4.2-4.5, and with its guard), keeps it across a SIGKILL, answers
the same update again with the same schedule, and answers bad requests with a reason."""
from __future__ import annotations

import json
import signal
import threading
from dataclasses import replace

import numpy as np
import pytest

from common import keys
from common.bus import Node, query_one
from common.codec import encode
from common.config import dump_toml
from common.messages import ControllerStatus, ScheduleUpdate, SpeedSchedule, TrialEvent
from common.path import Path
from deploy.launcher import Launcher
from deploy.router import free_port
from services.localizer.config import LocalizerConfig
from services.localizer.routes import RouteStore
from services.scheduler.config import SchedulerConfig
from services.scheduler.core import DECREASE, INCREASE, SchedulerParams

pytestmark = pytest.mark.integration
N = 201                      # vertices 0.25 m apart: a 50 m straight route
ROUTE = "straight"
# the thesis rule alone (eq. 4.2-4.5 worked by hand below); the guard has its own test
PARAMS = SchedulerParams(v_init=0.5, v_max=2.0, gamma1=0.2, gamma2=0.24, a_max=0.2, a_min=-0.05,
                         v_start=0.4, start_m=5.0, v_end=0.4, end_m=5.0, guard=False)


def status(trial: int, i: int, state: str, lateral_m: float, w: float = 0.1, v: float = 0.5) -> ControllerStatus:
    return ControllerStatus(
        stamp_s=float(i), tick=i, trial=trial, algorithm="fl", state=state, reason="", path_id=ROUTE, vertex=i,
        distance_m=0.25 * i, lateral_m=float(lateral_m), heading_rad=0.01, v_cmd_mps=v, w_cmd_radps=w,
        solve_ms=0.1, iterations=0, loc_age_s=0.0, rejected_msgs=0, experiences_sent=0, experiences_pending=0,
        window_experiences=0, hyper_version=0, w_ff_radps=0.0, pred_x_m=[], pred_y_m=[], pred_theta_rad=[],
        sigma_lat_m=0.0, sigma_head_rad=0.0, solver_status="", spread_factors=[], pred_sigma_lat_m=[],
        pred_sigma_head_rad=[], learning_off_since_s=-1.0, learning_note="", step_late_ms=0.0, turn_cap_mps=0.0,
        turn_loss_per_mps2=0.0, speed_held_by="")


class Rig:
    """Router + localizer (serves the route) + scheduler, and a client node playing robot r1."""

    def __init__(self, base, params: SchedulerParams = PARAMS):
        self.base = base
        RouteStore(base / "data" / "routes").save(
            Path(ROUTE, np.column_stack([np.arange(N) * 0.25, np.zeros(N), np.zeros(N)])), 0.0)
        (base / "loc.toml").write_text(dump_toml(LocalizerConfig(robot_name="r1", data_dir=str(base / "data"))))
        (base / "sched.toml").write_text(dump_toml(SchedulerConfig(db_path=str(base / "data" / "sched.db"),
                                                                   params=params)))
        self.port = free_port()
        self.launcher = Launcher(f"tcp/127.0.0.1:{self.port}", base / "logs")
        self.launcher.start_router(self.port)
        self.launcher.start_service("localizer", base / "loc.toml")
        self.node = Node("test", "r1", f"tcp/127.0.0.1:{self.port}")
        self.published: list[SpeedSchedule] = []
        self.new = threading.Condition()
        self.node.subscribe(keys.sched_schedule(ROUTE), SpeedSchedule, self._on_schedule)
        self.alive = False
        self.node.liveliness_subscriber(keys.alive(keys.STORE_ROBOT, "scheduler"), self._on_alive)
        # the scheduler asks the localizer for the route: on a busy machine the localizer can come up
        # after the scheduler has already been asked for its first schedule
        self.localizer_up = threading.Event()
        self.node.liveliness_subscriber(keys.alive("r1", "localizer"),
                                        lambda _key, alive: alive and self.localizer_up.set())
        assert self.localizer_up.wait(60), "the localizer did not come up"
        self.start_scheduler()

    def _on_alive(self, _key: str, alive: bool) -> None:
        with self.new:
            self.alive = alive
            self.new.notify_all()

    def wait_alive(self, alive: bool) -> None:
        with self.new:
            assert self.new.wait_for(lambda: self.alive == alive, 30), f"scheduler alive != {alive}"

    def kill_scheduler(self) -> None:
        self.launcher.kill("scheduler", signal.SIGKILL)
        self.wait_alive(False)      # the router noticed; a restart's token is then really the new one

    def _on_schedule(self, msg: SpeedSchedule, _key: str) -> None:
        with self.new:
            self.published.append(msg)
            self.new.notify_all()

    def start_scheduler(self) -> None:
        self.launcher.start_service("scheduler", self.base / "sched.toml")
        self.wait_alive(True)
        for key in (keys.ctrl_status("r1"), keys.trial_event("r1")):
            assert self.node.wait_matching(key, 30), f"the scheduler does not subscribe to {key}"

    def schedule(self) -> SpeedSchedule:
        return query_one(self.node.session, keys.sched_schedule(ROUTE), SpeedSchedule, timeout_s=10.0)

    def drive_trial(self, trial: int, lateral_m, end_event_first: bool = False, w=lambda i: 0.1,
                    v=lambda i: 0.5) -> None:
        """One repeat as the scheduler sees it: a status per vertex and the controller's end of the route,
        and the bridge's end-of-trial event (after them, or overtaking them as it may on a real bus)."""
        def event():
            self.node.publish(keys.trial_event("r1"), TrialEvent(stamp_s=float(N), trial=trial, mode="repeat",
                                                                 event="ended", reason="finished", path_id=ROUTE))
        if end_event_first:
            self.node.publish(keys.ctrl_status("r1"), status(trial, 0, "tracking", lateral_m(0)))
            event()
        for i in range(N):
            self.node.publish(keys.ctrl_status("r1"), status(trial, i, "tracking", lateral_m(i), w(i), v(i)))
        self.node.publish(keys.ctrl_status("r1"), status(trial, N - 1, "finished", 0.0))
        if not end_event_first:
            event()

    def wait_version(self, version: int) -> SpeedSchedule:
        with self.new:
            assert self.new.wait_for(lambda: any(s.version == version for s in self.published), 30), \
                f"no schedule v{version} published; log:\n{self.log()}"
            return next(s for s in self.published if s.version == version)

    def log(self) -> str:
        return (self.base / "logs" / "scheduler.log").read_text(errors="replace")

    def close(self) -> None:
        self.node.close()
        self.launcher.stop()


@pytest.fixture
def rig(tmp_path):
    r = Rig(tmp_path)
    try:
        yield r
    finally:
        r.close()


def test_collects_passes_from_the_bus_and_schedules_the_next_trial(rig):
    v1 = rig.schedule()
    assert v1.version == 1 and len(v1.v_mps) == N
    s = np.arange(N) * 0.25
    assert np.allclose(np.asarray(v1.v_mps)[(s > 5) & (s < 44)], 0.5)   # v_init; 0.4 over the first and last 5 m
    assert max(v1.v_mps[0], v1.v_mps[-1]) <= 0.4 + 1e-9

    # 0.25 m off between 20 and 25 m (beyond 0.15 * 1.1), well inside elsewhere
    rig.drive_trial(1, lambda i: 0.25 if 80 <= i <= 100 else 0.02)
    v2 = rig.wait_version(2)
    d, v = np.asarray(v2.decisions), np.asarray(v2.v_mps)
    assert v2.based_on_robot == "r1" and v2.based_on_trial == 1
    assert np.all(d[80:101] == DECREASE) and np.all(d[:80] == INCREASE) and np.all(d[101:] == INCREASE)
    assert np.allclose(v[80:101], 0.5 - 0.24)                                # eq. 4.2, second case
    # eq. 4.4's deceleration limit ramps the speed down before the slow section
    ramp = np.sqrt(0.26 ** 2 + 2 * 0.05 * (20.0 - s[60:80]))
    assert np.allclose(v[60:80], np.minimum(0.7, ramp))
    assert any("feature criterion is skipped" in n for n in v2.notes)

    # the runner asking for the same update gets the same schedule, not a second step
    again = query_one(rig.node.session, keys.sched_update(ROUTE), SpeedSchedule,
                      payload=encode(ScheduleUpdate(stamp_s=0.0, path_id=ROUTE, robot="r1", trial=1)), timeout_s=10)
    assert again.version == 2 and again.v_mps == v2.v_mps
    assert rig.schedule().version == 2


def test_lbc_sched_show_prints_the_latest_schedule(rig, capsys):
    from deploy.cli import main
    rig.schedule()
    assert main(["sched", "show", "--path", ROUTE, "--json", "--connect", f"tcp/127.0.0.1:{rig.port}"]) == 0
    shown = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert shown["version"] == 1 and len(shown["v_mps"]) == N
    assert main(["sched", "show", "--path", "nowhere", "--connect", f"tcp/127.0.0.1:{rig.port}"]) == 1
    assert "no taught route" in capsys.readouterr().err


def test_an_end_event_overtaking_the_passes_waits_for_them(rig):
    rig.schedule()
    rig.drive_trial(1, lambda i: 0.25 if i == N // 2 else 0.02, end_event_first=True)
    v2 = rig.wait_version(2)
    assert not any("not passed" in n for n in v2.notes), v2.notes
    assert v2.decisions[N // 2] == DECREASE and v2.decisions[0] == INCREASE


def test_schedules_and_passes_survive_a_sigkill(rig):
    rig.schedule()
    rig.drive_trial(1, lambda i: 0.02)
    v2 = rig.wait_version(2)
    rig.kill_scheduler()
    rig.start_scheduler()
    after = rig.schedule()
    assert after.version == 2 and after.v_mps == v2.v_mps
    rig.drive_trial(2, lambda i: 0.02)
    v3 = rig.wait_version(3)
    assert v3.based_on_trial == 2 and max(v3.v_mps) > max(v2.v_mps)


def test_bad_requests_get_a_reason_and_the_service_keeps_running(rig):
    with pytest.raises(LookupError, match="no taught route"):
        query_one(rig.node.session, keys.sched_schedule("nowhere"), SpeedSchedule, timeout_s=10)
    with pytest.raises(LookupError, match="no experience collected"):
        query_one(rig.node.session, keys.sched_update(ROUTE), SpeedSchedule,
                  payload=encode(ScheduleUpdate(stamp_s=0.0, path_id=ROUTE, robot="r1", trial=7)), timeout_s=10)
    with pytest.raises(LookupError, match="ScheduleUpdate"):
        query_one(rig.node.session, keys.sched_update(ROUTE), SpeedSchedule, payload=b"\x92\x01", timeout_s=10)
    assert rig.schedule().version == 1


def test_the_guard_holds_a_turn_the_thesis_rule_would_speed_up(tmp_path):
    """A turn at 23.75-26.25 m took 0.7 rad/s at a commanded 0.45 m/s (eq. 4.2 raises it: 0.7 < 1.0).
    The guard's bound is min(1.0, 0.8 * w_max 1.2) = 0.96 rad/s, reached at 0.96 * 0.45 / 0.7 = 0.617 m/s:
    the turn and 3 m either side rise only that far, the rest by gamma1 to 0.7."""
    rig = Rig(tmp_path, replace(PARAMS, guard=True, w_max=1.2))
    try:
        rig.schedule()
        rig.drive_trial(1, lambda i: 0.02, w=lambda i: 0.7 if 95 <= i <= 105 else 0.1, v=lambda i: 0.45)
        v2 = rig.wait_version(2)
        d, v = np.asarray(v2.decisions), np.asarray(v2.v_mps)
        assert np.all(d[20:180] == INCREASE)                    # eq. 4.2's decisions, as they were
        assert np.allclose(v[83:118], 0.96 * 0.45 / 0.7) and v[40] == pytest.approx(0.7)
        assert v[150] == pytest.approx(0.7)
        assert any(n.startswith("guard: ") and "turn rate" in n for n in v2.notes), v2.notes
    finally:
        rig.close()


def test_the_guard_keeps_an_ackermann_at_v_init_where_it_turned_at_its_curvature_limit(tmp_path):
    """G8 through the service (the route's curvature comes from the localizer's route). Every vertex of the
    straight route was 0.25 m off at 0.5 m/s (beyond lambda_L 0.15 and its deadband: eq. 4.2 lowers all to
    0.26); at 23.75-26.25 m the robot turned at 0.15 rad/s, 0.30 /m, at a MATS's limit (kappa_max 0.3039,
    0.9 of it 0.2735). Those vertices and 3 m either side stay at v_init; the rest go to 0.26."""
    rig = Rig(tmp_path, replace(PARAMS, guard=True, w_max=1.0, kappa_max=0.3039))
    try:
        rig.schedule()
        rig.drive_trial(1, lambda i: 0.25, w=lambda i: 0.15 if 95 <= i <= 105 else 0.05, v=lambda i: 0.5)
        v2 = rig.wait_version(2)
        d, v = np.asarray(v2.decisions), np.asarray(v2.v_mps)
        assert np.all(d[20:180] == DECREASE)                    # eq. 4.2's decisions, as they were
        assert v[100] == pytest.approx(0.5) and v[90] == pytest.approx(0.5)
        assert v[40] == pytest.approx(0.26) and v[150] == pytest.approx(0.26)
        assert any("not lowered below v_init" in n for n in v2.notes), v2.notes
    finally:
        rig.close()

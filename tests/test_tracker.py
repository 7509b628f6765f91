"""The feedback-linearized tracker (eq. 3.1-3.5) in closed loop with the simulator, and the
controller core's safety behaviour (stale or lost localization, dropouts, end of route)."""
import math

import numpy as np
import pytest

from common.messages import LocState
from common.path import Path
from common.scenario import TerrainPatch
from services.controller.core import ControllerCore
from services.controller.fl import FLGains, fl_angular_rate
from services.controller.laws import FLLaw, LawResult
from services.controller.corridor import Corridor
from services.controller.tracker import PathTracker, TrackerLimits
from services.localizer.pose_source import PoseSourceSettings
from bench.closed_loop import ClosedLoop
from bench.stops import stops_on

STRAIGHT_THEN_ARC = [[0, 0], [12, 0], [20, 8], [20, 16]]   # 12 m straight, then 3 m-radius arcs
SLOPE = TerrainPatch(kind="side_slope", center=(8.0, 0.0), radius_m=5.0, slope_deg=12.0, downhill_deg=-90.0)


def test_fl_law_is_eq_3_5_in_our_sign_convention():
    g = FLGains(gamma1=1.0, gamma2=2.0, curvature_feedforward=False)
    # left of the route (e_L > 0), aligned: turn right
    assert fl_angular_rate(0.5, 0.1, 0.0, 0.0, g) == pytest.approx(-1.0 * 0.1 / 0.5)
    # heading left of the route: turn right, -g2 tan(e_H)
    assert fl_angular_rate(0.5, 0.0, 0.2, 0.0, g) == pytest.approx(-2.0 * math.tan(0.2))
    # on an arc, on the route: the route's own turn rate v*kappa
    assert fl_angular_rate(0.5, 0.0, 0.0, 0.2, FLGains()) == pytest.approx(0.1)


def test_flat_ground_straight_then_arc_stays_within_5_cm():
    sim = ClosedLoop(STRAIGHT_THEN_ARC, preset="husky", seed=2)
    sim.teach()
    r = sim.repeat(1, speed=0.5)
    assert r.finished
    assert r.max_lateral < 0.05


def test_side_slope_error_is_clearly_larger_and_repeatable():
    flat = ClosedLoop(STRAIGHT_THEN_ARC, preset="husky", seed=2)
    flat.teach()
    slope = ClosedLoop(STRAIGHT_THEN_ARC, terrain=[SLOPE], preset="husky", seed=2)
    slope.teach()
    f = flat.repeat(1, 0.5)
    s1, s2 = slope.repeat(1, 0.5), slope.repeat(2, 0.5)
    assert s1.finished and s2.finished
    assert s1.max_lateral > 0.08 and s1.max_lateral > 3 * f.max_lateral
    # the same place gives the same error, trial after trial: there is something to learn
    n = min(len(s1.lateral_m), len(s2.lateral_m))
    assert abs(s1.max_lateral - s2.max_lateral) < 0.02
    assert np.corrcoef(s1.lateral_m[:n], s2.lateral_m[:n])[0, 1] > 0.9


def test_ackermann_robot_tracks_through_eq_5_27():
    sim = ClosedLoop([[0, 0], [15, 0], [30, 10], [30, 25]], preset="mats", seed=1)
    sim.teach()
    r = sim.repeat(1, speed=1.0)
    assert r.finished and r.max_lateral < 0.15


def test_noisy_delayed_localization_still_tracks():
    sim = ClosedLoop(STRAIGHT_THEN_ARC, preset="husky", seed=3,
                     loc=PoseSourceSettings(noise_m=0.01, noise_heading_rad=math.radians(0.3), delay_ticks=2,
                                            dropout_prob=0.02, dropout_ticks=2))
    sim.teach()
    r = sim.repeat(1, 0.5)
    assert r.finished and r.max_lateral < 0.1


# --- safety behaviour of the core, with hand-made estimates ------------------------------------
PATH = Path("p", np.column_stack([np.arange(0, 10, 0.25), np.zeros(40), np.zeros(40)]))
LIMITS = TrackerLimits(v_max_mps=1.0, w_max_radps=1.0)


def loc(t, x=1.0, y=0.05, status="ok", capture=None):
    v = PATH.nearest_vertex((x, y))
    ok = status == "ok"
    cap = t if capture is None else capture
    return LocState(stamp_s=t, capture_stamp_s=cap, tick=round(t * 10), capture_tick=round(cap * 10), trial=1,
                    path_id="p", source="pose", status=status, reason="", vertex=v, distance_m=x,
                    T_vertex_robot=(x - PATH.poses[v, 0], y, 0.0) if ok else None,
                    cov_T_vertex_robot=(1e-4, 0, 0, 0, 1e-4, 0, 0, 0, 1e-6) if ok else None, matched_features=None)


def posed(t, x, y, theta):
    """An estimate at pose (x, y, theta) on PATH (heading 0)."""
    v = PATH.nearest_vertex((x, y))
    return LocState(stamp_s=t, capture_stamp_s=t, tick=round(t * 10), capture_tick=round(t * 10), trial=1,
                    path_id="p", source="pose", status="ok", reason="", vertex=v, distance_m=x,
                    T_vertex_robot=(x - PATH.poses[v, 0], y, theta),
                    cov_T_vertex_robot=(1e-4, 0, 0, 0, 1e-4, 0, 0, 0, 1e-6), matched_features=None)


def test_waits_for_first_estimate_then_tracks():
    tr = PathTracker(PATH, FLLaw(FLGains()), LIMITS, speed_mps=0.5)
    d = tr.step(0.0, loc(0.0, status="initializing"))
    assert d.state == "waiting" and d.v_mps == 0.0
    d = tr.step(0.1, loc(0.1))
    assert d.state == "tracking" and d.v_mps == pytest.approx(0.5) and d.w_radps < 0


def test_holds_through_short_dropout_and_stops_when_stale():
    tr = PathTracker(PATH, FLLaw(FLGains()), LIMITS, speed_mps=0.5, loc_timeout_s=0.5)
    d0 = tr.step(1.0, loc(1.0))
    d = tr.step(1.2, loc(1.2, status="dropout"))
    assert d.state == "holding" and (d.v_mps, d.w_radps) == (d0.v_mps, d0.w_radps)
    d = tr.step(1.6, loc(1.6, status="dropout"))
    assert d.state == "stopped" and d.v_mps == 0.0 and "stale" in d.reason
    d = tr.step(1.7, loc(1.7, x=1.1))
    assert d.state == "tracking"  # fresh estimates again: carry on


def test_delayed_estimate_counts_its_age_from_capture():
    tr = PathTracker(PATH, FLLaw(FLGains()), LIMITS, speed_mps=0.5, loc_timeout_s=0.5)
    d = tr.step(2.0, loc(2.0, capture=1.4))
    assert d.state == "stopped" and d.loc_age_s == pytest.approx(0.6)


def test_stops_at_once_when_lost():
    tr = PathTracker(PATH, FLLaw(FLGains()), LIMITS, speed_mps=0.5)
    tr.step(1.0, loc(1.0))
    d = tr.step(1.1, loc(1.1, status="lost"))
    assert d.state == "stopped" and d.v_mps == 0.0 and "lost" in d.reason


class FailingLaw:
    name = "failing"

    def __init__(self, exc: Exception):
        self.exc = exc

    def angular(self, ctx):
        raise self.exc


@pytest.mark.parametrize("exc", [np.linalg.LinAlgError("singular"), FloatingPointError("overflow"),
                                 ZeroDivisionError("division")])
def test_a_law_failing_numerically_gives_feedback_linearization_for_that_step(exc):
    tr = PathTracker(PATH, FailingLaw(exc), LIMITS, speed_mps=0.5)
    d = tr.step(1.0, loc(1.0))
    fl = PathTracker(PATH, FLLaw(FLGains()), LIMITS, speed_mps=0.5).step(1.0, loc(1.0))
    assert d.state == "tracking" and d.w_radps == pytest.approx(fl.w_radps)
    assert "failing failed" in d.reason and "feedback linearization" in d.reason


@pytest.mark.parametrize("exc", [KeyError("sigma_lat_max_m"), AttributeError("no such field"), TypeError("args")])
def test_a_law_with_a_programming_error_fails_loudly(exc):
    """Only numerical failures fall back to FL: a bug in a law must fail the tests, not drive on FL."""
    tr = PathTracker(PATH, FailingLaw(exc), LIMITS, speed_mps=0.5)
    with pytest.raises(type(exc)):
        tr.step(1.0, loc(1.0))


class StoppingLaw:
    """Tracks like FL until `at_s`, then stops the robot for safety (as RC-LB-NMPC does)."""
    name = "stopping"

    def __init__(self, at_s: float):
        self.at_s, self.fl = at_s, FLLaw(FLGains())

    def angular(self, ctx):
        if ctx.now_s >= self.at_s:
            return LawResult(0.0, v_mps=0.0, stop_reason="predicted uncertainty no longer fits the corridor: stopped")
        return self.fl.angular(ctx)


def test_a_safety_stop_brakes_along_the_route_at_the_robots_limit():
    """A law's stop is a manoeuvre: the speed falls by decel * dt per period and the turn rate keeps
    steering towards the route (FL's curvature at the braking speed, within BRAKE_CURVATURE_PER_M: FL's
    turn rate grows like 1 / v and would spin a slow robot in place), until the robot stands; then it
    is stopped."""
    from services.controller.tracker import BRAKE_CURVATURE_PER_M
    limits = TrackerLimits(v_max_mps=1.0, w_max_radps=1.0, decel_mps2=2.0)
    tr = PathTracker(PATH, StoppingLaw(at_s=1.05), limits, speed_mps=1.0, period_s=0.1)
    assert tr.step(1.0, loc(1.0, x=1.0, y=0.0)).v_mps == pytest.approx(1.0)
    states, speeds = [], []
    for k in range(1, 9):
        d = tr.step(1.0 + 0.1 * k, loc(1.0 + 0.1 * k, x=1.0 + 0.1 * k, y=0.05))
        states.append(d.state)
        speeds.append(d.v_mps)
        if d.state == "stopping":   # left of the route: steering right, as FL at that speed would
            c = max(-BRAKE_CURVATURE_PER_M, fl_angular_rate(d.v_mps, 0.05, 0.0, 0.0, FLGains()) / d.v_mps)
            assert d.w_radps == pytest.approx(c * d.v_mps) and d.w_radps < 0
            assert "braking along the route" in d.reason and "uncertainty" in d.reason
    assert states == ["stopping"] * 4 + ["stopped"] * 4
    assert speeds[:4] == pytest.approx([0.8, 0.6, 0.4, 0.2]) and speeds[4:] == [0.0] * 4


def test_a_lagging_ackermann_keeps_steering_along_the_route_until_its_drive_has_stopped():
    """A 0.5 s drive lag: the command reaches 0 in two periods, the robot rolls on for a second. The
    stop keeps steering (towards the route, by a curvature within the steering limit) until the lag model
    says the drive has stopped, commanding an Ackermann a creep so that its wheels can still steer
    (eq. 5.27 needs a speed); only then is it stopped."""
    from services.controller.actuator import ActuatorLag
    from services.controller.tracker import CREEP_MPS, REST_MPS
    lag = ActuatorLag(0.5, 0.0, 0.1)
    limits = TrackerLimits(v_max_mps=1.0, w_max_radps=1.0, max_curvature=0.3, decel_mps2=5.0)
    tr = PathTracker(PATH, StoppingLaw(at_s=1.05), limits, speed_mps=1.0, period_s=0.1, lag=lag)
    sent = {k: (1.0, 0.0) for k in range(10)}
    decisions = []
    for k in range(10, 40):
        d = tr.step(0.1 * k, loc(0.1 * k, x=0.1 * k, y=0.05), tick=k, command_at=sent.get)
        sent[k] = (d.v_mps, d.w_radps)
        decisions.append(d)
    stopping = [d for d in decisions if d.state == "stopping"]
    drive = [lag.state_before(k, sent.get)[0] for k in range(10, 41)]
    first_zero = next(i for i, d in enumerate(decisions) if d.state == "stopped")
    assert len(stopping) > 5                                     # far beyond the two periods of the command ramp
    assert all(d.v_mps >= CREEP_MPS and d.w_radps < 0 for d in stopping)   # left of the route: steering right
    assert all(abs(d.w_radps) <= 0.3 * d.v_mps + 1e-12 for d in stopping)  # within the steering limit
    assert drive[first_zero] <= REST_MPS < drive[first_zero - 1]
    assert all(d.state == "stopped" and d.v_mps == 0.0 for d in decisions[first_zero:])


def test_a_lagging_skid_steer_brakes_without_turning_off_the_route():
    """A skid-steer's turn drive lags too (0.73 s, a Grizzly's). A stop just out of a turn finds the
    drive still turning at the turn's rate while its speed falls: commanding the route's curvature times
    the speed lets that rate turn the robot on. The brake brings the drive's turn rate to the route's
    curvature at the speed the drive will have (here 0: a straight route), countering the drive's rate
    within the robot's turn-rate limit, so the robot (here the lag model itself) turns half as far; it is
    stopped once the model's drive neither rolls nor turns."""
    from services.controller.actuator import ActuatorLag
    from services.controller.tracker import REST_MPS, REST_RADPS
    lag = ActuatorLag(0.53, 0.73, 0.1)
    tr = PathTracker(PATH, StoppingLaw(at_s=1.05), TrackerLimits(v_max_mps=2.0, w_max_radps=1.2, decel_mps2=2.5),
                     speed_mps=1.5, period_s=0.1, lag=lag)
    sent = {k: (1.5, 0.6) for k in range(10)}          # the drive still turns at 0.6 rad/s
    x, y, th, xi = 1.0, 0.0, 0.0, (1.5, 0.6)
    states, heading = [], []
    for k in range(10, 50):
        d = tr.step(0.1 * k, posed(0.1 * k, x, y, th), tick=k, command_at=sent.get)
        sent[k] = (d.v_mps, d.w_radps)
        states.append(d.state)
        (v, w), xi = lag.step(xi, sent[k])
        th += w * 0.1
        x, y = x + v * 0.1 * math.cos(th), y + v * 0.1 * math.sin(th)
        heading.append(th)
    assert states[0] == "tracking" and states[1] == "stopping" and states[-1] == "stopped"
    # 7 deg, 3 of them in the period before the stop; 13 deg when the command ignores the lag
    assert max(abs(h) for h in heading) < math.radians(8.5)
    rest = states.index("stopped")
    assert rest > 5 and abs(xi[0]) <= REST_MPS and abs(lag.state_before(10 + rest, sent.get)[1]) <= REST_RADPS

def test_a_safety_stop_without_an_estimate_stops_at_once():
    tr = PathTracker(PATH, StoppingLaw(at_s=1.05), TrackerLimits(1.0, 1.0, decel_mps2=2.0), speed_mps=1.0)
    tr.step(1.0, loc(1.0))
    d = tr.step(1.1, loc(1.1, status="lost"))
    assert d.state == "stopped" and d.v_mps == 0.0 and d.w_radps == 0.0


def test_slows_into_the_end_and_finishes():
    tr = PathTracker(PATH, FLLaw(FLGains()), LIMITS, speed_mps=1.0, stop_decel_mps2=0.4)
    assert tr.step(0.0, loc(0.0, x=2.0, y=0.0)).v_mps == pytest.approx(1.0)
    near = tr.step(0.1, loc(0.1, x=9.5, y=0.0)).v_mps
    assert 0.0 < near < 0.6
    d = tr.step(0.2, loc(0.2, x=PATH.length_m + 0.01, y=0.0))
    assert d.state == "finished" and d.v_mps == 0.0
    assert tr.step(0.3, loc(0.3, x=2.0)).state == "finished"   # and stays finished


class SlowingLaw:
    """FL's turn at a slower speed of its own, saying why (as RC-LB-NMPC's speed ladder does)."""
    name = "slowing"

    def angular(self, ctx):
        return LawResult(FLLaw(FLGains()).angular(ctx).w_radps, v_mps=0.3, held_by="ladder-heading")


def test_each_step_says_what_held_its_speed_below_the_asked_one():
    """The asked speed: nothing; the slow-down into the end: "route-end"; the robot's top speed:
    "robot-limit"; a law that drives slower: its own cause."""
    tr = PathTracker(PATH, FLLaw(FLGains()), LIMITS, speed_mps=1.0, stop_decel_mps2=0.4)
    assert tr.step(0.0, loc(0.0, x=2.0, y=0.0)).held_by == ""
    assert tr.step(0.1, loc(0.1, x=9.5, y=0.0)).held_by == "route-end"
    fast = PathTracker(PATH, FLLaw(FLGains()), LIMITS, speed_mps=LIMITS.v_max_mps + 1.0)
    assert fast.step(0.0, loc(0.0, x=2.0, y=0.0)).held_by == "robot-limit"
    slowed = PathTracker(PATH, SlowingLaw(), LIMITS, speed_mps=1.0)
    d = slowed.step(0.0, loc(0.0, x=2.0, y=0.0))
    assert d.v_mps == pytest.approx(0.3) and d.held_by == "ladder-heading"


def test_a_skid_steer_heading_for_its_corridors_edge_slows_to_where_it_can_turn_away_in_time():
    """0.1 m left of a straight route in a 0.3 m corridor, heading 0.5 rad further left: turning that away
    within the 0.2 m left takes c = 0.5^2 / (2 x 0.2) = 0.625 /m, which 80 % of a 0.5 rad/s turn gives at
    0.4 / 0.625 = 0.64 m/s (turn_speed.turn_cap without a turn loss). Heading back towards the route, the
    0.4 m to the far edge ask 0.3125 /m: 1.28 m/s, above the asked 1 m/s. An Ackermann's curvature does
    not grow as it slows, and a law that chooses its speed (turn share 0) is left to it."""
    limits = TrackerLimits(v_max_mps=1.0, w_max_radps=0.5)
    corridor = Corridor(PATH.s, 0.3, math.radians(40))

    def step(heading, limits=limits, turn_share=0.8):
        tr = PathTracker(PATH, FLLaw(FLGains()), limits, speed_mps=1.0, corridor=corridor, turn_share=turn_share)
        return tr.step(0.0, posed(0.0, 2.0, 0.1, heading))
    out = step(0.5)
    assert out.v_mps == pytest.approx(0.4 / 0.625) and out.held_by == "recovery"
    back = step(-0.5)
    assert back.v_mps == pytest.approx(1.0) and back.held_by == ""
    assert step(0.5, turn_share=0.0).v_mps == pytest.approx(1.0)
    ackermann = TrackerLimits(v_max_mps=1.0, w_max_radps=0.5, max_curvature=0.8)
    assert step(0.5, limits=ackermann).v_mps == pytest.approx(1.0)


def test_after_a_recovery_the_speed_stays_down_until_the_errors_are_back_within_half_the_corridor():
    """The case above holds 0.64 m/s. Turned back to the route's heading 0.25 m out (0.83 of the 0.3 m),
    nothing caps the speed by the heading, but the robot is still far out: it stays at 0.64. At 0.05 m
    (0.17), heading 0.2 rad and turning at 2 rad/s, the heading a period ahead (0.4 rad, 0.57 of 40 deg)
    keeps it there; once the heading has settled, back to the asked 1 m/s."""
    limits = TrackerLimits(v_max_mps=1.0, w_max_radps=0.5)
    tr = PathTracker(PATH, FLLaw(FLGains()), limits, speed_mps=1.0, corridor=Corridor(PATH.s, 0.3, math.radians(40)),
                     turn_share=0.8)
    assert tr.step(0.0, posed(0.0, 2.0, 0.1, 0.5)).v_mps == pytest.approx(0.64)
    far = tr.step(0.1, posed(0.1, 2.1, 0.25, 0.0))
    assert far.v_mps == pytest.approx(0.64) and far.held_by == "recovery"
    assert tr.step(0.2, posed(0.2, 2.2, 0.05, 0.2)).v_mps == pytest.approx(0.64)    # heading -> 0.4 rad
    back = tr.step(0.3, posed(0.3, 2.3, 0.05, 0.2))
    assert back.v_mps == pytest.approx(1.0) and back.held_by == ""


def test_loop_route_is_repeated_once_round_without_jumping_to_its_end():
    sim = ClosedLoop([[0, 0], [12, 0], [12, 8], [0, 8]], preset="husky", seed=5, loop=True)
    path = sim.teach()
    assert path.loop and np.hypot(*(path.poses[0, :2] - path.poses[-1, :2])) < 0.5
    r = sim.repeat(1, 0.6)
    assert r.finished and r.max_lateral < 0.06
    assert r.steps * 0.1 * 0.6 > 0.9 * path.length_m     # drove the whole lap, did not stop at once


def test_teach_pass_failure_shifts_the_estimate_not_the_robot():
    jump = (8.0, 2.0, 0.25)   # 8-10 m along the route, 25 cm sideways
    sim = ClosedLoop(STRAIGHT_THEN_ARC, preset="husky", seed=2, loc=PoseSourceSettings(noise_m=0.0, noise_heading_rad=0.0,
                                                                                        jumps=(jump,)))
    sim.teach()
    r = sim.repeat(1, 0.5)
    assert r.finished
    # the controller chases the phantom offset: the real robot moves about 25 cm the other way there
    s = np.arange(len(r.lateral_m)) * 0.05
    inside = (s > 9.0) & (s < 10.0)
    assert np.min(r.lateral_m[inside]) < -0.15
    assert np.max(np.abs(r.lateral_m[s < 7.0])) < 0.05


class StopsAt:
    """Straight ahead until `stop_s`, then the law asks for a safety stop (as C-/RC-LB-NMPC do)."""
    name = "stops-at"

    def __init__(self, stop_s: float):
        self.stop_s = stop_s

    def angular(self, ctx):
        return LawResult(0.0, stop_reason="test stop" if ctx.now_s >= self.stop_s else "")


def test_a_robot_held_at_rest_after_a_safety_stop_yields_no_experiences():
    """Experiences come from every refined estimate while the robot drives; once stopped, none: a robot at
    rest shows nothing of how it moves (its estimates' noise looks like motion), and how long it is held
    depends on when the runner ends the trial."""
    core = ControllerCore(PATH, PathTracker(PATH, StopsAt(1.0), LIMITS, speed_mps=0.5), 0.1)
    states, observed = [], []
    for k in range(1, 21):
        t = round(0.1 * k, 1)
        jitter = 0.02 * (k % 2) if k > 10 else 0.0     # 2 cm of localization noise: 0.2 m/s apparent
        d, obs = core.step(t, k, loc(t, x=1.0 + 0.05 * min(k, 10) + jitter))
        states.append(d.state)
        observed.append(bool(obs))
    assert states[:9] == ["tracking"] * 9 and set(states[10:]) == {"stopped"}
    assert sum(observed[1:9]) >= 7 and not any(observed[10:])


def test_a_lagging_robot_at_the_end_of_the_route_steers_along_it_until_its_drive_has_stopped():
    """The estimate passes the last vertex while a 0.5 s drive still rolls: the end of the route is the
    same manoeuvre as a safety stop (braking while steering towards the route, left of it: right), in the
    state "finished" from its first step, until the lag model says the drive has stopped."""
    from services.controller.actuator import ActuatorLag
    from services.controller.tracker import REST_MPS
    lag = ActuatorLag(0.5, 0.0, 0.1)
    tr = PathTracker(PATH, FLLaw(FLGains()), TrackerLimits(v_max_mps=1.0, w_max_radps=1.0, decel_mps2=2.0),
                     speed_mps=1.0, period_s=0.1, lag=lag)
    sent = {k: (1.0, 0.0) for k in range(10)}
    decisions = []
    for k in range(10, 40):
        d = tr.step(0.1 * k, loc(0.1 * k, x=PATH.length_m + 0.01 * (k - 9), y=0.05), tick=k, command_at=sent.get)
        sent[k] = (d.v_mps, d.w_radps)
        decisions.append(d)
    assert all(d.state == "finished" for d in decisions)
    braking = [d for d in decisions if "braking along the route" in d.reason]
    assert len(braking) > 5 and all(d.w_radps < 0 for d in braking)
    drive = [lag.state_before(k, sent.get)[0] for k in range(10, 41)]
    first_still = next(i for i, d in enumerate(decisions) if "braking" not in d.reason)
    assert drive[first_still] <= REST_MPS < drive[first_still - 1]
    assert all(d.v_mps == 0.0 and d.w_radps == 0.0 for d in decisions[first_still:])


def test_a_grizzly_stopped_from_speed_in_a_corner_comes_to_rest_near_the_routes_heading():
    """`lbc bench stops`'s case: the simulated Grizzly (0.73 s turn-drive lag, yaw-acceleration limit,
    slip), with the drive model its teach pass identifies, stopped at 1.9 m/s in the middle of a 5 m
    corner. It turned 30.4 deg after the stop when the brake commanded the curvature times the speed
    (docs/results.md, stop 61); countering the drive's lag, 14.0 deg, while its lateral error grows
    by 5 cm as before."""
    (out,) = stops_on("grizzly", 5.0, [0.75], [0.5], seed=3)
    assert out.heading_turned_deg < 20.0
    assert out.lateral_growth_m < 0.08

"""The speed cap from the robot's turn (services/controller/turn_speed.py), worked by hand."""
import math

import numpy as np
import pytest

from common.path import Path
from services.controller.actuator import ActuatorLag
from services.controller.laws import FLLaw
from services.controller.fl import FLGains
from services.controller.tracker import PathTracker, TrackerLimits
from services.controller.turn_speed import TURN_SHARE, TurnLoss, turn_cap, turn_speed_caps

R = 2.77          # corner radius (m), bench seed 6841's Grizzly s1770375239
SPACING = 0.1


def _corner_path(before_m: float = 20.0, after_m: float = 20.0) -> Path:
    """A straight, a left quarter circle of radius R, a straight, one vertex every SPACING."""
    a = np.arange(0.0, before_m, SPACING)
    poses = [(x, 0.0, 0.0) for x in a]
    arc = np.arange(0.0, 0.5 * math.pi * R, SPACING) / R
    poses += [(before_m + R * math.sin(t), R * (1 - math.cos(t)), t) for t in arc]
    b = np.arange(0.0, after_m, SPACING)
    poses += [(before_m + R, R + y, 0.5 * math.pi) for y in b]
    return Path("corner", np.array(poses), spacing_m=SPACING)


def test_the_cap_is_the_share_of_the_turn_at_the_limit_over_the_curvature():
    # 0.8 * 0.555 * 1.2 rad/s over 1 / 2.77 m: 1.476 m/s
    assert turn_cap(1 / R, TURN_SHARE * 0.555, 1.2, math.inf) == pytest.approx(0.8 * 0.555 * 1.2 * R)
    # an Ackermann whose steering cannot make the curve at any speed: no cap helps
    assert turn_cap(0.5, 0.8, 1.0, 0.4) == math.inf
    assert turn_cap(0.0, 0.8, 1.0, math.inf) == math.inf


def test_with_a_turn_loss_the_cap_turns_the_route_at_the_share_of_what_the_robot_makes_there():
    c, k, w = 0.31, 0.664, 1.2
    v = turn_cap(1 / R, TURN_SHARE * k, w, math.inf, c)
    made = k * w / (1 + c * v * w)         # the robot's turn at its limit at that speed
    assert v / R == pytest.approx(TURN_SHARE * made)
    assert v < turn_cap(1 / R, TURN_SHARE * k, w, math.inf)


def test_the_robot_brakes_into_the_corner_a_drive_lag_early():
    path = _corner_path()
    cap = TURN_SHARE * 0.555 * 1.2 * R
    a, lead = 0.4, 0.5
    caps = turn_speed_caps(path, TURN_SHARE * 0.555, 1.2, math.inf, settle_m=0.5, decel_mps2=a, lead_m=lead)
    mid = int(np.argmin(np.abs(path.s - (20.0 + 0.25 * math.pi * R))))
    assert caps[mid] == pytest.approx(cap, rel=0.02)
    # 10 m before the corner: braking at a down to the cap where the route's 1 m curvature window lies in
    # the arc (0.5 m into it), begun `lead` early
    i = int(np.argmin(np.abs(path.s - 10.0)))
    lo, hi = (math.sqrt(cap ** 2 + 2 * a * (10.0 + 0.5 - lead + d)) for d in (-SPACING, SPACING))
    assert lo <= caps[i] <= hi
    # nothing caps the straight after the corner, beyond the curvature window
    assert np.all(np.isinf(caps[path.s > 20.0 + 0.5 * math.pi * R + 1.0]))
    # and every drop is one braking at a can make
    assert np.all(np.diff(caps[np.isfinite(caps)] ** 2) >= -2 * a * SPACING * 1.001)


def test_the_tracker_asks_the_capped_speed_in_the_corner_and_the_asked_one_elsewhere():
    path = _corner_path()
    lag = ActuatorLag(0.27, 0.37, 0.1, turn_gain=0.555)
    limits = TrackerLimits(2.0, 1.2)
    t = PathTracker(path, FLLaw(FLGains(), lag), limits, speed_mps=1.85, lag=lag)
    corner = 20.0 + 0.25 * math.pi * R
    assert t.speed_at(corner) == pytest.approx(TURN_SHARE * 0.555 * 1.2 * R, rel=0.02)
    assert t.speed_at(2.0) == pytest.approx(1.85)
    metres, lowest = t.turn_capped()
    assert 0.5 * math.pi * R < metres < 0.5 * math.pi * R + 8.0 and lowest == pytest.approx(t.speed_at(corner))
    off = PathTracker(path, FLLaw(FLGains(), lag), limits, speed_mps=1.85, lag=lag, turn_share=0.0)
    assert off.speed_at(corner) == pytest.approx(1.85) and off.turn_capped() == (0.0, math.inf)


def test_the_turn_loss_is_the_one_the_ground_turned_the_robot_with():
    """Corners of a robot that turns at k w_d / (1 + c v |w_d|), with noise on the measured turn: c comes
    back. Slow periods, gentle curves and a drive held against the ground's yaw say nothing."""
    k, c = 0.6, 0.3
    rng = np.random.default_rng(3)
    loss = TurnLoss(k)
    for _ in range(400):
        v, wd = rng.uniform(0.5, 2.0), rng.choice([-1, 1]) * rng.uniform(0.2, 1.2)
        w = k * wd / (1 + c * v * abs(wd))
        loss.add(v, wd, w + 0.02 * rng.standard_normal(), w)
    assert loss.per_mps2 == pytest.approx(c, rel=0.1)
    few = TurnLoss(k)
    for _ in range(50):
        few.add(0.2, 1.0, 0.1, 0.5)         # a crawl
        few.add(1.0, 0.5, 0.3, 0.1)         # a gentle curve
        few.add(1.0, 1.0, 0.0, 0.0)         # on a straight, held against a side slope's yaw
        few.add(1.0, -1.0, 0.3, 0.5)        # in a corner, against it
    assert few.samples == 0 and few.per_mps2 == 0.0


def test_a_skid_steer_asked_for_more_turn_than_it_makes_slows_for_the_corners_and_stays_near_the_route():
    """A perturbed Grizzly (bench seed 6841, s1770375239) at 1.85 m/s round 2.77 m corners: at its limit it
    turns about 0.5 rad/s there, and the route needs 0.67. At the asked speed FL leaves the route by 1.7 m;
    capped, and learning the turn lost to skidding in the first corner, by 0.49 m."""
    from bench.closed_loop import ClosedLoop
    from common.robot import robot_from_preset
    from services.localizer.pose_source import PoseSourceSettings
    robot = robot_from_preset("grizzly", dict(
        tau_v_s=0.272, tau_w_s=0.369, accel_max_mps2=0.844, yaw_accel_max_radps2=1.221, turn_efficiency=0.664,
        turn_loss_per_mps2=0.31, side_slip_s=0.079, noise_v_mps=0.0, noise_w_radps=0.0))
    cl = ClosedLoop([[0.0, 0.0], [11.5, 15.23], [-1.21, 22.9], [-8.66, 24.94]], preset=robot, seed=1,
                    teach_speed=0.96, loc=PoseSourceSettings(noise_m=0.01, delay_ticks=1))
    cl.teach()
    m = cl.identified()
    lag = ActuatorLag(m.tau_v_s, m.tau_w_s, 0.1, m.curvature_rate_max_per_ms, m.turn_gain)
    loss = TurnLoss(lag.turn_gain)
    asked = cl.repeat(1, 1.85, law=FLLaw(FLGains(), lag), lag=lag, turn_share=0.0)
    capped = cl.repeat(1, 1.85, law=FLLaw(FLGains(), lag), lag=lag, turn_loss=loss)
    assert asked.finished and capped.finished
    assert asked.max_lateral > 1.2 and capped.max_lateral < 0.4 * asked.max_lateral, (asked.max_lateral,
                                                                                       capped.max_lateral)
    # the loss it learned lies between none and the simulator's 0.31 on top of the teach pass's gain
    assert 0.05 < loss.per_mps2 < 0.31


def test_the_learned_loss_survives_a_restart_on_disk_and_a_stale_or_broken_file_is_learned_afresh(tmp_path, caplog):
    from services.controller import turn_loss_file
    loss = TurnLoss(0.555, sxx=40.0, sxy=4.8, samples=300)
    turn_loss_file.save(tmp_path, "unicycle-gw555", loss)
    back = turn_loss_file.load(tmp_path, "unicycle-gw555", 0.555)
    assert back == loss and back.per_mps2 == pytest.approx(0.12)
    assert turn_loss_file.load(tmp_path, "unicycle-other", 0.555).samples == 0          # none stored
    assert turn_loss_file.load(tmp_path, "unicycle-gw555", 0.7).samples == 0            # another turn gain
    turn_loss_file.file_of(tmp_path, "unicycle-gw555").write_bytes(b"\x93not a record")
    assert turn_loss_file.load(tmp_path, "unicycle-gw555", 0.555).samples == 0
    assert "learned afresh" in caplog.text

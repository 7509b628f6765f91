"""FL's lead (fl.py): eq. 3.5 taken at the errors the robot's turn leads to over the estimate's age and
the drive's settling time. Checked against numerical integration, the drive's own lag model, and in
closed loop on the simulator against eq. 3.5 as the thesis writes it."""
import math

import numpy as np
import pytest

from bench.closed_loop import ClosedLoop
from common.path import Path
from common.robot import robot_from_preset
from common.scenario import TerrainPatch
from services.controller.actuator import ActuatorLag
from services.controller.fl import FLGains, led_errors
from services.controller.laws import FLLaw, StepContext
from services.controller.turn_speed import TurnLoss
from services.localizer.pose_source import PoseSourceSettings


@pytest.mark.parametrize("e_L, e_H, delta, t", [(0.1, 0.2, 0.5, 0.8), (-0.3, -0.1, 0.0, 0.5), (0.0, 0.4, -1.2, 1.0)])
def test_led_errors_follow_the_arc_turned_relative_to_a_straight_route(e_L, e_H, delta, t):
    v, n = 1.5, 20000
    h = t / n
    y, th = e_L, e_H
    for _ in range(n):       # midpoint rule on e_L' = v sin e_H, e_H' = delta
        y += h * v * math.sin(th + 0.5 * h * delta)
        th += h * delta
    assert led_errors(v, e_L, e_H, delta, t) == pytest.approx((y, th), abs=1e-9)


@pytest.mark.parametrize("lag", [ActuatorLag(0.2, 0.17, 0.1, 0.284, 0.92), ActuatorLag(0.2, 0.4, 0.1, 0.5),
                                 ActuatorLag(0.2, 0.4, 0.1)])
@pytest.mark.parametrize("v, kappa0", [(0.8, 0.05), (1.6, 0.15), (1.6, 0.3)])
def test_the_settling_time_is_the_heading_the_drive_turns_on_while_it_comes_back(lag, v, kappa0):
    """From a turn of delta, commanded straight: the drive's lag model (actuator.py) turns the robot by
    delta times the settling time more (a rate-limited steering ramps, then lags)."""
    xi = (v, kappa0 if lag.rate_limited else kappa0 * v)
    delta, turned = lag.turn_rate(xi), 0.0
    for _ in range(200):
        (_, w), xi = lag.step(xi, (v, 0.0))
        turned += w * lag.dt
    assert delta * lag.turn_settling_s(delta, v) == pytest.approx(turned, rel=0.04)


def _mats_over_rough_ground(seed: int) -> tuple[float, float]:
    """Max lateral error without and with the lead: a perturbed MATS (slow steering: 0.28 /(m s)) at
    1.62 m/s across a rough patch that yaws it by up to 0.15 rad/s at 1 m/s (bench seed 6841, s547555188)."""
    robot = robot_from_preset("mats", dict(
        tau_v_s=0.896, tau_w_s=0.191, tau_steer_s=0.179, accel_max_mps2=0.674, yaw_accel_max_radps2=1.566,
        steer_rate_max_dps=30.89, turn_efficiency=0.936, side_slip_s=0.043, slope_slide_mps=0.128,
        slope_yaw_radps=0.293, understeer_s2pm2=0.037, noise_v_mps=0.0, noise_w_radps=0.0))
    terrain = [TerrainPatch(kind="rough", center=(49.05, -1.96), radius_m=7.363, amplitude=0.145)]
    cl = ClosedLoop([[0.0, 0.0], [70.0, 0.0]], terrain, preset=robot, seed=seed, teach_speed=0.78,
                    loc=PoseSourceSettings(noise_m=0.0, noise_heading_rad=0.0, delay_ticks=1))
    cl.teach()
    m = cl.identified()
    lag = ActuatorLag(m.tau_v_s, m.tau_w_s, 0.1, m.curvature_rate_max_per_ms, m.turn_gain)
    out = []
    for lead in (False, True):
        r = cl.repeat(1, 1.62, law=FLLaw(FLGains(lead=lead), lag), lag=lag)
        assert r.finished
        out.append(r.max_lateral)
    return out[0], out[1]


@pytest.mark.parametrize("seed", [1, 2])
def test_the_lead_stops_a_slow_steering_from_swinging_after_a_yaw_kick(seed):
    """Eq. 3.5 alone answers the kick with full lock, sees the heading it turns on while the steering
    comes back only once it is there, and swings: 0.99 / 1.32 m. With the lead: 0.64 / 0.71 m (the ground's
    yaw beyond the steering's reach at this speed is left)."""
    plain, led = _mats_over_rough_ground(seed)
    assert plain > 0.8 and led < 0.75 * plain, (plain, led)


def test_the_lead_costs_nothing_where_the_drive_keeps_up():
    """A Husky at 1 m/s round corners on estimates 0.1 s old: as close as eq. 3.5 alone (0.061 m)."""
    cl = ClosedLoop([[0, 0], [15, 0], [22, 7], [22, 20], [10, 26], [0, 20]], preset="husky", seed=4,
                    teach_speed=0.6, loc=PoseSourceSettings(noise_m=0.01, delay_ticks=1))
    cl.teach()
    m = cl.identified()
    lag = ActuatorLag(m.tau_v_s, m.tau_w_s, 0.1, m.curvature_rate_max_per_ms, m.turn_gain)
    plain, led = (cl.repeat(1, 1.0, law=FLLaw(FLGains(lead=lead), lag), lag=lag) for lead in (False, True))
    assert led.max_lateral < 1.1 * plain.max_lateral
    assert np.sqrt(np.mean(led.lateral_m ** 2)) < 1.05 * np.sqrt(np.mean(plain.lateral_m ** 2))


def _straight_then_arc(radius_m: float, straight_m: float = 10.0, arc_m: float = 10.0, step_m: float = 0.1) -> Path:
    poses = [(x, 0.0, 0.0) for x in np.arange(0.0, straight_m, step_m)]
    poses += [(straight_m + radius_m * math.sin(a), radius_m * (1.0 - math.cos(a)), a)
              for a in np.arange(0.0, arc_m, step_m) / radius_m]
    return Path("arc", np.array(poses), spacing_m=step_m)


def test_the_lead_asks_for_the_routes_turn_where_it_takes_the_robot():
    """Straight for 10 m, then a left arc of 5 m radius. The drive at 2 m/s and not turning, estimates
    0.2 s old, a 0.4 s turn lag: the lead is 0.6 s, 1.2 m. At 9.5 m, on the straight and on the route, the
    law asks for the arc's turn over the turn gain, 2 / 5 / 0.8 = 0.5 rad/s; 3 m before the arc for none,
    and eq. 3.5 as written for the turn of the place it is at (none)."""
    R, k, v = 5.0, 0.8, 2.0
    path = _straight_then_arc(R)
    lag = ActuatorLag(0.3, 0.4, 0.1, turn_gain=k)

    def at(s_m: float) -> StepContext:
        i = int(np.argmin(np.abs(path.s - s_m)))
        return StepContext(now_s=0.0, path=path, vertex=i, pose=path.poses[i], s_m=s_m, e_lat_m=0.0, e_head_rad=0.0,
                           v_mps=v, speed_at=lambda s: v, prev_cmd=(v, 0.0), prev_pose=None, w_limit=5.0,
                           w_limit_at=lambda u: 5.0, xi_capture=(v, 0.0), xi_now=(v, 0.0), loc_age_s=0.2)

    assert FLLaw(FLGains(), lag).angular(at(9.5)).w_radps == pytest.approx(v / R / k, rel=1e-3)
    assert FLLaw(FLGains(), lag).angular(at(7.0)).w_radps == pytest.approx(0.0, abs=1e-9)
    assert FLLaw(FLGains(lead=False), lag).angular(at(9.5)).w_radps == pytest.approx(0.0, abs=1e-9)


def test_the_lead_takes_a_lagging_grizzly_round_its_corners_on_the_route():
    """A perturbed Grizzly (bench seed 2207, s2098974819: a 0.45 s turn lag, turning at 0.49 of its
    drive's rate, estimates 0.2 s old) round the 3 m corners of a 77 m triangle at 1.36 m/s. Asked for each
    corner's turn only once there, FL went 0.44 m wide and overshot at each corner's end (RMS 0.20 m);
    asked for the turn where its lead takes it, 0.21 m (RMS 0.093 m)."""
    robot = robot_from_preset("grizzly", dict(
        tau_v_s=0.303, tau_w_s=0.457, accel_max_mps2=0.934, yaw_accel_max_radps2=1.892, turn_efficiency=0.607,
        turn_loss_per_mps2=0.39, side_slip_s=0.063, noise_v_mps=0.0, noise_w_radps=0.0))
    cl = ClosedLoop([[0.0, 0.0], [33.89, 17.94], [18.66, 29.85]], preset=robot, seed=1, teach_speed=0.99, loop=True,
                    loc=PoseSourceSettings(noise_m=0.0, noise_heading_rad=0.0, delay_ticks=2))
    cl.teach()
    m = cl.identified()
    lag = ActuatorLag(m.tau_v_s, m.tau_w_s, 0.1, m.curvature_rate_max_per_ms, m.turn_gain)
    r = cl.repeat(1, 1.36, law=FLLaw(FLGains(), lag), lag=lag, turn_loss=TurnLoss(lag.turn_gain))
    assert r.finished
    assert r.max_lateral < 0.3 and np.sqrt(np.mean(r.lateral_m ** 2)) < 0.13, r.max_lateral


def test_the_curvature_ahead_goes_round_a_loop_and_holds_at_an_open_routes_end():
    """Path.curvature_at, which the lead reads ahead with: past a loop's end it is the curvature as far
    into the loop (a corner's, where the loop ends on a straight); past an open route's end, the last
    vertex's."""
    from services.bridge.teach_driver import smooth_waypoints
    loop = Path("o", smooth_waypoints([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]], 3.0, True), loop=True)
    corner = float(loop.s[int(np.argmax(np.abs(loop.curvature)))])
    assert abs(loop.curvature_at(corner)) > 0.2 and abs(loop.curvature[-1]) < 0.05
    assert loop.curvature_at(loop.length_m + corner) == pytest.approx(loop.curvature_at(corner))
    path = _straight_then_arc(5.0)
    assert path.curvature_at(path.length_m + 3.0) == pytest.approx(float(path.curvature[-1]))

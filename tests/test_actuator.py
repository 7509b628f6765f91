"""The drive-lag model (actuator.py) against a finely integrated continuous first-order lag, and the
experiences it changes."""
import math

import numpy as np
import pytest

from common.path import Path
from services.controller.actuator import ActuatorLag
from services.controller.experience import ExperienceBuilder

DT = 0.1


def continuous_lag(tau: float, xi0: float, u: np.ndarray, substeps: int = 20000):
    """xi' = (u - xi) / tau under a held command per period, by small exact-exponential substeps; returns
    the mean of xi over each period and xi at its end."""
    h = DT / substeps
    decay = math.exp(-h / tau)
    means, xi = [], xi0
    for uk in u:
        acc = 0.0
        for _ in range(substeps):
            nxt = uk + (xi - uk) * decay
            acc += 0.5 * (xi + nxt) * h
            xi = nxt
        means.append(acc / DT)
    return np.array(means), xi


def test_period_averages_match_a_continuous_first_order_lag():
    rng = np.random.default_rng(0)
    lag = ActuatorLag(0.45, 0.4, DT)
    K = 8
    u_v, u_w = rng.uniform(0, 2, K), rng.uniform(-1, 1, K)
    Lv, cv, Lw, cw = lag.matrices(K)
    for L, c, tau, u, xi0 in ((Lv, cv, 0.45, u_v, 0.7), (Lw, cw, 0.4, u_w, -0.3)):
        ref, _ = continuous_lag(tau, xi0, u)
        np.testing.assert_allclose(L @ u + c * xi0, ref, atol=1e-6)
    # step() agrees with the matrices period by period
    xi = (0.7, -0.3)
    for k in range(K):
        avg, xi = lag.step(xi, (u_v[k], u_w[k]))
        assert avg[0] == pytest.approx((Lv @ u_v + cv * 0.7)[k]) and avg[1] == pytest.approx((Lw @ u_w + cw * -0.3)[k])
    ref_end = continuous_lag(0.45, 0.7, u_v)[1]
    assert xi[0] == pytest.approx(ref_end, abs=1e-6)


def test_no_lag_is_the_unicycle_and_history_replays_the_commands():
    lag0 = ActuatorLag(0.0, 0.0, DT)
    assert not lag0.active
    assert lag0.step((0.3, 0.1), (1.0, -0.5)) == ((1.0, -0.5), (1.0, -0.5))
    Lv, cv, _, _ = lag0.matrices(5)
    np.testing.assert_array_equal(Lv, np.eye(5))
    np.testing.assert_array_equal(cv, 0.0)
    lag = ActuatorLag(0.45, 0.4, DT)
    history = {t: (1.5, 0.2) for t in range(100, 140)}
    xi = lag.state_before(140, history.get)
    assert xi[0] == pytest.approx(1.5, abs=1e-3) and xi[1] == pytest.approx(0.2, abs=1e-3)   # settled
    assert lag.state_before(100, history.get) == (0.0, 0.0)                                   # at rest before
    one = lag.state_before(101, history.get)
    assert one[0] == pytest.approx(1.5 * (1 - math.exp(-DT / 0.45)))


def test_experiences_of_a_robot_that_lags_exactly_as_modelled_are_zero():
    route = Path("r", np.column_stack([np.arange(0, 20, 0.25), np.zeros(80), np.zeros(80)]))
    lag = ActuatorLag(0.45, 0.4, DT)
    builder, plain = ExperienceBuilder(route, DT, lag=lag), ExperienceBuilder(route, DT)
    pose, xi = np.array([1.0, 0.05, 0.02]), (0.0, 0.0)
    out, out_plain = [], []
    for k in range(30):
        u = (0.8, 0.3 * math.sin(0.3 * k))
        vertex = route.nearest_vertex(pose)
        T = np.array([pose[0] - route.poses[vertex, 0], pose[1], pose[2]])
        for b, o in ((builder, out), (plain, out_plain)):
            obs = b.add_estimate(k, k * DT, vertex, T)
            if obs is not None:
                o.append(obs)
            b.add_command(k, *u)
        (vb, wb), xi = lag.step(xi, u)
        pose = pose + DT * np.array([vb * math.cos(pose[2]), vb * math.sin(pose[2]), wb])
    assert len(out) == 28
    for o in out:
        np.testing.assert_allclose(o.g, 0.0, atol=1e-12)
    # the plain unicycle would have learned the lag as a disturbance: the robot falls behind its command
    assert out_plain[0].g[0] < -0.02


def test_a_skipped_tick_holds_the_command_before_it():
    lag = ActuatorLag(0.45, 0.4, DT)
    steady = {t: (1.5, 0.2) for t in range(100, 140)}
    gap = dict(steady)
    del gap[137]                     # a realtime loop that missed a tick: the drive kept the last command
    assert lag.state_before(140, gap.get) == pytest.approx(lag.state_before(140, steady.get))


def test_nmpc_settings_still_validate_everything():
    from services.controller.settings import NMPCSettings
    for bad in (dict(actuator_tau_s=(-0.1, 0.0)), dict(actuator_tau_s=(0.1,)), dict(horizon=0),
                dict(r_w=0.0, r_dw=0.0), dict(min_band_fraction=1.0)):
        with pytest.raises(ValueError):
            NMPCSettings(**bad)
    assert NMPCSettings(actuator_tau_s=[0.45, 0.4]).lag(DT) == ActuatorLag(0.45, 0.4, DT)


def _ackermann_turn_rates(v_cmd: np.ndarray, w_cmd: np.ndarray, v0: float, substeps: int = 50) -> np.ndarray:
    """The simulator's MATS (services/bridge/vehicle.py: steering lagged and rate limited, eq. 5.27),
    noise-free, from speed v0 driving straight: the turn rate's mean over each period of the commands."""
    from dataclasses import replace

    from common.robot import PRESETS
    from services.bridge.terrain import TerrainEffect
    from services.bridge.vehicle import Vehicle
    p = replace(PRESETS["mats"], noise_v_mps=0.0, noise_w_radps=0.0)
    car = Vehicle(p)
    car.s.v_act = v0
    rng, h, means = np.random.default_rng(0), DT / substeps, []
    for v, w in zip(v_cmd, w_cmd):
        acc = 0.0
        for _ in range(substeps):
            car.step(h, float(v), float(w), False, TerrainEffect(), rng)
            acc += car.s.w_act
        means.append(acc / substeps)
    return np.array(means)


def _model_turn_rates(lag: ActuatorLag, v_cmd, w_cmd, v0: float) -> np.ndarray:
    xi, out = (v0, 0.0), []
    for u in zip(v_cmd, w_cmd):
        avg, xi = lag.step(xi, u)
        out.append(avg[1])
    return np.array(out)


def test_the_steering_rate_limit_follows_an_ackermann_robot_where_the_turn_rate_lag_does_not():
    """Against the simulated MATS: turn-rate swings at 2 m/s, where the steering rate (40 deg/s) holds the
    turn rate to ~0.7 rad/s^2, which the plain 0.15 s lag does not know; and braking from 2 to 0.3 m/s
    in a turn, where the turn rate falls with the speed at a held steering angle."""
    from common.robot import PRESETS
    p = PRESETS["mats"]
    K = 40
    swings = (np.full(K, 2.0), np.where((np.arange(K) // 10) % 2 == 0, 0.5, -0.5))
    kappa = np.where(np.arange(K) < 5, 0.0, 0.1)
    v_brake = np.where(np.arange(K) < 15, 2.0, 0.3)
    braking = (v_brake, v_brake * kappa)
    plain = ActuatorLag(p.tau_v_s, p.tau_steer_s, DT)
    limited = ActuatorLag(p.tau_v_s, p.tau_steer_s, DT, p.max_curvature_rate)
    for v_cmd, w_cmd in (swings, braking):
        truth = _ackermann_turn_rates(v_cmd, w_cmd, 2.0)
        err_plain = np.abs(_model_turn_rates(plain, v_cmd, w_cmd, 2.0) - truth)
        err = np.abs(_model_turn_rates(limited, v_cmd, w_cmd, 2.0) - truth)
        assert err.max() < 0.1 and np.sqrt(np.mean(err ** 2)) < 0.04, err
        assert np.sqrt(np.mean(err ** 2)) < 0.5 * np.sqrt(np.mean(err_plain ** 2))
        # the horizon's form is the same model
        v_avg = plain.matrices(K)[0] @ v_cmd + plain.matrices(K)[1] * 2.0
        wb = limited.turn_rates(w_cmd, v_cmd, v_avg, 0.0)[0]
        np.testing.assert_allclose(wb, _model_turn_rates(limited, v_cmd, w_cmd, 2.0), atol=1e-12)


def test_the_steering_rate_limit_jacobians_match_finite_differences_and_it_is_the_lag_below_the_limit():
    lag = ActuatorLag(0.3, 0.15, DT, 0.37)
    rng = np.random.default_rng(3)
    K = 12
    w, v, vb = rng.uniform(-0.6, 0.6, K), rng.uniform(0.5, 2.0, K), rng.uniform(0.5, 2.0, K)
    wb, Lw, Lv, kb = lag.turn_rates(w, v, vb, 0.1)
    np.testing.assert_allclose(wb, vb * kb)
    eps = 1e-6
    for arg, jac in ((0, Lw), (1, Lv)):
        num = np.empty((K, K))
        for i in range(K):
            d = np.zeros(K)
            d[i] = eps
            plus, minus = [w, v], [w, v]
            plus[arg], minus[arg] = plus[arg] + d, minus[arg] - d
            num[:, i] = (lag.turn_rates(*plus, vb, 0.1)[0] - lag.turn_rates(*minus, vb, 0.1)[0]) / (2 * eps)
        np.testing.assert_allclose(jac, num, atol=1e-6)
        assert np.all(np.triu(jac, 1) == 0.0)
    # small curvature changes: the plain lag on the curvature within 0.3 %
    v2 = np.full(K, 2.0)
    small = 2.0 * 0.02 * np.sin(np.arange(K))
    _, _, Lk, _ = lag.matrices(K)
    np.testing.assert_allclose(lag.turn_rates(small, v2, v2, 0.0)[0], Lk @ small, rtol=3e-3, atol=1e-9)
    assert "-kr370m" in lag.model_tag and "kr" not in ActuatorLag(0.3, 0.15, DT).model_tag
    assert lag.settled((2.0, 0.5)) == (2.0, 0.25) and ActuatorLag(0.3, 0.15, DT).settled((2.0, 0.5)) == (2.0, 0.5)


@pytest.mark.parametrize("rate", [0.0, 0.37])
def test_a_turn_gain_scales_the_robots_turn_rate_not_the_drives(rate):
    """The robot turns at turn_gain times its drive's turn rate: step(), the matrices and the rate-limited
    turn rates (with their Jacobians) all scale by it; the drive's state xi does not (the odometry's)."""
    K, g = 8, 0.62
    rng = np.random.default_rng(5)
    w, v = rng.uniform(-0.6, 0.6, K), rng.uniform(0.5, 2.0, K)
    plain, gained = ActuatorLag(0.3, 0.2, DT, rate), ActuatorLag(0.3, 0.2, DT, rate, g)
    xi_p, xi_g = (1.0, 0.2), (1.0, 0.2)
    for k in range(K):
        (ap, xi_p), (ag, xi_g) = plain.step(xi_p, (v[k], w[k])), gained.step(xi_g, (v[k], w[k]))
        assert ag[0] == ap[0] and ag[1] == pytest.approx(g * ap[1]) and xi_g == xi_p
    if rate:
        vb = plain.matrices(K)[0] @ v
        out_p, out_g = plain.turn_rates(w, v, vb, 0.1), gained.turn_rates(w, v, vb, 0.1)
        for a, b in zip(out_p, out_g):
            np.testing.assert_allclose(b, g * a)
    else:
        for a, b, scale in zip(plain.matrices(K), gained.matrices(K), (1.0, 1.0, g, g)):
            np.testing.assert_allclose(b, scale * a)
    assert gained.command_for(0.31) == pytest.approx(0.5) and gained.active and ActuatorLag(dt=DT, turn_gain=g).active
    assert gained.model_tag == plain.model_tag + "-gw620"
    with pytest.raises(ValueError):
        ActuatorLag(turn_gain=0.1)

"""The learned disturbance model on real recorded driving: fit on one run, predict a repeat of the route.

Data: F1/10 FrictionMaps logs, MIT license (a 1/10-scale Ackermann car, remotely driven; runs DS3
and DS4 drive the same ~170 m route). Read in place from ../shared/data/f1tenth_friction (relative to
the project root), never copied into the project; see that folder's SOURCE_README.md.

What is tested (thesis 5.2.1, eq. 5.14-5.17; 5.3.1, eq. 5.26; 5.4.5, eq. 5.27): one-step residuals
g_k = x_{k+1} - f(x_k, u_k) of the nominal unicycle (eq. 5.26) on DS3 are fitted with the project's
GP (`common.gp`), which then predicts DS4's residuals from DS4's own inputs. The learned model must
cut the RMSE of the heading-rate residual (g_k[2] / dt) by at least 30 % against the nominal model
alone (which predicts zero residual).

Processing and assumptions:
- Times are s + 1e-9 ns. Poses are the particle-filter poses (x, y, yaw from the quaternion); they
  and the commands are put on a common 10 Hz grid (dt = 0.1 s, the controller's period) over the
  span where the commanded speed exceeds 0.1 m/s. Poses are linearly interpolated (yaw unwrapped);
  commands are a zero-order hold of the most recent command at each grid time.
- The logs command speed V and steering angle delta. The commanded unicycle rate is the inverse of
  eq. 5.27 (`common.robot.steering_from_unicycle`): w_cmd = V tan(delta) / L, with L = 0.325 m, the
  usual F1/10 wheelbase -- an assumption, the logs do not state it.
- Inputs a_k = (v_act_{k-1}, w_act_{k-1}, v_cmd_k, w_cmd_k, v_cmd_{k-1}, w_cmd_{k-1}): the velocity
  and input part of eq. 5.15. There is no taught route here, so the route-relative pose part of
  a_k (s, e_L, e_H in `services.controller.experience`) is left out.
- No latency compensation: commands and poses are paired on their recorded stamps as they are.
"""
from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import pytest

from common.shared_data import shared_data_dir
from common.gp import GaussianProcess, fit_hyperparameters
from common.robot import steering_from_unicycle
from services.controller.experience import body_residual, body_velocity

DATA = shared_data_dir() / "f1tenth_friction"
DT = 0.1                 # s, controller period
WHEELBASE_M = 0.325      # assumed F1/10 wheelbase (L of eq. 5.27)
MOVING_V = 0.1           # m/s, commanded speed above which the car counts as driving


def _csv(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(time s + 1e-9 ns, the data columns after the index, s and ns)."""
    raw = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    return raw[:, 1] + 1e-9 * raw[:, 2], raw[:, 3:]


def _w_from_steering(v: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """Inverse of eq. 5.27 (delta = atan(L w / v)): w = v tan(delta) / L."""
    return v * np.tan(delta) / WHEELBASE_M


def load_run(name: str) -> dict:
    """One run on the 10 Hz grid: poses (N, 3), commands (N, 2), inputs a (N-2, 6), residuals g (N-2, 3)."""
    t_cmd, cmd = _csv(DATA / name / "commandData.csv")          # V [m/s], delta [rad]
    t_pose, pf = _csv(DATA / name / "pfPoseData.csv")          # x, y, qx, qy, qz, qw
    t0 = math.floor(t_pose[0])
    t_cmd, t_pose = t_cmd - t0, t_pose - t0
    qx, qy, qz, qw = pf[:, 2], pf[:, 3], pf[:, 4], pf[:, 5]
    yaw = np.unwrap(np.arctan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz)))

    moving = t_cmd[cmd[:, 0] > MOVING_V]
    t = np.arange(max(moving[0], t_pose[0]), min(moving[-1], t_pose[-1]), DT)
    pose = np.column_stack([np.interp(t, t_pose, pf[:, 0]), np.interp(t, t_pose, pf[:, 1]),
                            np.interp(t, t_pose, yaw)])
    last = np.searchsorted(t_cmd, t, side="right") - 1           # zero-order hold
    v_cmd = cmd[last, 0]
    w_cmd = _w_from_steering(v_cmd, cmd[last, 1])

    a, g = [], []
    for k in range(1, len(t) - 1):
        v_act, w_act = body_velocity(pose[k - 1], pose[k], DT)
        a.append((v_act, w_act, v_cmd[k], w_cmd[k], v_cmd[k - 1], w_cmd[k - 1]))
        g.append(body_residual(pose[k], v_cmd[k], w_cmd[k], pose[k + 1], DT))
    travel = float(np.sum(np.hypot(np.diff(pose[:, 0]), np.diff(pose[:, 1]))))
    return {"pose": pose, "a": np.array(a), "g": np.array(g), "travel_m": travel}


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


def test_inverse_steering_matches_eq_5_27():
    v, w = 1.3, 0.7
    delta = steering_from_unicycle(v, w, WHEELBASE_M)
    assert _w_from_steering(np.array(v), np.array(delta)) == pytest.approx(w)


@pytest.mark.slow
def test_gp_learned_on_ds3_cuts_heading_rate_residual_on_ds4():
    if not (DATA / "DS3").is_dir() or not (DATA / "DS4").is_dir():
        pytest.skip(f"real F1/10 data not found at {DATA}")
    t_start = time.perf_counter()
    train, test = load_run("DS3"), load_run("DS4")

    for name, run in (("DS3", train), ("DS4", test)):
        assert run["travel_m"] > 100.0, f"{name}: only {run['travel_m']:.0f} m of travel"
        assert len(run["a"]) > 500, f"{name}: only {len(run['a'])} samples"
        assert np.all(np.isfinite(run["a"])) and np.all(np.isfinite(run["g"])), name
    # same route, same frame: DS4's path stays close to DS3's (the README states a median ~0.2 m)
    d = np.hypot(test["pose"][:, None, 0] - train["pose"][None, :, 0],
                 test["pose"][:, None, 1] - train["pose"][None, :, 1]).min(axis=1)
    assert np.median(d) < 0.5

    # heading dimension of g (eq. 5.17); an independent GP per output (eq. 5.21) makes fitting it
    # alone the same model as fitting all three and reading the third
    y_train = train["g"][:, 2:3]
    fit = fit_hyperparameters(train["a"], y_train, restarts=2, rng=np.random.default_rng(0), max_points=1000)
    gp = GaussianProcess(train["a"], y_train, fit.hypers)
    mean, _ = gp.predict(test["a"])

    hr = test["g"][:, 2] / DT                     # heading-rate residual of the nominal model, rad/s
    rmse_nominal = _rms(hr)
    rmse_learned = _rms(hr - mean[:, 0] / DT)
    cut = 1.0 - rmse_learned / rmse_nominal
    msg = (f"DS4 heading-rate residual RMSE: nominal {rmse_nominal:.3f} rad/s, learned {rmse_learned:.3f} "
           f"rad/s, cut {100 * cut:.1f}% (n_train={len(train['a'])}, n_test={len(test['a'])}, "
           f"{time.perf_counter() - t_start:.1f} s; {fit.hypers[0]})")
    print(msg)
    assert rmse_learned <= 0.7 * rmse_nominal, msg

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
The loaders and the residuals live in deploy/robot_logs.py, the fit in deploy/fit_logs.py (`lbc model
fit-logs`), which this test runs as a user would.
"""
from __future__ import annotations

import io
import json
from contextlib import redirect_stdout

import numpy as np
import pytest

from common.robot import steering_from_unicycle
from common.shared_data import shared_data_dir
from deploy import fit_logs
from deploy.robot_logs import F1TENTH_WHEELBASE_M, load_f1tenth_csv, residuals, unicycle_rate

DATA = shared_data_dir() / "f1tenth_friction"
DT = 0.1                 # s, controller period


def test_inverse_steering_matches_eq_5_27():
    v, w = 1.3, 0.7
    delta = steering_from_unicycle(v, w, F1TENTH_WHEELBASE_M)
    assert unicycle_rate(v, delta, F1TENTH_WHEELBASE_M) == pytest.approx(w)


@pytest.mark.slow
def test_gp_learned_on_ds3_cuts_heading_rate_residual_on_ds4():
    if not (DATA / "DS3").is_dir() or not (DATA / "DS4").is_dir():
        pytest.skip(f"real F1/10 data not found at {DATA}")
    train, test = load_f1tenth_csv(DATA / "DS3", DT), load_f1tenth_csv(DATA / "DS4", DT)
    for run in (train, test):
        a, g = residuals(run)
        assert run.travel_m > 100.0, f"{run.name}: only {run.travel_m:.0f} m of travel"
        assert len(a) > 500, f"{run.name}: only {len(a)} samples"
        assert np.all(np.isfinite(a)) and np.all(np.isfinite(g)), run.name
    # same route, same frame: DS4's path stays close to DS3's (the README states a median ~0.2 m)
    d = np.hypot(test.pose[:, None, 0] - train.pose[None, :, 0], test.pose[:, None, 1] - train.pose[None, :, 1]).min(axis=1)
    assert np.median(d) < 0.5

    # the figure through the command a user runs (README): lbc model fit-logs DS3 --test DS4 --nominal unicycle
    out = io.StringIO()
    with redirect_stdout(out):
        assert fit_logs.main([str(DATA / "DS3"), "--test", str(DATA / "DS4"), "--nominal", "unicycle"]) == 0
    result = json.loads(out.getvalue().strip().splitlines()[-1])
    print(result)
    assert result["n_train"] > 1000 and result["n_test"] > 1000
    assert result["heading_rate_rmse_gp"] <= 0.7 * result["heading_rate_rmse_nominal"], result
    assert result["identified"]["lag_w_s"] > 0.0     # identified on the logs even where not used

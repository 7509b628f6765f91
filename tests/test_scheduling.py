"""Speed scheduling through the real services (router, bridge, localizer, controller, store, scheduler
as processes): the thesis 4.3 experiment as shipped in examples/, and the scheduler together with
LB-NMPC (thesis 5.4.4), shortened for CI."""
from __future__ import annotations

import json
import math
import os
import pathlib

import numpy as np
import pytest

from common.scenario import load_scenario
from deploy.experiment import run_experiment

pytestmark = pytest.mark.integration
EXAMPLES = pathlib.Path(__file__).resolve().parents[1] / "examples"


def run(out: pathlib.Path, scenario: pathlib.Path) -> list[dict]:
    run_experiment(scenario, out, progress_stream=open(os.devnull, "w"))
    return json.loads((out / "summary.json").read_text())["trials"]


@pytest.mark.slow
def test_thesis_4_3_mats_cuts_travel_time_by_40_percent_within_the_limits(tmp_path):
    """~100 m, 10 trials, v_init 0.5, v_max 2.0; lateral < 0.15 m, heading < 10 deg, |w| < 1 rad/s."""
    sc = load_scenario(EXAMPLES / "sched-mats.toml")
    p = sc.scheduler
    assert (sc.robot.preset, sc.trials.count, p.v_init, p.v_max) == ("mats", 10, 0.5, 2.0)
    assert (p.lambda_L, p.lambda_H, p.lambda_omega, p.lambda_feat, p.lambda_db) == (0.15, 10.0, 1.0, 30, 1.1)
    trials = run(tmp_path / "sched", EXAMPLES / "sched-mats.toml")
    assert len(trials) == 10 and all(t["completed"] for t in trials)
    assert 90 <= trials[0]["route_length_m"] <= 110
    travel = [t["travel_time_s"] for t in trials]
    assert travel[-1] <= 0.6 * travel[0], travel
    # no trial beyond the limits by more than the deadband (errors from simulator truth)
    db = p.lambda_db
    for t in trials:
        assert t["max_lateral_m"] <= p.lambda_L * db, (t["trial"], t["max_lateral_m"])
        assert math.degrees(t["max_heading_rad"]) <= p.lambda_H * db, (t["trial"], t["max_heading_rad"])
        assert t["max_w_cmd_radps"] <= p.lambda_omega * db, (t["trial"], t["max_w_cmd_radps"])
    # trial 1 at v_init; the schedule then rises towards v_max
    assert trials[0]["scheduled_speed_max_mps"] == pytest.approx(0.5)
    assert trials[-1]["scheduled_speed_max_mps"] >= 1.8
    versions = [t["schedule_version"] for t in trials]
    assert versions == sorted(versions) and len(set(versions)) == 10


@pytest.mark.slow
def test_scheduler_with_lb_nmpc_rises_speeds_and_lowers_errors(tmp_path):
    """Thesis 5.4.4 (roc6, 60 m loop): speeds rise from 0.35 m/s while the learned model brings the
    errors below trial 1's, which ran at a third of the speed without experience."""
    src = (EXAMPLES / "lbnmpc-roc6-sched.toml").read_text()
    assert "count = 20" in src
    short = tmp_path / "roc6.toml"
    short.write_text(src.replace("count = 20", "count = 7"))
    trials = run(tmp_path / "roc6", short)
    assert all(t["completed"] for t in trials)
    speeds = [t["scheduled_speed_mean_mps"] for t in trials]
    assert speeds[0] == pytest.approx(0.35, abs=0.01) and speeds[-1] >= 0.8, speeds
    assert np.all(np.diff(speeds) >= -1e-9), speeds
    lat = [t["max_lateral_m"] for t in trials]
    assert max(lat[-3:]) <= 0.8 * lat[0], lat
    assert trials[-1]["heading_rate_residual_rmse_learned_radps"] < 0.6 * trials[-1][
        "heading_rate_residual_rmse_nominal_radps"]
    assert trials[-1]["travel_time_s"] <= 0.5 * trials[0]["travel_time_s"]

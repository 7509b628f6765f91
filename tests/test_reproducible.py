"""One seed, one run: with the lockstep clock, two runs of a learning scenario give the same summary.json
except for the wall-clock values (deploy/reproducible.py); and the helpers that compare them."""
from __future__ import annotations

import io
import json

import pytest

from deploy.experiment import run_experiment
from deploy.reproducible import TRIAL_WALL_CLOCK_KEYS, differences, reproducible_part

# RC-LB-NMPC across a sandy side slope, as the main job but on a ~20 m route and three trials: trial 1 has
# no model, trials 2 and 3 predict from the GP fitted on the trials before, with eviction under way
SIDESLOPE = {
    "name": "repro", "seed": 3, "robot": {"preset": "husky"},
    "path": {"waypoints": [[0, 0], [7, 0], [13, 4], [19, 4]], "teach_speed_mps": 0.5},
    "terrain": [{"kind": "side_slope", "center": [10.0, 2.0], "radius_m": 4.0, "slope_deg": 12.0,
                 "downhill_deg": 90.0},
                {"kind": "slip", "center": [10.0, 2.0], "radius_m": 3.0, "traction": 0.7}],
    "localization": {"source": "pose", "noise_m": 0.01, "delay_s": 0.1},
    "controller": {"algorithm": "rc-lb-nmpc", "nmpc": {"crab_reference": True}},
    "constraints": {"lateral_m": 0.25, "heading_deg": 15.0},
    "trials": {"count": 3, "speed": 1.0},
}


@pytest.mark.integration
@pytest.mark.slow
def test_two_lockstep_runs_of_one_seed_give_the_same_summary(tmp_path, scenario_file):
    path = scenario_file(SIDESLOPE)
    first = run_experiment(path, tmp_path / "a", progress_stream=io.StringIO())
    second = run_experiment(path, tmp_path / "b", progress_stream=io.StringIO())
    trials = first["trials"]
    # it learned: every trial completed and was followed by a fit, so trials 2 and 3 drove on a model
    assert len(trials) == 3 and all(t["completed"] for t in trials), trials
    assert all(t["experiences_fit_retained"] for t in trials), trials
    on_disk = [json.loads((tmp_path / d / "summary.json").read_text()) for d in ("a", "b")]
    diff = differences(reproducible_part(on_disk[0]), reproducible_part(on_disk[1]))
    assert not diff, "\n".join(diff)
    assert on_disk[0] == json.loads(json.dumps(first)) and on_disk[1] == json.loads(json.dumps(second))


def test_the_comparison_leaves_out_exactly_the_wall_clock_values():
    trial = {"trial": 1, "max_lateral_m": 0.1, "control_steps": 200, "solve_ms_p50": 3.0, "solve_ms_p99": 7.0,
             "wall_time_s": 2.0}
    a = {"scenario": "s", "identified_model": {"stamp_s": 1.0, "tau_v_s": 0.2}, "trials": [trial]}
    b = {"scenario": "s", "identified_model": {"stamp_s": 2.0, "tau_v_s": 0.2},
         "trials": [dict(trial, solve_ms_p50=4.0, solve_ms_p99=9.0, wall_time_s=3.0)]}
    assert differences(reproducible_part(a), reproducible_part(b)) == []
    assert {"solve_ms_p50", "solve_ms_p99", "wall_time_s"} <= TRIAL_WALL_CLOCK_KEYS
    assert "control_steps" not in TRIAL_WALL_CLOCK_KEYS and "max_lateral_m" not in TRIAL_WALL_CLOCK_KEYS
    # anything else that differs is named by its path
    c = dict(b, identified_model={"stamp_s": 2.0, "tau_v_s": 0.3}, trials=[dict(trial, control_steps=201)])
    assert differences(reproducible_part(a), reproducible_part(c)) == [
        ".identified_model.tau_v_s: 0.2 != 0.3", ".trials[0].control_steps: 200 != 201"]
    assert differences({"trials": [1]}, {"trials": [1, 2]}) == [".trials: 1 != 2 entries"]
    assert differences({"x": 1}, {"y": 1}) == [".x: only in the first", ".y: only in the second"]
    # the input is not changed
    assert a["trials"][0]["wall_time_s"] == 2.0 and a["identified_model"]["stamp_s"] == 1.0

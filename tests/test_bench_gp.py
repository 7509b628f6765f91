"""`lbc bench gp`: one JSON line with the project's and scikit-learn's fits on simulated disturbances."""
import json
import math

import numpy as np
import pytest

from bench import gp as bench_gp

pytest.importorskip("sklearn")


@pytest.mark.slow
def test_bench_gp_reports_a_fit_within_2_percent_of_sklearn(capsys):
    assert bench_gp.main(["--n", "300", "--restarts", "1"]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    res = json.loads(out[-1])
    for key in ("n", "fit_s", "lml", "sklearn_fit_s", "sklearn_lml", "n_used", "restarts", "lml_gap_pct",
                "eval_n"):
        assert key in res, key
    assert res["n"] == 300 and res["n_used"] == 300 and res["eval_n"] == 300 and res["restarts"] == 1
    for key in ("fit_s", "lml", "sklearn_fit_s", "sklearn_lml", "lml_gap_pct"):
        assert isinstance(res[key], (int, float)) and math.isfinite(res[key]), key
    assert res["fit_s"] > 0 and res["sklearn_fit_s"] > 0
    assert res["lml"] >= res["sklearn_lml"] - 0.02 * abs(res["sklearn_lml"])
    assert res["lml_gap_pct"] == pytest.approx(
        100.0 * (res["sklearn_lml"] - res["lml"]) / abs(res["sklearn_lml"]), rel=1e-9, abs=1e-12)


def test_disturbance_observations_follow_eq_5_17():
    """Small, direct check of the generator: 9 inputs, 3 body-frame residuals of the right size."""
    obs = bench_gp.generate(200, seed=3, speeds=(0.5, 1.0))
    A, G = obs.A, obs.G
    assert A.shape == (200, 9) and G.shape == (200, 3)
    assert np.all(np.isfinite(A)) and np.all(np.isfinite(G))
    # commanded speeds are the trial speeds, the gentle stop at the end, or 0 while rolling to a halt
    assert A[:, 5].max() <= 1.0 + 1e-9 and A[:, 5].min() >= 0.0
    # the robot stays near the route: small lateral errors
    assert np.abs(A[:, 1]).max() < 0.5
    # one-step residuals are centimetres, not metres (dt = 0.1 s)
    assert np.abs(G[:, :2]).max() < 0.1 and np.abs(G[:, 2]).max() < 0.2
    assert obs.trials >= 2 and obs.pool >= 200 and obs.tiles.shape == (200,)

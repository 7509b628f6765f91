"""`lbc bench controller` runs end to end and reports the DESIGN.md keys (the IPOPT comparison only
when the optional casadi is installed)."""
import json
import math

import pytest

from bench import controller

pytestmark = pytest.mark.integration


@pytest.mark.slow
def test_bench_controller_reports_the_design_keys(capsys):
    assert controller.main(["--keep-every", "300"]) == 0
    res = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    for key in ("algorithm", "horizon", "window", "solve_ms_p50", "solve_ms_p99", "casadi_solve_ms_p50", "cost_gap"):
        assert key in res
    assert res["algorithm"] == "lb-nmpc" and res["horizon"] == 10
    assert res["window"] > 150 and res["window_max"] <= 180
    assert 0 < res["solve_ms_p50"] <= res["solve_ms_p99"] and math.isfinite(res["solve_ms_p99"])
    try:
        import casadi  # noqa: F401
    except ImportError:
        assert res["casadi_solve_ms_p50"] is None and res["cost_gap"] is None
    else:   # the same optimum as IPOPT (relative cost difference), found much faster
        assert abs(res["cost_gap"]) < 1e-4 and res["casadi_solve_ms_p50"] > res["solve_ms_p50"]

"""Iterative Learning Control (thesis 3.2.2-3.2.3): the update law worked by hand, persistence, and
learning in closed loop with the simulated robot."""
import math

import numpy as np
import pytest

from bench.closed_loop import ClosedLoop
from common.scenario import TerrainPatch
from services.controller.fl import FLGains
from services.controller.ilc import ILCGains, ILCLaw, ILCMemory
from services.localizer.pose_source import PoseSourceSettings


def test_update_is_eq_3_14_with_the_lookahead_of_eq_3_15():
    mem = ILCMemory("r", 6, w_ff=np.array([0.1, 0.0, 0.0, 0.0, 0.0, -0.2]))
    # two samples at vertex 1 (mean 0.2 m, 0.1 rad), one each at 2 and 3; vertices 0, 4, 5 unseen
    for v, el, eh in [(1, 0.1, 0.0), (1, 0.3, 0.2), (2, -0.1, 0.0), (3, 0.4, -0.1)]:
        mem.record(v, el, eh)
    g = ILCGains(gamma_L=0.5, gamma_H=0.2, gamma_u=0.9, lookahead=2)
    mem.update(g)

    def law(eps_l, eps_h):
        return (-g.gamma_L * eps_l - g.gamma_H * math.sin(eps_h)) / math.cos(eps_h)
    expected = 0.9 * np.array([0.1, 0.0, 0.0, 0.0, 0.0, -0.2])
    expected[0] += law((0.2 - 0.1) / 2, (0.1 + 0.0) / 2)    # vertices 1, 2
    expected[1] += law((-0.1 + 0.4) / 2, (0.0 - 0.1) / 2)   # vertices 2, 3
    expected[2] += law(0.4, -0.1)                           # vertex 3 (4 was not seen)
    # vertices 3, 4, 5 look ahead at nothing seen: only forgetting
    np.testing.assert_allclose(mem.w_ff, expected, atol=1e-12)
    assert mem.trials == 1
    mem.update(g)   # the record was consumed: a second update only forgets
    np.testing.assert_allclose(mem.w_ff, 0.9 * expected, atol=1e-12)


def test_feedforward_is_saved_per_route_and_checked_on_load(tmp_path):
    mem = ILCMemory("route_a", 4, w_ff=np.array([0.1, -0.2, 0.3, 0.0]), trials=3)
    path = mem.save(tmp_path)
    back = ILCMemory.load(tmp_path, "route_a", 4)
    np.testing.assert_array_equal(back.w_ff, mem.w_ff)
    assert back.trials == 3
    assert ILCMemory.load(tmp_path, "route_b", 7).w_ff.tolist() == [0.0] * 7   # nothing learned yet
    with pytest.raises(ValueError, match="holds 4 vertices"):
        ILCMemory.load(tmp_path, "route_a", 5)
    path.write_bytes(b"\x00garbage")
    with pytest.raises(ValueError):
        ILCMemory.load(tmp_path, "route_a", 4)


ROUTE = [[0, 0], [12, 0], [22, 5], [32, 5], [40, 0]]
SANDY_SLOPE = [TerrainPatch(kind="side_slope", center=(16.0, 1.0), radius_m=7.0, slope_deg=12.0, downhill_deg=-90.0),
               TerrainPatch(kind="slip", center=(16.0, 1.0), radius_m=6.0, traction=0.6)]


def trials(learning: bool, n: int = 6):
    sim = ClosedLoop(ROUTE, SANDY_SLOPE, preset="husky", seed=1, teach_speed=0.5,
                     loc=PoseSourceSettings(noise_m=0.01, noise_heading_rad=math.radians(0.3), delay_ticks=1))
    path = sim.teach()
    mem, gains, out = ILCMemory("route", len(path)), ILCGains(), []
    for t in range(1, n + 1):
        r = sim.repeat(t, 0.5, law=ILCLaw(FLGains(), mem), ic_vertices=gains.ic_vertices)
        out.append((r.max_lateral, float(np.max(np.abs(r.heading_rad)))))
        if learning:
            mem.update(gains)
    return out


def test_ilc_cuts_max_errors_about_three_times_in_six_trials():
    """Thesis 3.3.2: a Husky on a sandy 5-15 degree side slope, errors down by ~3x after six trials."""
    res = trials(learning=True)
    (lat1, head1), (lat6, head6) = res[0], res[-1]
    assert lat1 > 0.15
    assert lat6 <= lat1 / 2.5 and head6 <= head1 / 2.5, res


def test_without_learning_ilc_repeats_its_first_trial():
    res = trials(learning=False, n=3)
    lat = [r[0] for r in res]
    assert max(lat) - min(lat) < 0.15 * lat[0], res

"""A curvature-limited robot's plan carried on beyond its horizon (services/controller/steered_out.py)
against the arc worked by hand, and RC-LB-NMPC's stop at its slowest speed where that arc leaves the
corridor: an Ackermann with little curvature to spare stops, one that can turn back drives on."""
import dataclasses
import math

import numpy as np
import pytest

from services.controller.corridor import Corridor
from services.controller.robust_nmpc import RCLBNMPCLaw
from services.controller.settings import NMPCSettings
from services.controller.speed_ladder import SPEED_LADDER
from services.controller.steered_out import lateral_reach
from tests.test_robust_nmpc import DT, arc_path, ctx_for


def _straight_plan(e0: float, h: np.ndarray, step_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Errors and poses of a plan along the x axis (the route) with heading errors `h`, moving `step_m`
    a step."""
    K = len(h)
    X = np.zeros((K + 1, 3))
    X[1:, 0] = step_m * np.arange(1, K + 1)
    E = np.column_stack([X[1:, 0], e0 + np.zeros(K), h])
    return E, X


def test_the_reach_is_the_arc_of_the_plans_heading_change_per_metre_worked_by_hand():
    # the heading error closes from 0.059 to 0.05 rad over 0.09 m: rho = -0.1 rad/m
    E, X = _straight_plan(0.10, np.linspace(0.059, 0.05, 10), 0.01)
    low, high = lateral_reach(E, X, 1.5)
    rho = (0.05 - 0.059) / 0.09
    x_turn = -0.05 / rho                                             # 0.5 m: closed inside the lookahead
    assert high == pytest.approx(0.10 + math.sin(0.05) * x_turn + 0.5 * rho * x_turn ** 2)
    assert high == pytest.approx(0.1125, abs=2e-4) and low == pytest.approx(0.10)
    # opening: the lateral error grows all the way
    E, X = _straight_plan(0.10, np.linspace(0.05, 0.059, 10), 0.01)
    low, high = lateral_reach(E, X, 1.5)
    assert low == pytest.approx(0.10) and high == pytest.approx(0.10 + math.sin(0.059) * 1.5 + 0.5 * 0.1 * 2.25)
    # a plan that does not move: the heading error held, in a straight line
    E, X = _straight_plan(-0.05, np.full(10, -0.02), 0.0)
    assert lateral_reach(E, X, 1.0) == pytest.approx((-0.05 + math.sin(-0.02), -0.05))


def _ackermann_at_the_slowest_rung(kappa_max: float):
    """An Ackermann at a crawl on a 0.2 m corridor's middle on the arc's straight, its heading 8 deg out, its
    spread widened 6x so that only the ladder's bottom rung fits."""
    path = arc_path()
    corridor = Corridor(path.s, 0.2, math.radians(20))
    ctx = ctx_for(path, path.pose_at(5.0) + np.array([0.0, 0.0, math.radians(8.0)]), v=0.8, corridor=corridor,
                  cov=np.diag([0.01 ** 2, 0.01 ** 2, 1e-5]), prev_cmd=(0.05, 0.0))
    ctx = dataclasses.replace(ctx, w_limit=kappa_max, w_limit_at=lambda v: abs(v) * kappa_max,
                              spread_factors=(6.0,) * 10, xi_now=(0.05, 0.0))
    law = RCLBNMPCLaw(NMPCSettings(curvature_rate_max_per_ms=2.0, actuator_tau_s=(0.3, 0.1)), DT)
    return law.angular(ctx), law


def test_an_ackermann_that_cannot_turn_back_in_time_stops_at_its_slowest_speed_and_says_why():
    out, law = _ackermann_at_the_slowest_rung(0.05)
    assert law._rung == len(SPEED_LADDER) - 1
    assert out.v_mps == 0.0 and ("at a crawl the steering turns the heading error (+7.8 deg) back too slowly: "
                                 "the lateral error reaches +0.15") in out.stop_reason
    assert "within 1.5 m, beyond the corridor [-0.20, +0.20] m" in out.stop_reason
    out, law = _ackermann_at_the_slowest_rung(1.0)                  # it can turn back within centimetres
    assert not out.stop_reason and out.v_mps > 0

"""Where LB-NMPC's Gauss-Newton starts (nmpc.best_start): on a rate-limited steering the cost is flat in
commands far from the curvature reached, so the solve must not depend on starting on the right side."""
from dataclasses import replace

import numpy as np
import pytest

from services.controller.nmpc import LBNMPCLaw, best_start, build_problem
from services.controller.settings import NMPCSettings
from tests.test_held_turn import LinearHeading
from tests.test_nmpc import STRAIGHT, ctx_at

DT = 0.1
LIMIT = 0.305
# a MATS-like Ackermann drive: lags 0.3 / 0.18 s, curvature rate 0.34 /(m s), understeer 0.925
ACKERMANN = NMPCSettings(actuator_tau_s=(0.3, 0.18), curvature_rate_max_per_ms=0.34, turn_gain=0.925)


def _ctx(lat_m: float, head_rad: float, kappa: float):
    """At 1 m/s on a straight, the steering at curvature `kappa` (and last commanded there)."""
    ctx = ctx_at(STRAIGHT, (5.0, lat_m, head_rad), v=1.0, prev_cmd=(1.0, kappa))
    return replace(ctx, w_limit=LIMIT, w_limit_at=lambda _v: LIMIT, xi_now=(1.0, kappa))


def test_the_start_of_lowest_cost_is_taken_wherever_it_stands():
    """The first start is costed from its residual, the others from the cost: either way the cheapest wins."""
    problem, lim = build_problem(_ctx(-0.05, -0.18, 0.3), ACKERMANN, DT, None)
    zero = np.zeros_like(lim)
    assert problem.cost(lim) < problem.cost(zero) < problem.cost(-lim)
    assert best_start(problem, [-lim, lim, zero]) == pytest.approx(lim)
    assert best_start(problem, [lim, -lim, zero]) == pytest.approx(lim)
    assert best_start(problem, [zero, -lim]) == pytest.approx(zero)
    assert best_start(problem, [-lim, zero]) == pytest.approx(zero)


@pytest.mark.parametrize("slope", [0.0, -0.1, -0.2])
def test_lb_nmpc_turns_back_after_a_plan_at_the_other_limit_on_a_rate_limited_steering(slope):
    """Step 1 (heading +11 deg, steering straight) plans the right turn limit throughout; step 2 finds
    the robot steering left at +0.3 /m with a -10 deg heading error: the plan must keep steering left.
    A heading model that keeps 80-100 % of the turn (slope: its answer to the command, per rad/s)
    gives Gauss-Newton from step 1's plan a slope towards the right limit, where it stayed before
    best_start (cost 4.85 against 2.83 with slope -0.1). Reference: the best of 61 constant turns."""
    model = LinearHeading(slope * DT) if slope else None
    law = LBNMPCLaw(ACKERMANN, DT, model_for=lambda _ctx: model)
    law.angular(_ctx(0.1, 0.2, 0.0))
    assert law.last_plan.w[1] < 0.0
    ctx = _ctx(-0.05, -0.18, 0.3)
    law.angular(ctx)
    problem, _ = build_problem(ctx, ACKERMANN, DT, model)
    best_constant = min(problem.cost(np.full(problem.K, w)) for w in np.linspace(-LIMIT, LIMIT, 61))
    assert law.last_plan.w[0] > 0.0
    assert problem.cost(law.last_plan.w) <= best_constant + 1e-9


def test_a_drive_without_a_steering_rate_limit_starts_from_the_warm_start():
    """Without the rate limit the cost is smooth in the turn and the extra starts would cost rollouts."""
    skid = NMPCSettings(actuator_tau_s=(0.3, 0.18), turn_gain=0.925)
    law = LBNMPCLaw(skid, DT, model_for=lambda _ctx: LinearHeading(-0.1 * DT))
    law.angular(_ctx(0.1, 0.2, 0.0))
    problem, lim = build_problem(_ctx(-0.05, -0.18, 0.3), skid, DT, LinearHeading(-0.1 * DT))
    assert not problem.curvature_steered
    assert law.start(problem, lim) == pytest.approx(law.warm_start(problem))
    assert problem.cost(law.warm_start(problem)) > problem.cost(lim)   # a limit would have been cheaper


def test_rc_lb_nmpcs_sqp_starts_from_the_least_merit_of_its_warm_start_and_either_limit_on_a_rate_limited_steering():
    """RC-LB-NMPC's SQP, given a warm start at the wrong limit (the robot steering left at +0.3 /m with a
    -10 deg heading error), starts from the left limit held, the plan of least merit, with that plan's
    GP inputs; a skid-steer's starts from its warm start."""
    import math

    from services.controller.corridor import Corridor
    from services.controller.robust_nmpc import RCLBNMPCLaw
    corridor = Corridor(STRAIGHT.s, 0.5, math.radians(30))
    for settings, steered in ((ACKERMANN, True), (replace(ACKERMANN, curvature_rate_max_per_ms=0.0), False)):
        ctx = replace(_ctx(-0.05, -0.18, 0.3), corridor=corridor, pose_cov=np.diag([1e-4, 1e-4, 1e-5]),
                      v_max_mps=1.0, w_limit_at=lambda v: LIMIT * max(v, 0.05))
        law = RCLBNMPCLaw(settings, DT)
        law.angular(ctx)
        nlp, v = law.last_step.nlp, law.last_step.start.v
        assert nlp.problem.curvature_steered == steered
        limit = nlp.w_limits(v)
        A = np.empty((len(v), 9))
        start = law._start(nlp, v, -limit, A)
        merits = [nlp.evaluate(v, w).merit for w in (-limit, limit)]
        if not steered:
            assert start.w == pytest.approx(-limit)
            continue
        assert merits[1] < merits[0] and start.w == pytest.approx(limit) and start.merit == pytest.approx(merits[1])
        fresh = np.empty_like(A)
        nlp.evaluate(v, limit, fresh)
        np.testing.assert_allclose(A, fresh)

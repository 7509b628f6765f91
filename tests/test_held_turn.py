"""The controller's check of a learned heading model's turn authority at its own plan (held_turn.py)."""
import numpy as np
import pytest

from common.gp import GaussianProcess, SEHyper
from common.turn_share import HEADING, W_CMD
from services.controller.held_turn import HeldTurn, held_note, least_kept_share
from services.controller.nmpc import LBNMPCLaw, build_problem
from services.controller.settings import NMPCSettings
from tests.test_nmpc import STRAIGHT, ctx_at

DT = 0.1


class LinearHeading:
    """g = (0, 0, c w_cmd + d): a heading disturbance per period linear in the commanded turn rate."""

    def __init__(self, c: float, d: float = 0.0):
        self.c, self.d = c, d

    def mean_and_grad(self, a):
        dg = np.zeros((3, 9))
        dg[HEADING, W_CMD] = self.c
        return np.array([0.0, 0.0, self.c * a[W_CMD] + self.d]), dg

    def mean(self, A):
        A = np.atleast_2d(A)
        return np.column_stack([np.zeros(len(A)), np.zeros(len(A)), self.c * A[:, W_CMD] + self.d])


def test_the_share_a_linear_heading_model_keeps_worked_by_hand():
    # k = 0.6, c = -0.066 per period: G = c / dt = -0.66, (k + G) / k = -0.06 / 0.6 = -0.1; no turn
    # history inputs, so the settled share is the same
    A = np.zeros((3, 9))
    A[:, W_CMD] = [-0.3, 0.0, 0.4]
    for slope, share in ((-0.066, -0.1), (-0.03, 0.5)):
        gradients = np.array([LinearHeading(slope).mean_and_grad(a)[1] for a in A])
        assert least_kept_share(gradients, 0.6, DT) == pytest.approx(share)


@pytest.mark.parametrize("slope, min_share, held", [(-1.06 * DT, 0.1, True), (-0.5 * DT, 0.1, False),
                                                    (-1.06 * DT, 0.0, False)])
def test_a_model_that_cancels_the_turn_is_held_and_one_that_scales_it_is_not(slope, min_share, held):
    model = LinearHeading(slope, 0.01)
    ctx = ctx_at(STRAIGHT, (5.0, 0.0, 0.1), v=0.8, prev_cmd=(0.8, -0.3))
    problem, _ = build_problem(ctx, NMPCSettings(min_turn_share=min_share), DT, model)
    assert isinstance(problem.model, HeldTurn) is held
    if held:
        assert problem.model.kept_share == pytest.approx(-0.06)
        assert "kept -6% of the turn" in held_note(problem.model)
    else:
        assert problem.model is model and held_note(problem.model) == ""


class SaturatedCancel(LinearHeading):
    """Scales the turn by 0.7 below 0.25 rad/s and cancels it above: a fit of closed-loop data in which the
    controller saturated where the terrain turned the robot the other way."""

    def mean_and_grad(self, a):
        g, dg = super().mean_and_grad(a)
        c = -0.3 * DT if abs(a[W_CMD]) < 0.25 else -1.06 * DT
        dg[HEADING, W_CMD] = c
        g[HEADING] = c * a[W_CMD]
        return g, dg


def test_the_check_also_probes_the_warm_start_where_a_fit_cancels_only_at_the_turn_limit():
    model = SaturatedCancel(0.0)
    ctx = ctx_at(STRAIGHT, (5.0, 0.0, 0.1), v=0.8, prev_cmd=(0.8, -0.3))
    st = NMPCSettings(min_turn_share=0.1)
    at_limit = np.full(st.horizon, -0.3)
    assert build_problem(ctx, st, DT, model)[0].model is model
    held = build_problem(ctx, st, DT, model, probes=(at_limit,))[0].model
    assert isinstance(held, HeldTurn) and held.kept_share == pytest.approx(1.0 - 1.06)   # nominal turn gain 1
    assert build_problem(ctx, st, DT, model, probes=(np.zeros(st.horizon),))[0].model is model


def _gp():
    rng = np.random.default_rng(3)
    X = rng.normal(size=(80, 9)) * [2, 0.1, 0.05, 0.2, 0.3, 0.1, 0.3, 0.1, 0.3] + [5, 0, 0, 0.5, 0, 0.5, 0, 0.5, 0]
    Y = np.column_stack([0.01 * np.sin(X[:, 0]), 0.01 * np.cos(3 * X[:, W_CMD]), -0.05 * X[:, W_CMD]])
    return X, GaussianProcess(X, Y, [SEHyper(np.array([1.5, .2, .1, .3, .4, .3, .3, .3, .4]), 0.02, 0.001)] * 3)


S_KNOTS = np.array([4.0, 5.0, 6.0, 7.0])
KAPPA = np.array([0.0, 0.2, 0.5, 0.5])         # a corner's entry: the held turn rate changes along the route


def test_the_held_model_takes_the_heading_mean_at_the_routes_turn_rate_and_the_rest_as_it_was():
    X, gp = _gp()
    held = HeldTurn(gp, S_KNOTS, KAPPA, 0.8, -0.1)
    A = X[:5] + 0.05
    at_route = A.copy()
    at_route[:, W_CMD] = np.interp(A[:, 0], S_KNOTS, KAPPA) * A[:, 5] / 0.8      # kappa(s) v_cmd / turn gain
    for a, a_r, row in zip(A, at_route, held.mean(A)):
        g, dg = held.mean_and_grad(a)
        g_raw, dg_raw = gp.mean_and_grad(a)
        np.testing.assert_allclose(g[:HEADING], g_raw[:HEADING])
        np.testing.assert_allclose(dg[:HEADING], dg_raw[:HEADING])
        assert g[HEADING] == pytest.approx(gp.mean_and_grad(a_r)[0][HEADING])
        assert dg[HEADING, W_CMD] == 0.0
        np.testing.assert_allclose(row, g)


def test_the_held_heading_gradient_matches_central_differences():
    X, gp = _gp()
    held = HeldTurn(gp, S_KNOTS, KAPPA, 0.8, -0.1)
    for a in X[:6] + 0.05:
        a = a.copy()
        a[0] = 4.3 + 0.4 * (a[0] % 5)        # inside the knots, away from their kinks
        _, dg = held.mean_and_grad(a)
        for i in range(9):
            h = np.zeros(9)
            h[i] = 1e-6
            fd = (held.mean(a + h)[0, HEADING] - held.mean(a - h)[0, HEADING]) / 2e-6
            assert dg[HEADING, i] == pytest.approx(fd, rel=1e-4, abs=1e-8)


def test_lb_nmpc_turns_back_against_a_heading_error_where_its_learned_model_would_cancel_the_turn():
    """Heading 8 deg left of a straight route, and a model in which commanding a turn reverses 6 % of it:
    planned on as it is, the law does not turn back; held, it does."""
    model = LinearHeading(-1.06 * DT)
    ctx = ctx_at(STRAIGHT, (5.0, 0.0, np.radians(8.0)), v=0.8, prev_cmd=(0.8, -0.3))
    w = {}
    for share in (0.0, 0.1):
        law = LBNMPCLaw(NMPCSettings(min_turn_share=share), DT, lambda c: model)
        w[share] = law.angular(ctx).w_radps
    assert w[0.1] < -0.2
    assert w[0.0] > -0.05


def test_lb_nmpc_solves_again_held_where_its_solution_went_where_the_model_cancels_the_turn():
    """The reference (straight) and the first step's warm start keep 70 % of the turn; the turn needed to
    correct 12 deg lies beyond 0.25 rad/s, where the model cancels it. Held at the straight route's turn
    rate (0, where this model's mean is 0) the plan is the nominal model's; unheld, it believes its
    first turn leaves the heading where it is."""
    model = SaturatedCancel(0.0)
    ctx = ctx_at(STRAIGHT, (5.0, 0.0, np.radians(12.0)), v=0.8, prev_cmd=(0.8, 0.0))
    result = {share: LBNMPCLaw(NMPCSettings(min_turn_share=share), DT, lambda c: model).angular(ctx)
              for share in (0.0, 0.1)}
    nominal = LBNMPCLaw(NMPCSettings(), DT).angular(ctx)
    assert "kept -6% of the turn" in result[0.1].note and result[0.0].note == ""
    assert result[0.1].w_radps == pytest.approx(nominal.w_radps, abs=1e-6)
    np.testing.assert_allclose(result[0.1].predicted, nominal.predicted, atol=1e-6)
    assert result[0.0].predicted[0, 2] > nominal.predicted[0, 2] + 0.05

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
def test_a_model_that_cancels_the_turn_is_held_at_the_last_command_and_one_that_scales_it_is_not(
        slope, min_share, held):
    model = LinearHeading(slope, 0.01)
    ctx = ctx_at(STRAIGHT, (5.0, 0.0, 0.1), v=0.8, prev_cmd=(0.8, -0.3))
    problem, _ = build_problem(ctx, NMPCSettings(min_turn_share=min_share), DT, model)
    assert isinstance(problem.model, HeldTurn) is held
    if held:
        assert problem.model.w_cmd_radps == -0.3
        assert problem.model.kept_share == pytest.approx(-0.06)
        assert "kept -6% of the turn" in held_note(problem.model)
    else:
        assert problem.model is model and held_note(problem.model) == ""


def test_the_held_model_keeps_the_heading_mean_at_the_command_without_its_slope_and_the_rest_as_it_was():
    rng = np.random.default_rng(3)
    X = rng.normal(size=(80, 9)) * [2, 0.1, 0.05, 0.2, 0.3, 0.1, 0.3, 0.1, 0.3] + [5, 0, 0, 0.5, 0, 0.5, 0, 0.5, 0]
    Y = np.column_stack([0.01 * np.sin(X[:, 0]), 0.01 * np.cos(3 * X[:, W_CMD]), -0.05 * X[:, W_CMD]])
    gp = GaussianProcess(X, Y, [SEHyper(np.array([1.5, .2, .1, .3, .4, .3, .3, .3, .4]), 0.02, 0.001)] * 3)
    held = HeldTurn(gp, 0.2, -0.1)
    A = X[:5] + 0.05
    at_command = A.copy()
    at_command[:, W_CMD] = 0.2
    for a, a_c, row in zip(A, at_command, held.mean(A)):
        g, dg = held.mean_and_grad(a)
        g_raw, dg_raw = gp.mean_and_grad(a)
        g_c, dg_c = gp.mean_and_grad(a_c)
        np.testing.assert_allclose(g[:HEADING], g_raw[:HEADING])
        np.testing.assert_allclose(dg[:HEADING], dg_raw[:HEADING])
        assert g[HEADING] == pytest.approx(g_c[HEADING])
        assert dg[HEADING, W_CMD] == 0.0
        np.testing.assert_allclose(np.delete(dg[HEADING], W_CMD), np.delete(dg_c[HEADING], W_CMD))
        np.testing.assert_allclose(row, g)


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

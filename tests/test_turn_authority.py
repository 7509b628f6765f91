"""The store's check that a learned heading model leaves the controller its steering
(services/gp_store/authority.py), against the derivative of the function the data were drawn from."""
import numpy as np
import pytest

from common.gp import SEHyper
from services.controller.actuator import ActuatorLag
from common.turn_share import W_ACT, W_CMD
from services.gp_store.authority import TURN_INPUTS, AuthorityRule, turn_authority
from services.gp_store.fitting import fit_route

DT = 0.1


def _inputs(n: int, rng: np.random.Generator) -> np.ndarray:
    """Experience inputs a (A_NAMES) of a robot passing 20 m of route at 0.5-1 m/s."""
    A = np.zeros((n, 9))
    A[:, 0] = rng.uniform(0.0, 20.0, n)
    A[:, 1], A[:, 2] = rng.normal(0.0, 0.03, n), rng.normal(0.0, 0.03, n)
    A[:, 3] = A[:, 5] = A[:, 7] = rng.uniform(0.5, 1.0, n)
    A[:, W_CMD] = rng.uniform(-0.5, 0.5, n)
    A[:, 8] = A[:, W_CMD] + rng.normal(0.0, 0.02, n)
    A[:, W_ACT] = A[:, W_CMD] + rng.normal(0.0, 0.02, n)
    return A


def _linear_in_command(slope: float, n: int = 300, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Heading residuals slope * w_cmd * dt: the robot turns at (1 + slope) times the command."""
    rng = np.random.default_rng(seed)
    A = _inputs(n, rng)
    return A, slope * A[:, W_CMD] * DT + rng.normal(0.0, 1e-4, n)


def _interior(A: np.ndarray) -> np.ndarray:
    return np.abs(A[:, W_CMD]) < 0.3


@pytest.mark.parametrize("slope", [-0.95, -0.8, -0.3, 0.2])
def test_the_authority_kept_is_one_plus_the_slope_of_a_linear_command_dependence(slope):
    A, y = _linear_in_command(slope)
    # the command's lengthscale long against its range: the posterior mean is the line, other inputs flat
    hyper = SEHyper(np.array([1e3, 1e3, 1e3, 1e3, 1e3, 1e3, 3.0, 1e3, 1e3]), 0.2, 1e-4)
    check = turn_authority(A, y, None, hyper, AuthorityRule(period_s=DT))
    inner = check.shares[_interior(A)]
    assert np.allclose(inner, 1.0 + slope, atol=0.03), (inner.min(), inner.max())
    assert check.passed == (1.0 + slope >= check.min_share)


def test_a_model_where_the_last_turn_rate_persists_whatever_is_commanded_has_no_steady_turn():
    rng = np.random.default_rng(1)
    A = _inputs(300, rng)
    A[:, W_ACT] = rng.uniform(-0.5, 0.5, 300)        # measured turn rates apart from the commands
    y = (A[:, W_ACT] - A[:, W_CMD]) * DT               # g = (w_act - w_cmd) dt: the NMPC's steering is gone
    ell = np.full(9, 1e3)
    ell[[W_ACT, W_CMD]] = 3.0
    check = turn_authority(A, y, None, SEHyper(ell, 0.2, 1e-4), AuthorityRule(period_s=DT))
    assert not check.passed and np.all(check.shares[_interior(A)] < 0.1)


def test_the_rule_reads_the_period_and_turn_gain_from_the_nominal_models_tag():
    lag = ActuatorLag(tau_v_s=0.3, tau_w_s=0.2, dt=0.05, curvature_rate_max_per_ms=0.4, turn_gain=1.12)
    rule = AuthorityRule.for_model(lag.model_tag, 0.5, 100.0)
    assert (rule.period_s, rule.turn_gain, rule.min_share, rule.off_lengthscale) == (0.05, 1.12, 0.5, 100.0)
    assert AuthorityRule.for_model(ActuatorLag().model_tag, 0.5, 100.0).turn_gain == 1.0
    assert AuthorityRule.for_model("", 0.5, 100.0) is None          # untagged experiences: no period known
    assert AuthorityRule.for_model(lag.model_tag, 0.0, 100.0) is None   # the check switched off


def test_a_fit_that_learned_the_commands_is_refitted_with_the_turn_rate_inputs_off():
    A, y = _linear_in_command(-0.97, n=400, seed=2)
    G = np.column_stack([np.zeros(len(y)), np.zeros(len(y)), y]) + np.random.default_rng(3).normal(0, 1e-4, (len(y), 3))
    floors = [0.5, 1.0, 1.0, 0.3, 0.3, 0.3, 0.3, 0.3, 0.3]
    free = fit_route("r", A, G, None, 1, 1000, 0, None, floors)
    h = free.dims[2]
    learned = turn_authority(A, G[:, 2], None, SEHyper(np.asarray(h.lengthscales), h.signal_std, h.noise_std),
                             AuthorityRule(period_s=DT))
    assert free.note == "" and np.allclose(learned.shares[_interior(A)], 0.03, atol=0.03)
    checked = fit_route("r", A, G, None, 1, 1000, 0, None, floors, AuthorityRule(period_s=DT))
    assert "switched off" in checked.note and "steering" in checked.note
    assert min(checked.dims[2].lengthscales[i] for i in TURN_INPUTS) >= 100.0
    assert checked.dims[:2] == free.dims[:2]          # the other outputs keep their fit
    assert checked.message(version=1, stamp_s=0.0).note == checked.note


def test_a_fit_that_keeps_the_steering_is_left_alone():
    A, y = _linear_in_command(-0.6, n=400, seed=4)
    G = np.column_stack([np.zeros(len(y)), np.zeros(len(y)), y]) + np.random.default_rng(5).normal(0, 1e-4, (len(y), 3))
    floors = [0.5, 1.0, 1.0, 0.3, 0.3, 0.3, 0.3, 0.3, 0.3]
    checked = fit_route("r", A, G, None, 1, 1000, 0, None, floors, AuthorityRule(period_s=DT))
    assert checked.note == "" and checked.dims == fit_route("r", A, G, None, 1, 1000, 0, None, floors).dims

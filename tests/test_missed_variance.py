"""The long memory of what the predictions missed (services/controller/missed_variance.py) and its floors
on the predicted spread (calibration.py, horizon_covariance.py): the sliding maximum and quantile against
brute force ones, floors per channel that outlive the recent window and carry over to a surer model, and
the widened spread and its derivative against their definitions."""
import math

import numpy as np
import pytest

from services.controller.calibration import WINDOW, Prediction, SpreadCalibration
from services.controller.horizon_covariance import HorizonCovariance
from services.controller.missed_variance import LONG_WINDOW, MARGIN, SlidingMax, SlidingQuantile, SpreadFloors


def test_the_sliding_maximum_and_quantile_are_those_of_the_last_values():
    rng = np.random.default_rng(0)
    values = rng.exponential(size=3000)
    size = 200
    mx, qu = SlidingMax(size), SlidingQuantile(size, 0.99)
    for i, v in enumerate(values):
        mx.push(v)
        qu.push(v)
        last = values[max(0, i - size + 1):i + 1]
        assert mx.value == last.max()
        assert qu.value == np.sort(last)[len(last) - max(1, math.ceil(0.01 * len(last)))]   # the 2nd largest of 200
        if i == 1500:
            mx_copy, qu_copy, at = mx.copy(), qu.copy(), i
    for v in values[:50]:
        mx_copy.push(v)
        qu_copy.push(v)
    window = np.concatenate([values[at + 1 - size + 50:at + 1], values[:50]])
    assert mx_copy.value == window.max() and qu_copy.value == np.sort(window)[-2]


def realize_one(cal: SpreadCalibration, k: int, lat_err: float, head_err: float, sigma_lat: float,
                sigma_head: float) -> float:
    """A one-step prediction on the route's axis with model spreads `sigma_*`, widened as the laws widen
    them (HorizonCovariance.widened: factor, added floor or least share), realized with the given errors."""
    kappa = float(cal.factors_at(None)[0])
    cov = HorizonCovariance(var=None, Sigma0=np.eye(3), dt=0.1, gamma=2.0, factors=np.array([math.sqrt(kappa)]),
                            floors=cal.floors())
    model = np.array([[0.0, sigma_lat, sigma_head]])
    wide = cov.widened(model, np.zeros((1, 3)))
    cal.predict(k, [Prediction(1, 0.0, 0.0, float(wide[0, 1]), float(wide[0, 2]), kappa,
                               model_sigma_lat_m=sigma_lat, model_sigma_head_rad=sigma_head)])
    return cal.realize(k + 1, lat_err, head_err, 0.0, 0.0)[0]


def test_a_heading_that_wanders_beyond_the_model_floors_the_heading_and_not_the_lateral():
    """Heading errors 3x what the model claims, lateral errors as it claims: the floors under the heading
    share hold the heading errors (their asked-for quantile: ~9x the model's variance); the lateral ones
    stay about the model's own variance, what the tail of calibrated errors asks for."""
    rng = np.random.default_rng(1)
    cal = SpreadCalibration(horizon=1)
    for k in range(2000):
        realize_one(cal, k, 0.01 * rng.standard_normal(), 0.03 * rng.standard_normal(), 0.01, 0.01)
    f = cal.floors()
    assert f.least[0, 0] < 1.5 * 0.01 ** 2 and f.added[0, 0] < 0.01 ** 2
    assert 0.5 * 0.03 ** 2 < f.least[0, 1] < 1.5 * 0.03 ** 2 and f.added[0, 1] > 0.03 ** 2


def test_what_a_trial_missed_floors_the_next_trials_surer_model_from_its_first_prediction():
    """Trial 1's model claims 3 cm where the robot's own noise is 3 cm: nothing is missed, but what the
    errors asked for is remembered in m^2, not as a ratio to the model. Trial 2's model is thirty times
    surer of itself (the fit on trial 1): from its first prediction its spread holds the noise."""
    rng = np.random.default_rng(2)
    cal = SpreadCalibration(horizon=1)
    for k in range(WINDOW * 4):
        realize_one(cal, k, 0.03 * rng.standard_normal(), 0.0, 0.03, 0.01)
    assert cal.outside[0] <= 3
    nxt = cal.continued()
    np.testing.assert_allclose(nxt.floors().least, cal.floors().least)
    z = np.array([realize_one(nxt, k, 0.03 * rng.standard_normal(), 0.0, 0.001, 0.001) for k in range(600)])
    assert np.mean(z[:50] > 3.0) == 0.0 and np.mean(z > 3.0) <= 0.01


def test_the_floors_are_forgotten_a_long_window_after_the_error_that_set_them():
    cal = SpreadCalibration(horizon=1)
    realize_one(cal, 0, 0.05, 0.0, 0.01, 0.01)            # a 5-sigma surprise
    added = cal.floors().added[0, 0]
    assert added == pytest.approx(MARGIN * (0.05 ** 2 / 9.0 - 0.01 ** 2))
    for k in range(1, LONG_WINDOW):
        realize_one(cal, k, 0.0, 0.0, 0.01, 0.01)
    assert cal.scales[0] == 1.0                            # the recent window forgot it long ago ...
    assert cal.floors().added[0, 0] == pytest.approx(added)   # ... the long memory still holds it
    assert cal.floors().least[0, 0] == 0.0                 # one error in 1500 is beyond the quantile
    realize_one(cal, LONG_WINDOW, 0.0, 0.0, 0.01, 0.01)
    assert cal.floors().added[0, 0] == 0.0


def test_a_floored_prediction_is_checked_against_the_models_own_share():
    """A prediction whose spread was a floor's reports the model's own spread, so the need of its error is
    measured against the model's share, as for one the factors widened."""
    cal = SpreadCalibration(horizon=1)
    share, sigma = 0.01 ** 2, 0.03
    cal.predict(0, [Prediction(1, 0.0, 0.0, sigma, sigma, 1.0, model_sigma_lat_m=0.01, model_sigma_head_rad=0.01)])
    cal.realize(1, 0.06, 0.0, 0.0, 0.0)
    assert cal.scales[0] == pytest.approx(MARGIN * (0.06 ** 2 / 9.0) / share)
    assert cal.floors().added[0, 0] == pytest.approx(MARGIN * (0.06 ** 2 / 9.0 - share))


def test_the_widened_spread_takes_the_largest_of_factor_floor_and_least_share_and_its_derivative_follows():
    sig = np.array([[0.0, 0.03, 0.02], [0.0, 0.05, 0.03], [0.0, 0.08, 0.04], [0.0, 0.03, 0.02]])
    loc = np.full((4, 3), 0.01)
    loc[:, 1] = 0.02
    factors = np.array([1.0, 2.0, 1.2, 1.0])           # on the standard deviations
    added = np.array([[1e-3, 4e-4], [1e-4, 0.0], [1e-3, 1e-4], [0.0, 0.0]])
    least = np.array([[0.0, 0.0], [0.0, 0.0], [0.0, 0.0], [4e-3, 1e-3]])
    cov = HorizonCovariance(var=None, Sigma0=np.eye(3), dt=0.1, gamma=2.0, factors=factors,
                            floors=SpreadFloors(added, least))
    wide = cov.widened(sig, loc)
    for j in range(4):
        share = sig[j, 1:] ** 2 - loc[j, 1:] ** 2
        expected = np.sqrt(loc[j, 1:] ** 2 + np.maximum(np.maximum(factors[j] ** 2 * share, share + added[j]),
                                                         least[j]))
        np.testing.assert_allclose(wide[j, 1:], expected)
    np.testing.assert_allclose(cov.least(loc)[:, 1:], np.sqrt(loc[:, 1:] ** 2 + np.maximum(added, least)))
    analytic = cov.widened_derivative(np.eye(4), sig, loc)   # d wide_lat / d sig_lat, rows j
    h = 1e-7
    for i in range(4):
        up, down = sig.copy(), sig.copy()
        up[i, 1] += h
        down[i, 1] -= h
        fd = (cov.widened(up, loc)[i, 1] - cov.widened(down, loc)[i, 1]) / (2 * h)
        assert analytic[i, i] == pytest.approx(fd, rel=1e-5, abs=1e-9)
    assert analytic[3, 3] == 0.0                         # at the least share the spread does not follow the model's

"""The learned mean fades to zero at rest below the slowest speed of a window's experiences
(services/controller/rest_fade.py), against the plain GP and finite differences."""
import numpy as np

from common.gp import GaussianProcess, SEHyper
from services.controller.rest_fade import RestFaded
from services.controller.uncertainty import DisturbanceVariance, PriorStd


def window(n=200, seed=3):
    """A rutted stretch driven at 0.8-1.2 m/s: a heading push per period growing with speed."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, 9)) * 0.1
    A[:, 0] = rng.uniform(0.0, 10.0, n)
    A[:, 3] = rng.uniform(0.8, 1.2, n)
    G = np.column_stack([np.zeros(n), np.zeros(n), 0.02 * A[:, 3] * np.sin(A[:, 0])])
    h = SEHyper(np.array([1.0, 1, 1, 0.5, 1, 1, 1, 1, 1]), 0.02, 0.001)
    return A, GaussianProcess(A, G, [h, h, h])


def test_the_slowest_speed_is_the_windows_tenth_percentile_of_rolled_speeds():
    A, gp = window()
    assert RestFaded.of(gp, A).v_floor == np.percentile(A[:, 3], 10.0)
    assert RestFaded.of(gp, A[:0]).v_floor == 0.0


def test_the_mean_is_the_gps_at_and_above_the_slowest_speed_and_in_proportion_below_it():
    A, gp = window()
    model = RestFaded(gp, 0.8)
    a = A[7].copy()
    for v, share in ((1.0, 1.0), (0.8, 1.0), (0.4, 0.5), (0.08, 0.1), (0.0, 0.0), (-0.2, 0.0)):
        a[3] = v
        np.testing.assert_allclose(model.mean_and_grad(a)[0], share * gp.mean_and_grad(a)[0], atol=1e-15)
        np.testing.assert_allclose(model.mean(a[None])[0], share * gp.mean(a[None])[0], atol=1e-15)
        np.testing.assert_allclose(model.predict(a[None])[0][0], share * gp.predict(a[None])[0][0], atol=1e-15)
        np.testing.assert_array_equal(model.predict(a[None])[1], gp.predict(a[None])[1])   # the variance kept


def test_the_gradient_matches_finite_differences_below_the_slowest_speed():
    A, gp = window()
    model = RestFaded(gp, 0.8)
    a = A[11].copy()
    a[3] = 0.3
    _, dg = model.mean_and_grad(a)
    h = 1e-6
    for i in range(9):
        e = np.zeros(9)
        e[i] = h
        fd = (model.mean_and_grad(a + e)[0] - model.mean_and_grad(a - e)[0]) / (2 * h)
        np.testing.assert_allclose(dg[:, i], fd, rtol=1e-5, atol=1e-10)
    assert abs(dg[2, 3]) > 1e-3          # the fade's own term: the push grows with the rolled speed


def test_the_variance_gp_is_the_faded_model_itself_where_nothing_is_capped():
    """DisturbanceVariance then takes mean and variance from one prediction, as with a plain GP."""
    A, gp = window()
    model = RestFaded(gp, 0.8)
    assert model.capped((0, 5, 6), (100.0, 100.0, 100.0)) is model
    assert model.capped((0, 5, 6), (0.1, 0.1, 0.1)) is gp.capped((0, 5, 6), (0.1, 0.1, 0.1))


def test_below_the_slowest_speed_the_part_faded_away_is_variance_and_nothing_changes_above_it():
    """A push that acts per second (a slope) is the GP's whole mean at a crawl, one fixed to the place (a
    rut) the faded one: the variance holds the difference, (1 - f) |g|, so that slower than the data is
    not taken for narrower."""
    A, gp = window()
    model = RestFaded(gp, 0.8)
    faded, plain = (DisturbanceVariance(m, PriorStd(), (0.0, 0.0, 0.0)) for m in (model, gp))
    a = np.repeat(A[5][None], 5, axis=0)
    a[:, 3] = (1.0, 0.8, 0.4, 0.1, 0.0)
    raw = gp.mean(a)
    share = np.array([0.0, 0.0, 0.5, 0.875, 1.0])[:, None]
    np.testing.assert_allclose(model.gap(a, model.mean(a)), share * np.abs(raw), rtol=1e-9, atol=1e-15)
    (m_f, v_f), (m_p, v_p) = faded.with_mean(a), plain.with_mean(a)
    np.testing.assert_allclose(m_f, (1.0 - share) * m_p, atol=1e-15)
    np.testing.assert_allclose(v_f, v_p + np.square(share * raw), rtol=1e-9, atol=1e-18)
    assert v_f[4, 2] > v_p[4, 2] + 0.5 * raw[4, 2] ** 2 > v_p[4, 2]     # at rest: the whole push's worth

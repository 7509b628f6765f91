"""The GP disturbance model (common/gp.py) against independent references: scikit-learn's exact GP
regression, central finite differences, and the prior when there is no data."""
import json
import math
import time
import warnings

import numpy as np
import pytest

from common.gp import (GaussianProcess, SEHyper, fit_hyperparameters, hyper_bounds, log_marginal_likelihood,
                       se_ard)

sk_gp = pytest.importorskip("sklearn.gaussian_process")
from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel  # noqa: E402

P = 9


@pytest.fixture(autouse=True, scope="module")
def _one_blas_thread():
    """Multi-threaded BLAS on these small matrices only adds contention on a shared machine."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        yield
        return
    with threadpool_limits(limits=1, user_api="blas"):
        yield


def _data(rng, n=120, p=P, d=3):
    X = rng.normal(size=(n, p)) * rng.uniform(0.3, 3.0, p) + rng.normal(size=p)
    c = [X[:, i % p] for i in range(5)]
    Y = np.column_stack([np.sin(c[0]) + 0.5 * c[1] * c[2] / 3.0,
                         np.cos(0.5 * X.sum(axis=1)),
                         np.tanh(c[3] - c[4])][:d]) + 0.05 * rng.normal(size=(n, d))
    return X, Y


def _random_hypers(rng, X, d):
    sx = X.std(axis=0)
    return [SEHyper(sx * rng.uniform(0.5, 4.0, X.shape[1]), rng.uniform(0.3, 2.0), rng.uniform(0.02, 0.3))
            for _ in range(d)]


def _sklearn_exact(X, y, h: SEHyper):
    kernel = ConstantKernel(h.signal_std ** 2, "fixed") * RBF(h.lengthscales.copy(), "fixed")
    return sk_gp.GaussianProcessRegressor(kernel=kernel, alpha=h.noise_std ** 2, optimizer=None,
                                          normalize_y=False).fit(X, y)


# --- hyperparameters ---------------------------------------------------------------------------
def test_sehyper_round_trips_and_validates():
    h = SEHyper(np.array([0.5, 2.0, 3.0]), 1.5, 0.1)
    assert SEHyper.from_log(h.to_log()).to_log() == pytest.approx(h.to_log(), rel=1e-14)
    np.testing.assert_array_equal(h.to_log(), np.log([0.5, 2.0, 3.0, 1.5, 0.1]))
    d = json.loads(json.dumps(h.to_dict()))       # plain lists and floats (msgpack-able)
    assert SEHyper.from_dict(d) == h
    assert isinstance(d["lengthscales"], list) and isinstance(d["signal_std"], float)
    with pytest.raises(ValueError):
        SEHyper(np.array([1.0, -1.0]), 1.0, 0.1)
    with pytest.raises(ValueError):
        SEHyper(np.array([1.0]), 0.0, 0.1)
    with pytest.raises(ValueError):
        SEHyper(np.array([1.0]), 1.0, math.nan)


def test_se_ard_is_eq_5_20_without_noise():
    rng = np.random.default_rng(0)
    X1, X2 = rng.normal(size=(5, 3)), rng.normal(size=(4, 3))
    ell, sf = np.array([0.5, 1.0, 2.0]), 1.3
    ref = np.array([[sf ** 2 * math.exp(-0.5 * np.sum(((a - b) / ell) ** 2)) for b in X2] for a in X1])
    np.testing.assert_allclose(se_ard(X1, X2, ell, sf), ref, rtol=1e-12, atol=1e-15)


# --- against scikit-learn --------------------------------------------------------------------------
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_predictions_and_lml_equal_sklearn(seed):
    rng = np.random.default_rng(seed)
    X, Y = _data(rng, n=150, d=3)
    hypers = _random_hypers(rng, X, 3)
    Xq = np.vstack([rng.normal(size=(25, P)) * X.std(axis=0) + X.mean(axis=0), X[:5]])
    gp = GaussianProcess(X, Y, hypers)
    mean, var = gp.predict(Xq)
    mean2, var2, _, _ = gp.predict_with_grad(Xq)
    assert mean.shape == var.shape == (len(Xq), 3)
    for j, h in enumerate(hypers):
        ref = _sklearn_exact(X, Y[:, j], h)
        m_ref, s_ref = ref.predict(Xq, return_std=True)
        np.testing.assert_allclose(mean[:, j], m_ref, rtol=1e-6, atol=1e-8)
        np.testing.assert_allclose(var[:, j], s_ref ** 2, rtol=1e-6, atol=1e-8)
        np.testing.assert_allclose(mean2[:, j], m_ref, rtol=1e-6, atol=1e-8)
        np.testing.assert_allclose(var2[:, j], s_ref ** 2, rtol=1e-6, atol=1e-8)
        assert log_marginal_likelihood(X, Y[:, j], h) == pytest.approx(ref.log_marginal_likelihood_value_,
                                                                       rel=1e-6, abs=1e-6)


# --- gradients -------------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_lml_gradient_matches_central_differences(seed):
    rng = np.random.default_rng(10 + seed)
    X, Y = _data(rng, n=80, d=3)
    for j, h in enumerate(_random_hypers(rng, X, 3)):
        f, g = log_marginal_likelihood(X, Y[:, j], h, with_grad=True)
        assert f == pytest.approx(log_marginal_likelihood(X, Y[:, j], h))
        theta, eps = h.to_log(), 1e-5
        fd = np.array([(log_marginal_likelihood(X, Y[:, j], SEHyper.from_log(theta + eps * e))
                        - log_marginal_likelihood(X, Y[:, j], SEHyper.from_log(theta - eps * e))) / (2 * eps)
                       for e in np.eye(len(theta))])
        np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-5 * max(1.0, np.abs(fd).max()))


@pytest.mark.parametrize("seed", [0, 1])
def test_query_gradients_match_central_differences(seed):
    rng = np.random.default_rng(20 + seed)
    X, Y = _data(rng, n=100, d=3)
    gp = GaussianProcess(X, Y, _random_hypers(rng, X, 3))
    Xq = np.vstack([X[:3] + 0.1 * rng.normal(size=(3, P)),
                    rng.normal(size=(7, P)) * X.std(axis=0) + X.mean(axis=0)])
    mean, var, dmean, dvar = gp.predict_with_grad(Xq)
    assert dmean.shape == dvar.shape == (10, 3, P)
    eps = 1e-6
    for k in range(P):
        e = np.zeros(P)
        e[k] = eps * max(1.0, X[:, k].std())
        mp, vp = gp.predict(Xq + e)
        mm, vm = gp.predict(Xq - e)
        np.testing.assert_allclose(dmean[:, :, k], (mp - mm) / (2 * e[k]), rtol=1e-5, atol=1e-7)
        np.testing.assert_allclose(dvar[:, :, k], (vp - vm) / (2 * e[k]), rtol=1e-5, atol=1e-7)
    # the one-point path the NMPC rollout uses: the same mean and gradient
    for i, x in enumerate(Xq):
        g, Dg = gp.mean_and_grad(x)
        np.testing.assert_allclose(g, mean[i], rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(Dg, dmean[i], rtol=1e-9, atol=1e-12)


# --- fitting ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", [0, 1])
def test_fit_reaches_at_least_sklearn_lml(seed):
    """Same data, same number of restarts: our optimum is at least as good as scikit-learn's
    C * RBF(ARD) + WhiteKernel fit, both scored by the same exact LML."""
    rng = np.random.default_rng(seed)
    n, p, restarts = 250, 4, 2
    X = rng.uniform(-2.0, 2.0, size=(n, p))
    Y = np.column_stack([np.sin(1.5 * X[:, 0]) * np.cos(X[:, 1]) + 0.3 * X[:, 2] ** 2,
                         np.tanh(X[:, 0] + X[:, 1]) - 0.5 * np.sin(2.0 * X[:, 3])]) + 0.1 * rng.normal(size=(n, 2))
    fit = fit_hyperparameters(X, Y, restarts=restarts, rng=np.random.default_rng(seed), max_points=1000)
    assert fit.n_used == n and fit.restarts == restarts and len(fit.hypers) == 2 and fit.seconds > 0
    for j in range(2):
        kernel = ConstantKernel(1.0) * RBF(np.ones(p)) + WhiteKernel()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ref = sk_gp.GaussianProcessRegressor(kernel=kernel, n_restarts_optimizer=restarts,
                                                 random_state=seed).fit(X, Y[:, j])
        k = ref.kernel_
        h_sk = SEHyper(k.k1.k2.length_scale, math.sqrt(k.k1.k1.constant_value), math.sqrt(k.k2.noise_level))
        lml_sk = log_marginal_likelihood(X, Y[:, j], h_sk)
        lml_ours = log_marginal_likelihood(X, Y[:, j], fit.hypers[j])
        assert fit.lml[j] == pytest.approx(lml_ours, rel=1e-9)
        assert lml_ours >= lml_sk - 1e-6 * abs(lml_sk), (j, lml_ours, lml_sk)


def test_fit_is_deterministic_uses_init_and_stays_in_bounds():
    rng = np.random.default_rng(3)
    X, Y = _data(rng, n=120, p=3, d=2)
    a = fit_hyperparameters(X, Y, restarts=1, rng=np.random.default_rng(7))
    b = fit_hyperparameters(X, Y, restarts=1, rng=np.random.default_rng(7))
    assert a.hypers == b.hypers and a.lml == b.lml
    # starting from the optimum cannot end lower, even without restarts
    c = fit_hyperparameters(X, Y, restarts=0, rng=np.random.default_rng(8), init=a.hypers)
    assert all(lc >= la - 1e-9 * abs(la) for lc, la in zip(c.lml, a.lml))
    for j, h in enumerate(a.hypers):
        bnd = hyper_bounds(X - X.mean(axis=0), Y[:, j])
        assert np.all(h.to_log() >= bnd[:, 0] - 1e-9) and np.all(h.to_log() <= bnd[:, 1] + 1e-9)


def test_floors_and_ceilings_bound_the_lengthscales_and_equal_ones_hold_them():
    """min_lengthscales / max_lengthscales: the fitted lengthscales stay within them; a floor equal to its
    ceiling holds that lengthscale whatever the data say; inf leaves an input without a ceiling."""
    rng = np.random.default_rng(5)
    X, Y = _data(rng, n=120, p=3, d=2)
    free = fit_hyperparameters(X, Y, restarts=1, rng=np.random.default_rng(7))
    floors = np.array([0.0, 0.7, 0.0])
    ceilings = np.array([[np.inf, 0.7, 0.05], [np.inf, 0.7, 0.05]])
    held = fit_hyperparameters(X, Y, restarts=1, rng=np.random.default_rng(7), min_lengthscales=floors,
                               max_lengthscales=ceilings)
    for h in held.hypers:
        assert h.lengthscales[1] == pytest.approx(0.7)
        assert h.lengthscales[2] <= 0.05 * (1 + 1e-9)
    assert all(h.lengthscales[2] > 0.05 for h in free.hypers)   # the ceiling did bind
    assert all(lh <= lf + 1e-9 * abs(lf) for lh, lf in zip(held.lml, free.lml))


def test_fit_subsamples_above_max_points():
    rng = np.random.default_rng(4)
    X, Y = _data(rng, n=400, p=3, d=1)
    fit = fit_hyperparameters(X, Y, restarts=0, rng=np.random.default_rng(0), max_points=150)
    assert fit.n_used == 150
    assert np.isfinite(fit.lml[0])


# --- edge cases ------------------------------------------------------------------------------------
def test_no_data_gives_the_prior():
    hypers = [SEHyper(np.ones(P), 0.7, 0.1), SEHyper(np.full(P, 2.0), 1.5, 0.2), SEHyper(np.ones(P), 0.2, 0.01)]
    gp = GaussianProcess(np.zeros((0, P)), np.zeros((0, 3)), hypers)
    Xq = np.random.default_rng(0).normal(size=(6, P))
    mean, var = gp.predict(Xq)
    m2, v2, dm, dv = gp.predict_with_grad(Xq)
    np.testing.assert_array_equal(mean, 0.0)
    np.testing.assert_array_equal(m2, 0.0)
    np.testing.assert_allclose(var, np.tile([0.49, 2.25, 0.04], (6, 1)))
    np.testing.assert_allclose(v2, var)
    assert dm.shape == dv.shape == (6, 3, P)
    np.testing.assert_array_equal(dm, 0.0)
    np.testing.assert_array_equal(dv, 0.0)
    assert log_marginal_likelihood(np.zeros((0, P)), np.zeros(0), hypers[0]) == 0.0
    fit = fit_hyperparameters(np.zeros((0, P)), np.zeros((0, 3)), restarts=2, rng=np.random.default_rng(0))
    assert fit.n_used == 0 and len(fit.hypers) == 3 and fit.lml == [0.0, 0.0, 0.0]


def test_coverage_is_the_kernel_correlation_to_the_nearest_training_input():
    rng = np.random.default_rng(3)
    X, Y = _data(rng, n=60)
    hypers = _random_hypers(rng, X, 3)
    gp = GaussianProcess(X, Y, hypers)
    Xq = np.vstack([X[:3], X[:3] + 0.3, rng.normal(size=(4, P)) * 50.0])
    mean, var, near = gp.predict(Xq, coverage=True)
    m2, v2 = gp.predict(Xq)
    np.testing.assert_array_equal(mean, m2)
    np.testing.assert_array_equal(var, v2)
    for j, h in enumerate(hypers):
        d2 = (((Xq[:, None, :] - X[None, :, :]) / h.lengthscales) ** 2).sum(axis=2)
        np.testing.assert_allclose(near[:, j], np.exp(-0.5 * d2).max(axis=1), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(near[:3], 1.0)           # on a training input
    assert np.all(near[6:] < 1e-6)                      # far from all of them


def test_ill_conditioned_data_gives_no_nan():
    rng = np.random.default_rng(5)
    X = rng.normal(size=(40, P))
    X = np.vstack([X, X, X[:10]])                     # exact duplicate inputs
    X[:, 4] = 1.0                                     # a constant input
    y = np.sin(X[:, 0]) + X[:, 1]                     # noiseless
    Y = np.column_stack([y, y + 1e-12 * rng.normal(size=len(y))])
    tiny = [SEHyper(np.full(P, 3.0), 1.0, 1e-9), SEHyper(np.full(P, 50.0), 10.0, 1e-10)]
    gp = GaussianProcess(X, Y, tiny)
    Xq = np.vstack([X[:5], rng.normal(size=(5, P))])
    for out in (*gp.predict(Xq), *gp.predict_with_grad(Xq)):
        assert np.all(np.isfinite(out))
    assert np.all(gp.predict(Xq)[1] >= 0.0)
    for h in tiny:
        f, g = log_marginal_likelihood(X, y, h, with_grad=True)
        assert not math.isnan(f) and not np.any(np.isnan(g))
    fit = fit_hyperparameters(X, Y, restarts=2, rng=np.random.default_rng(0))
    assert all(np.all(np.isfinite(h.to_log())) for h in fit.hypers)
    assert all(not math.isnan(v) for v in fit.lml)
    gp2 = GaussianProcess(X, Y, fit.hypers)
    assert np.all(np.isfinite(gp2.predict_with_grad(Xq)[0]))


def test_non_finite_rows_are_dropped():
    rng = np.random.default_rng(6)
    X, Y = _data(rng, n=60, p=3, d=2)
    hypers = _random_hypers(rng, X, 2)
    Xb, Yb = X.copy(), Y.copy()
    Xb[3, 1] = np.nan
    Yb[7, 0] = np.inf
    keep = np.ones(60, bool)
    keep[[3, 7]] = False
    Xq = rng.normal(size=(4, 3))
    for a, b in zip(GaussianProcess(Xb, Yb, hypers).predict(Xq), GaussianProcess(X[keep], Y[keep], hypers).predict(Xq)):
        np.testing.assert_allclose(a, b, rtol=1e-12)
    fit = fit_hyperparameters(Xb, Yb, restarts=0, rng=np.random.default_rng(0))
    assert fit.n_used == 58 and all(np.isfinite(fit.lml))


def test_controller_sized_query_is_fast():
    """N = 180 experiences, M = 10 horizon points, d = 3, p = 9: well under a millisecond budget each."""
    rng = np.random.default_rng(7)
    X, Y = _data(rng, n=180, d=3)
    gp = GaussianProcess(X, Y, _random_hypers(rng, X, 3))
    Xq = X[:10] + 0.05
    times = []
    for _ in range(200):
        t0 = time.perf_counter()
        gp.predict_with_grad(Xq)
        times.append(time.perf_counter() - t0)
    assert np.median(times) < 5e-3      # typically ~0.3 ms; generous for loaded CI machines

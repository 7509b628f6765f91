"""`lbc bench gp --n N`: GP hyperparameter fitting (thesis 5.2.3) against scikit-learn, on realistic data.

Data: N one-step disturbance observations from the project's own simulator, exactly as the running
controller makes them (`services.controller.experience`, eq. 5.15 and 5.17: route coordinates, body
velocities from consecutive estimates, current and previous commands in `a`; the unicycle residual in
the body frame as `g`; p = 9, d = 3). A Husky is taught the 33 m route of examples/husky-sideslope.toml
(a 12 degree sandy side slope with a slip patch), then repeats it with the feedback-linearized tracker
at several speeds (0.3 to 1.0 m/s), through `bench.closed_loop.ClosedLoop`: the services' pure cores
without the bus, with the `pose` localizer's default noise (1 cm, 0.3 degrees). Trials cycle through
the speeds until at least N observations exist (every speed at least once); N are drawn at random.

Comparison (DESIGN.md, "Benchmarks"): the project fits all N by its own method (`fit_hyperparameters`:
exact, on a random subsample of `--max-points` rows when N is larger); E is a fixed random evaluation
set of min(N, 1000) observations; scikit-learn's GaussianProcessRegressor with the same kernel family
(ConstantKernel * RBF(ARD) + WhiteKernel, one regressor per output dimension as in the thesis), the
same initial values, bounds and number of random restarts, is fitted exactly on E. `lml` and
`sklearn_lml` are both the exact log marginal likelihood on E summed over the output dimensions, at
each method's hyperparameters, evaluated by the same function. `sklearn_*` are null only if
scikit-learn is not importable. Progress goes to stderr; the last stdout line is one JSON object.

Besides, `store_method_*` report what the experience store itself runs (the likelihood of its local
windows, with physical floors on the lengthscales; see services/gp_store/config.py): the model the
controller predicts from, regularized against closed-loop data, so its exact LML on E is lower than
the unconstrained optimum by design.

Both fits run under the same BLAS thread limit, `--blas-threads` (default 1; 0 leaves the library
default), applied with threadpoolctl when it is installed (it comes with scikit-learn): on a small
shared machine, multi-threaded OpenBLAS on matrices of this size was measured several times slower
than one thread (N = 1000 Cholesky plus inverse: ~56 ms single-threaded, ~300 ms with 2 threads
under load), which would only measure contention.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
import warnings
from contextlib import nullcontext
from dataclasses import dataclass

import numpy as np

from bench.closed_loop import ClosedLoop
from common.gp import SEHyper, fit_hyperparameters, heuristic_hyper, hyper_bounds, log_marginal_likelihood
from common.scenario import TerrainPatch
from services.controller.experience import G_NAMES
from services.gp_store.config import FitConfig
from common.bins import BinPolicy
from services.localizer.pose_source import PoseSourceSettings

DT = 0.1
EVAL_MAX = 1000
ROUTE = [[0.0, 0.0], [10.0, 0.0], [20.0, 6.0], [30.0, 6.0]]
TERRAIN = [
    TerrainPatch(kind="side_slope", center=(15.0, 2.0), radius_m=5.0, slope_deg=12.0, downhill_deg=90.0),
    TerrainPatch(kind="slip", center=(15.0, 2.0), radius_m=4.0, traction=0.7),
]
SPEEDS = (0.3, 1.0, 0.5, 0.8, 0.4, 0.9, 0.6, 0.7)   # interleaved so that a few trials span the range


def _log(msg: str) -> None:
    print(f"[bench.gp] {msg}", file=sys.stderr, flush=True)


@dataclass(frozen=True)
class Observations:
    """N disturbance observations and how they were made."""
    A: np.ndarray          # (n, 9): a of eq. 5.15
    G: np.ndarray          # (n, 3): g of eq. 5.17
    tiles: np.ndarray      # (n,): the store's window tile of each (services/gp_store/db.py, all_of)
    trials: int            # simulated repeats
    pool: int              # observations they yielded, of which n were drawn
    sim_s: float           # wall time of teach and repeats, rounded to ms


def generate(n: int, seed: int, speeds=SPEEDS) -> Observations:
    """N disturbance observations drawn from simulated repeats (see the module doc)."""
    data = ClosedLoop(ROUTE, TERRAIN, preset="husky", seed=seed, loc=PoseSourceSettings(), period_s=DT)
    t0 = time.perf_counter()
    data.teach()
    _log(f"taught a {data.path.length_m:.1f} m route ({len(data.path)} vertices) in {time.perf_counter() - t0:.1f} s")
    As, Gs, tiles, total, trial = [], [], [], 0, 0
    policy = BinPolicy()
    while total < n or trial < len(speeds):
        speed = speeds[trial % len(speeds)]
        trial += 1
        t1 = time.perf_counter()
        rep = data.repeat(trial, speed)
        A, G = rep.arrays()
        As.append(A)
        Gs.append(G)
        tiles += [(o.vertex // (2 * policy.c_vertex + 1)) * 100_000
                  + policy.speed_bin(o.v_cmd_mps) // (2 * policy.c_velocity + 1) for o in rep.observations]
        total += len(A)
        _log(f"trial {trial} at {speed:.2f} m/s: {len(A)} observations ({total} total) "
             f"in {time.perf_counter() - t1:.1f} s")
        if trial > 10 * len(speeds) + 1000 and total == 0:
            raise RuntimeError("the simulated repeats yield no observations")
    A, G = np.concatenate(As), np.concatenate(Gs)
    pick = np.sort(np.random.default_rng([seed, 21]).choice(len(A), size=n, replace=False))
    return Observations(A=A[pick], G=G[pick], tiles=np.asarray(tiles)[pick], trials=trial, pool=int(len(A)),
                        sim_s=round(time.perf_counter() - t0, 3))


def _sklearn_fit(X: np.ndarray, Y: np.ndarray, restarts: int, seed: int) -> tuple[list[SEHyper], float, list[float]]:
    """One scikit-learn regressor per output dimension, same kernel family, start, bounds and restarts."""
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

    hypers, own_lml, seconds = [], [], 0.0
    Xc = X - X.mean(axis=0)
    for j in range(Y.shape[1]):
        y = Y[:, j]
        b = hyper_bounds(Xc, y)
        h0 = heuristic_hyper(Xc, y)
        p = X.shape[1]
        kernel = (ConstantKernel(h0.signal_std ** 2, (math.exp(2 * b[p, 0]), math.exp(2 * b[p, 1])))
                  * RBF(h0.lengthscales.copy(), np.exp(b[:p]))
                  + WhiteKernel(h0.noise_std ** 2, (math.exp(2 * b[p + 1, 0]), math.exp(2 * b[p + 1, 1]))))
        gpr = GaussianProcessRegressor(kernel=kernel, alpha=1e-10, n_restarts_optimizer=restarts,
                                       normalize_y=False, random_state=seed + j)
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            gpr.fit(X, y)
        seconds += time.perf_counter() - t0
        k = gpr.kernel_
        hypers.append(SEHyper(np.atleast_1d(k.k1.k2.length_scale), math.sqrt(k.k1.k1.constant_value),
                              math.sqrt(k.k2.noise_level)))
        own_lml.append(float(gpr.log_marginal_likelihood_value_))
    return hypers, seconds, own_lml


def _finite(v: float) -> float | None:
    return float(v) if v is not None and math.isfinite(v) else None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="lbc bench gp", description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=2000, help="number of experiences (default 2000)")
    ap.add_argument("--restarts", type=int, default=3,
                    help="random restarts per output dimension, for both methods (default 3)")
    ap.add_argument("--max-points", type=int, default=1000,
                    help="the project fits on a random subsample of this many when N is larger (default 1000)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--blas-threads", type=int, default=1,
                    help="BLAS threads for both fits (default 1; 0 = library default)")
    args = ap.parse_args(argv)
    if args.n < 2:
        ap.error("--n must be >= 2")
    limit, blas_threads = nullcontext(), None
    if args.blas_threads > 0:
        try:
            from threadpoolctl import threadpool_limits
            limit, blas_threads = threadpool_limits(limits=args.blas_threads, user_api="blas"), args.blas_threads
        except ImportError:
            _log("threadpoolctl is not installed: BLAS keeps its default thread count")
    with limit:
        return _run(args, blas_threads)


def _run(args, blas_threads: int | None) -> int:

    obs = generate(args.n, args.seed)
    X, Y = obs.A, obs.G
    _log(f"{len(X)} observations from {obs.trials} trials (pool {obs.pool}), "
         f"rms g = {np.sqrt(np.mean(Y ** 2, axis=0)).round(5).tolist()}")

    rng = np.random.default_rng([args.seed, 31])
    eval_idx = np.sort(rng.choice(len(X), size=min(len(X), EVAL_MAX), replace=False))
    XE, YE = X[eval_idx], Y[eval_idx]

    _log(f"fitting {Y.shape[1]} GPs on {len(X)} points (max_points {args.max_points}, "
         f"1 + {args.restarts} starts each)")
    fit = fit_hyperparameters(X, Y, restarts=args.restarts, rng=np.random.default_rng([args.seed, 32]),
                              max_points=args.max_points)
    fit_s = fit.seconds
    lml_dims = [log_marginal_likelihood(XE, YE[:, j], h) for j, h in enumerate(fit.hypers)]
    lml = float(sum(lml_dims))
    _log(f"project: {fit_s:.2f} s on {fit.n_used} points, LML on E = {lml:.3f} ({[round(v, 3) for v in lml_dims]})")
    for name, h in zip(G_NAMES, fit.hypers):
        _log(f"  {name}: {h}")

    # what the experience store runs: the likelihood of its local windows with physical lengthscale
    # floors (services/gp_store): a deliberately different objective, so its exact LML on E is lower
    store = fit_hyperparameters(X, Y, restarts=args.restarts, rng=np.random.default_rng([args.seed, 33]),
                                max_points=args.max_points, groups=obs.tiles,
                                min_lengthscales=np.asarray(FitConfig().floors(teach_only=False)))
    store_lml = float(sum(log_marginal_likelihood(XE, YE[:, j], h) for j, h in enumerate(store.hypers)))
    _log(f"store's method (local windows, floors): {store.seconds:.2f} s, LML on E = {store_lml:.3f}")

    sk_fit_s = sk_lml = gap = None
    sk_dims = sk_own = None
    try:
        import sklearn  # noqa: F401
        have_sklearn = True
    except ImportError:
        have_sklearn = False
        _log("scikit-learn is not installed: sklearn_* are null")
    if have_sklearn:
        _log(f"fitting scikit-learn on E ({len(XE)} points, n_restarts_optimizer={args.restarts})")
        sk_hypers, sk_fit_s, sk_own = _sklearn_fit(XE, YE, args.restarts, args.seed)
        sk_dims = [log_marginal_likelihood(XE, YE[:, j], h) for j, h in enumerate(sk_hypers)]
        sk_lml = float(sum(sk_dims))
        gap = 100.0 * (sk_lml - lml) / abs(sk_lml) if sk_lml != 0 else 0.0
        _log(f"scikit-learn: {sk_fit_s:.2f} s, LML on E = {sk_lml:.3f} ({[round(v, 3) for v in sk_dims]})")

    out = {
        "n": int(args.n),
        "fit_s": round(fit_s, 4),
        "lml": _finite(lml),
        "sklearn_fit_s": None if sk_fit_s is None else round(sk_fit_s, 4),
        "sklearn_lml": _finite(sk_lml),
        "lml_gap_pct": _finite(gap),
        "n_used": int(fit.n_used),
        "restarts": int(args.restarts),
        "eval_n": int(len(XE)),
        "p": int(X.shape[1]),
        "d": int(Y.shape[1]),
        "lml_dims": [_finite(v) for v in lml_dims],
        "sklearn_lml_dims": None if sk_dims is None else [_finite(v) for v in sk_dims],
        "sklearn_own_lml": None if sk_own is None else _finite(sum(sk_own)),
        "max_points": int(args.max_points),
        "seed": int(args.seed),
        "blas_threads": blas_threads,
        "trials": obs.trials,
        "sim_s": obs.sim_s,
        "store_method_fit_s": round(store.seconds, 4),
        "store_method_lml": _finite(store_lml),
        "store_method_lml_gap_pct": _finite(100.0 * (sk_lml - store_lml) / abs(sk_lml)) if sk_lml else None,
    }
    print(json.dumps(out), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

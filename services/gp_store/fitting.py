"""Offline GP hyperparameter fitting for one route (thesis 5.2.3), run in a worker process so that the
store keeps answering queries; the worker gets arrays in and returns a `FitResult` (plain, picklable
values) out."""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from common.gp import SEHyper, fit_hyperparameters, subsample_rows
from common.messages import HyperDim, HyperMsg
from common.turn_share import HEADING
from services.gp_store.authority import AuthorityRule, turn_authority, turn_free


@dataclass(frozen=True, kw_only=True)
class FitResult:
    """One fit of a route's hyperparameters, before the store gives it a version."""
    path_id: str
    n_used: int                   # experiences the likelihood was maximized on (a subsample above max_points)
    n_total: int                  # experiences of the fitted model on file
    fit_s: float                  # wall time of the optimization, in the worker
    lml: tuple[float, ...]        # log marginal likelihood per output dimension of g
    dims: tuple[HyperDim, ...]    # hyperparameters per output dimension of g
    note: str = ""                # what the store changed after the likelihood's fit, and why ("": nothing)

    def message(self, *, version: int, stamp_s: float, model: str = "") -> HyperMsg:
        """The HyperMsg of this fit as version `version` for nominal model `model`."""
        return HyperMsg(stamp_s=stamp_s, path_id=self.path_id, version=version, n_used=self.n_used,
                        n_total=self.n_total, fit_s=self.fit_s, lml=list(self.lml), dims=list(self.dims), model=model,
                        note=self.note)


def fit_route(path_id: str, A: np.ndarray, G: np.ndarray, tiles: np.ndarray | None, restarts: int,
              max_points: int, seed: int, init: list[HyperDim] | None,
              min_lengthscales: list[float] | list[list[float]] | None,
              authority: AuthorityRule | None = None,
              max_lengthscales: list[list[float]] | None = None) -> FitResult:
    """Maximize the log marginal likelihood per output dimension, from `init` (a previous fit's
    dimensions) if given.

    With `tiles`, the likelihood is that of the local windows the controller predicts from (each an
    independent GP), so the hyperparameters describe how the disturbance varies *within* a place;
    `min_lengthscales` are the physical floors (FitConfig.floors: one row per output, or one for all),
    `max_lengthscales` the ceilings (FitConfig.ceilings). With `authority`, a heading model that
    takes the steering away from the controller is refitted without the turn-rate inputs (authority.py)."""
    t0 = time.perf_counter()
    hypers = None
    if init:
        hypers = [SEHyper(np.asarray(d.lengthscales, dtype=float), d.signal_std, d.noise_std) for d in init]
    floors = np.asarray(min_lengthscales, dtype=float) if min_lengthscales else None
    res = fit_hyperparameters(A, G, restarts=restarts, rng=np.random.default_rng(seed), max_points=max_points,
                              init=hypers, groups=tiles, min_lengthscales=floors,
                              max_lengthscales=None if max_lengthscales is None else np.asarray(max_lengthscales))
    fitted, lml, note = list(res.hypers), list(res.lml), ""
    if authority is not None and len(A):
        rows = np.arange(len(A)) if len(A) <= max_points else subsample_rows(len(A), tiles, max_points,
                                                                                np.random.default_rng(seed))
        check = turn_authority(A[rows], G[rows, HEADING], None if tiles is None else tiles[rows],
                               fitted[HEADING], authority)
        if not check.passed:
            off, start = turn_free(fitted[HEADING], authority.off_lengthscale)
            if floors is not None:
                off = np.maximum(off, floors[HEADING] if floors.ndim == 2 else floors)
            again = fit_hyperparameters(A, G[:, HEADING:HEADING + 1], restarts=restarts,
                                        rng=np.random.default_rng(seed), max_points=max_points, init=[start],
                                        groups=tiles, min_lengthscales=off)
            fitted[HEADING], lml[HEADING] = again.hypers[0], again.lml[0]
            note = f"{check.describe()}: its turn-rate inputs are switched off"
    dims = tuple(HyperDim(lengthscales=[float(v) for v in h.lengthscales], signal_std=float(h.signal_std),
                          noise_std=float(h.noise_std)) for h in fitted)
    return FitResult(path_id=path_id, n_used=int(res.n_used), n_total=int(len(A)), fit_s=time.perf_counter() - t0,
                     lml=tuple(float(x) for x in lml), dims=dims, note=note)


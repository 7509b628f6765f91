"""Offline GP hyperparameter fitting for one route (thesis 5.2.3), run in a worker process so that the
store keeps answering queries; the worker gets arrays in and returns plain data out."""
from __future__ import annotations

import time

import numpy as np

from common.gp import SEHyper, fit_hyperparameters


def fit_route(path_id: str, A: np.ndarray, G: np.ndarray, tiles: np.ndarray | None, restarts: int,
              max_points: int, seed: int, init: list[dict] | None, min_lengthscales: list[float] | None) -> dict:
    """Maximize the log marginal likelihood per output dimension; returns the body of a HyperMsg.

    With `tiles`, the likelihood is that of the local windows the controller predicts from (each an
    independent GP), so the hyperparameters describe how the disturbance varies *within* a place;
    `min_lengthscales` are the physical floors (see StoreConfig)."""
    t0 = time.perf_counter()
    hypers = [SEHyper.from_dict(d) for d in init] if init else None
    floors = np.asarray(min_lengthscales, dtype=float) if min_lengthscales else None
    res = fit_hyperparameters(A, G, restarts=restarts, rng=np.random.default_rng(seed), max_points=max_points,
                              init=hypers, groups=tiles, min_lengthscales=floors)
    return {"path_id": path_id, "n_used": int(res.n_used), "n_total": int(len(A)),
            "fit_s": time.perf_counter() - t0, "lml": [float(x) for x in res.lml],
            "dims": [h.to_dict() for h in res.hypers]}

"""Offline GP hyperparameter fitting for one route (thesis 5.2.3), run in a worker process so that the
store keeps answering queries; the worker gets arrays in and returns plain data out."""
from __future__ import annotations

import time

import numpy as np

from common.gp import SEHyper, fit_hyperparameters


def fit_route(path_id: str, A: np.ndarray, G: np.ndarray, restarts: int, max_points: int, seed: int,
              init: list[dict] | None) -> dict:
    """Maximize the log marginal likelihood per output dimension; returns the body of a HyperMsg."""
    t0 = time.perf_counter()
    hypers = [SEHyper.from_dict(d) for d in init] if init else None
    res = fit_hyperparameters(A, G, restarts=restarts, rng=np.random.default_rng(seed), max_points=max_points,
                              init=hypers)
    return {"path_id": path_id, "n_used": int(res.n_used), "n_total": int(len(A)),
            "fit_s": time.perf_counter() - t0, "lml": [float(x) for x in res.lml],
            "dims": [h.to_dict() for h in res.hypers]}

"""How well the learned disturbance model predicts a trial it has not seen (thesis figs. 5.12, 6.6).

Before trial j the store holds the experiences of trials < j and hyperparameters fitted on them. For
every experience of trial j, the disturbance is predicted the way the controller does it: a GP on the
local window of bins around its vertex and commanded speed (thesis 5.3.2), with the store's
hyperparameters. Observed against predicted, this is the model the controller would have used.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.gp import GaussianProcess, SEHyper
from common.messages import Experience, HyperMsg

DT_NOTE = "g per control period"


@dataclass
class DisturbanceSeries:
    trial: int
    hyper_version: int          # 0: no model yet (prior: zero mean)
    train_n: int
    s_m: np.ndarray             # distance along the route of each experience
    observed: np.ndarray        # (n, 3) g
    mean: np.ndarray            # (n, 3) predicted g
    std: np.ndarray             # (n, 3) predictive standard deviation of the latent g

    def rmse(self) -> tuple[np.ndarray, np.ndarray]:
        """Per output dimension: RMSE of the nominal model (predicts 0) and of the learned one."""
        if not len(self.observed):
            return np.zeros(3), np.zeros(3)
        return (np.sqrt(np.mean(self.observed ** 2, axis=0)),
                np.sqrt(np.mean((self.observed - self.mean) ** 2, axis=0)))


def predict_trial(trial: int, test: list[Experience], train: list[Experience], hyper: HyperMsg | None,
                  v_bin_mps: float, c_vertex: int, c_velocity: int) -> DisturbanceSeries:
    A = np.array([e.a for e in test], dtype=float).reshape(-1, 9)
    observed = np.array([e.g for e in test], dtype=float).reshape(-1, 3)
    mean = np.zeros_like(observed)
    std = np.zeros_like(observed)
    if hyper is None:
        return DisturbanceSeries(trial, 0, len(train), A[:, 0], observed, mean, std)
    hypers = [SEHyper(np.asarray(d.lengthscales), d.signal_std, d.noise_std) for d in hyper.dims]
    std[:] = [h.signal_std for h in hypers]
    bins: dict[tuple[int, int], list[int]] = {}
    for i, e in enumerate(train):
        bins.setdefault((e.vertex, int(np.floor(e.v_cmd_mps / v_bin_mps))), []).append(i)
    train_A = np.array([e.a for e in train], dtype=float).reshape(-1, 9)
    train_G = np.array([e.g for e in train], dtype=float).reshape(-1, 3)
    groups: dict[tuple[int, int], list[int]] = {}
    for i, e in enumerate(test):
        groups.setdefault((e.vertex, int(np.floor(e.v_cmd_mps / v_bin_mps))), []).append(i)
    for (vertex, l), rows in groups.items():
        idx = [j for v in range(vertex - c_vertex, vertex + c_vertex + 1)
               for b in range(l - c_velocity, l + c_velocity + 1) for j in bins.get((v, b), ())]
        gp = GaussianProcess(train_A[idx], train_G[idx], hypers)
        m, var = gp.predict(A[rows])
        mean[rows], std[rows] = m, np.sqrt(np.maximum(var, 0.0))
    return DisturbanceSeries(trial, hyper.version, len(train), A[:, 0], observed, mean, std)

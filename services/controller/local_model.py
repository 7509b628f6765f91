"""The disturbance model the NMPC uses at each step: a GP on the local window of experiences around
the middle of its horizon (thesis 5.3.2), with the store's latest hyperparameters.

A window's GP (three Cholesky factorizations) is built once and reused while the robot stays in it;
with no hyperparameters or no experiences there is no model, and the controller runs on the nominal
unicycle, which is exactly the thesis's first trial.
"""
from __future__ import annotations

from collections import OrderedDict
from typing import Callable

import numpy as np

from common.gp import GaussianProcess, SEHyper
from common.messages import HyperMsg
from services.controller.laws import StepContext

Window = tuple[np.ndarray, np.ndarray]     # (A (n, 9), G (n, 3))


def hypers_of(msg: HyperMsg) -> list[SEHyper]:
    return [SEHyper(np.asarray(d.lengthscales, dtype=float), d.signal_std, d.noise_std) for d in msg.dims]


class LocalModels:
    def __init__(self, window: Callable[[int, float], Window], hyper: Callable[[], HyperMsg | None],
                 horizon_s: float, v_bin_mps: float = 0.25, keep: int = 6):
        self.window = window
        self.hyper = hyper
        self.horizon_s = horizon_s
        self.v_bin = v_bin_mps
        self.keep = keep
        self._cache: OrderedDict[tuple, GaussianProcess] = OrderedDict()
        self.last_n = 0
        self.last_version = 0

    def center_vertex(self, ctx: StepContext) -> int:
        s_mid = ctx.s_m + 0.5 * ctx.v_mps * self.horizon_s
        return int(np.clip(np.searchsorted(ctx.path.s, s_mid), 0, len(ctx.path) - 1))

    def model_for(self, ctx: StepContext) -> GaussianProcess | None:
        h = self.hyper()
        if h is None:
            self.last_n = self.last_version = 0
            return None
        center = self.center_vertex(ctx)
        A, G = self.window(center, ctx.v_mps)
        self.last_n, self.last_version = len(A), h.version
        if len(A) == 0:
            return None
        key = (center, int(np.floor(ctx.v_mps / self.v_bin)), h.version, len(A), float(A[0, 0]), float(A[-1, 0]))
        gp = self._cache.get(key)
        if gp is None:
            gp = GaussianProcess(A, G, hypers_of(h))
            self._cache[key] = gp
            while len(self._cache) > self.keep:
                self._cache.popitem(last=False)
        else:
            self._cache.move_to_end(key)
        return gp

"""The disturbance model the NMPC uses at each step: a GP on the local window of experiences around
the middle of its horizon (thesis 5.3.2), with the store's latest hyperparameters.

A window's GP (three Cholesky factorizations) is built once and reused while the robot stays in it,
and a background thread builds the next window's GP before the robot gets there, so the control loop
rarely pays for it; with no hyperparameters or no experiences there is no model, and the controller
runs on the nominal unicycle, which is exactly the thesis's first trial.
"""
from __future__ import annotations

import logging
import queue
import threading
from collections import OrderedDict
from typing import Callable

import numpy as np

from common.gp import GaussianProcess, SEHyper
from common.messages import HyperMsg
from services.controller.laws import StepContext

Window = tuple[np.ndarray, np.ndarray]     # (A (n, 9), G (n, 3))


def hypers_of(msg: HyperMsg) -> list[SEHyper]:
    return [SEHyper(np.asarray(d.lengthscales, dtype=float), d.signal_std, d.noise_std) for d in msg.dims]


log = logging.getLogger(__name__)


class LocalModels:
    def __init__(self, window: Callable[[int, float], Window], hyper: Callable[[], HyperMsg | None],
                 horizon_s: float, v_bin_mps: float = 0.25, keep: int = 8, prebuild: bool = False):
        self.window = window
        self.hyper = hyper
        self.horizon_s = horizon_s
        self.v_bin = v_bin_mps
        self.keep = keep
        self._lock = threading.Lock()
        self._cache: OrderedDict[tuple, GaussianProcess] = OrderedDict()
        self.last_n = 0
        self.last_version = 0
        self.built_in_loop = 0
        self._todo: queue.Queue = queue.Queue(maxsize=8)
        self._thread = None
        if prebuild:
            self._thread = threading.Thread(target=self._prebuild, name="gp-prebuild", daemon=True)
            self._thread.start()

    def close(self) -> None:
        if self._thread is not None:
            self._todo.put(None)
            self._thread.join(timeout=5)
            self._thread = None

    def center_vertex(self, ctx: StepContext) -> int:
        s_mid = ctx.s_m + 0.5 * ctx.v_mps * self.horizon_s
        return int(np.clip(np.searchsorted(ctx.path.s, s_mid), 0, len(ctx.path) - 1))

    def _key(self, center: int, speed: float, h: HyperMsg, A: np.ndarray) -> tuple:
        return (center, int(np.floor(speed / self.v_bin)), h.version, len(A), float(A[0, 0]), float(A[-1, 0]))

    def _get(self, key: tuple) -> GaussianProcess | None:
        with self._lock:
            gp = self._cache.get(key)
            if gp is not None:
                self._cache.move_to_end(key)
            return gp

    def _put(self, key: tuple, gp: GaussianProcess) -> None:
        with self._lock:
            self._cache[key] = gp
            while len(self._cache) > self.keep:
                self._cache.popitem(last=False)

    def model_for(self, ctx: StepContext) -> GaussianProcess | None:
        h = self.hyper()
        if h is None:
            self.last_n = self.last_version = 0
            return None
        center = self.center_vertex(ctx)
        A, G = self.window(center, ctx.v_mps)
        self.last_n, self.last_version = len(A), h.version
        if self._thread is not None:   # the windows ahead, while this one is in use
            for ahead in (1, 2):
                try:
                    self._todo.put_nowait((center + ahead, ctx.v_mps, h))
                except queue.Full:
                    break
        if len(A) == 0:
            return None
        key = self._key(center, ctx.v_mps, h, A)
        gp = self._get(key)
        if gp is None:
            gp = GaussianProcess(A, G, hypers_of(h))
            self._put(key, gp)
            self.built_in_loop += 1
        return gp

    def _prebuild(self) -> None:
        while True:
            item = self._todo.get()
            if item is None:
                return
            center, speed, h = item
            try:
                A, G = self.window(center, speed)
                if len(A) == 0:
                    continue
                key = self._key(center, speed, h, A)
                if self._get(key) is None:
                    self._put(key, GaussianProcess(A, G, hypers_of(h)))
            except Exception:  # a failed prebuild only means the loop builds it itself
                log.exception("background GP build for vertex %d failed", center)

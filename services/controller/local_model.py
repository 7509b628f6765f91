"""The disturbance model the NMPC uses at each step: a GP on the local window of experiences around
the middle of its horizon (thesis 5.3.2), with the store's latest hyperparameters.

A window's GP (three Cholesky factorizations) is built once and reused while the robot stays in it.
The node builds the next step's window on its own thread once the command is out (`prepare`), so
entering a new window does not delay a command (not on another thread: Python threads contend for the
interpreter). With no hyperparameters or no experiences, or if a window's GP cannot be built, there is
no model and the controller runs on the nominal unicycle, which is exactly the thesis's first trial.
Below the slowest speed of a window's experiences its mean fades to zero at rest (rest_fade.py).
"""
from __future__ import annotations

import logging
from collections import OrderedDict
from typing import Callable

import numpy as np

from common.gp import GaussianProcess, SEHyper
from common.messages import HyperMsg
from services.controller.laws import StepContext
from services.controller.rest_fade import RestFaded
from services.controller.uncertainty import variance_gp

Window = tuple[np.ndarray, np.ndarray]     # (A (n, 9), G (n, 3))


def hypers_of(msg: HyperMsg) -> list[SEHyper]:
    return [SEHyper(np.asarray(d.lengthscales, dtype=float), d.signal_std, d.noise_std) for d in msg.dims]


log = logging.getLogger(__name__)


class LocalModels:
    def __init__(self, window: Callable[[int, float], Window], hyper: Callable[[], HyperMsg | None],
                 horizon_s: float, v_bin_mps: float, keep: int = 8, hold_steps: int = 0,
                 variance_caps: tuple[float, float, float] | None = None):
        self.window = window
        self.hyper = hyper
        self.horizon_s = horizon_s
        self.v_bin = v_bin_mps
        self.keep = keep
        self.hold_steps = hold_steps
        # set: also build each window's variance GP, with these lengthscale caps (uncertainty.variance_gp)
        self.variance_caps = variance_caps
        self._bin: int | None = None
        self._away = 0
        self._bin_with_data: int | None = None
        self._cache: OrderedDict[tuple, RestFaded] = OrderedDict()
        self.last_n = 0
        self.last_version = 0
        self.builds = 0
        self.prepared = 0          # of the builds, those done by `prepare` between steps
        self.failures = 0

    def center_vertex(self, ctx: StepContext) -> int:
        return self._center(ctx.path, ctx.s_m, ctx.v_mps)

    def _center(self, path, s_m: float, v_mps: float) -> int:
        s_mid = s_m + 0.5 * v_mps * self.horizon_s
        return int(np.clip(np.searchsorted(path.s, s_mid), 0, len(path) - 1))

    def speed_bin(self, speed: float) -> int:
        """The speed bin the window is drawn at. With `hold_steps`, it follows the speed with hysteresis:
        a jump of two bins or more moves it at once, a neighbouring bin only once the speed has stayed
        there for `hold_steps` calls. The window spans the bins on either side of its own, so the speed
        still has experience around it while the window holds. A law that chooses its own speed needs
        it: drawn straight at the commanded speed, a speed at a bin edge would flip the window between
        two datasets every step, and with them the speed the plan allows."""
        b = int(np.floor(speed / self.v_bin))
        if self.hold_steps <= 0 or self._bin is None or abs(b - self._bin) >= 2:
            self._bin, self._away = b, 0
        elif b != self._bin:
            self._away += 1
            if self._away >= self.hold_steps:
                self._bin, self._away = b, 0
        else:
            self._away = 0
        return self._bin

    def _key(self, center: int, speed: float, h: HyperMsg, A: np.ndarray) -> tuple:
        # the window's data identity too: a refetched window after new experiences is a new model
        return (center, int(np.floor(speed / self.v_bin)), h.version, len(A), float(A[0, 0]), float(A[-1, 0]),
                float(A[:, 3].sum()))

    def model_for(self, ctx: StepContext) -> RestFaded | None:
        h = self.hyper()
        if h is None:
            self.last_n = self.last_version = 0
            return None
        center = self.center_vertex(ctx)
        b = self.speed_bin(ctx.v_mps)
        speed, A, G = self._window_at(center, b)
        if len(A):
            self._bin_with_data = int(np.floor(speed / self.v_bin))
        self.last_n, self.last_version = len(A), h.version
        return self._gp(center, speed, h, A, G)

    def model_at(self, ctx: StepContext, speed_mps: float) -> RestFaded | None:
        """The GP of the window drawn at `speed_mps`'s own bin, centred where a plan at that speed goes,
        the held bin (speed_bin) left as it is: for a law that tests a speed it does not drive (the speed
        ladder's top rung, speed_ladder.py). None where that bin is the one the law's own window is drawn
        at, or its window holds no experience."""
        h, b = self.hyper(), int(np.floor(speed_mps / self.v_bin))
        if h is None or b == self._bin:
            return None
        center = self._center(ctx.path, ctx.s_m, speed_mps)
        speed = (b + 0.5) * self.v_bin
        A, G = self.window(center, speed)
        return self._gp(center, speed, h, A, G)

    def prepare(self, path, s_m: float, v_mps: float) -> None:
        """Build, between control steps, the GP of the window the next step will most likely ask for
        (where the robot will be after this command, at this speed; the speed bin as it stands): a new
        window's GP then no longer delays the command of the step that enters it. If the next
        step asks for another window after all, it builds that one itself, as without this call."""
        h = self.hyper()
        if h is None:
            return
        center = self._center(path, s_m, v_mps)
        b = self._bin if self.hold_steps > 0 and self._bin is not None else int(np.floor(v_mps / self.v_bin))
        speed, A, G = self._window_at(center, b)
        before = self.builds
        self._gp(center, speed, h, A, G)
        self.prepared += self.builds - before

    def _window_at(self, center: int, b: int) -> tuple[float, np.ndarray, np.ndarray]:
        """(the speed it is drawn at, A, G): the window of speed bin b around vertex `center`."""
        speed = (b + 0.5) * self.v_bin                                # the middle of the window's bin
        A, G = self.window(center, speed)
        if len(A) == 0 and self.hold_steps > 0 and self._bin_with_data not in (None, b):
            # a law that has just slowed far below where it has driven here: a window with no experience
            # would drop the learned mean too (a rut's pull hardly depends on speed) and plan on the bare
            # unicycle; the last speed's window still knows the place, and its variance at the new speed
            # is the prior's wherever the data are far (uncertainty.py)
            speed = (self._bin_with_data + 0.5) * self.v_bin
            A, G = self.window(center, speed)
        return speed, A, G

    def _gp(self, center: int, speed: float, h: HyperMsg, A: np.ndarray, G: np.ndarray) -> RestFaded | None:
        """The window's GP, from the cache or built now (None: no data, or it cannot be built)."""
        if len(A) == 0:
            return None
        key = self._key(center, speed, h, A)
        gp = self._cache.get(key)
        if gp is not None:
            self._cache.move_to_end(key)
            return gp
        try:
            gp = GaussianProcess(A, G, hypers_of(h))
        except (ValueError, np.linalg.LinAlgError) as exc:
            self.failures += 1
            log.warning("no model for the window at vertex %d (%s): nominal model this step", center, exc)
            return None
        if self.variance_caps is not None:
            variance_gp(gp, self.variance_caps)     # its variance's GP too, while between steps
        gp = RestFaded.of(gp, A)
        self.builds += 1
        self._cache[key] = gp
        while len(self._cache) > self.keep:
            self._cache.popitem(last=False)
        return gp

"""The learned disturbance fades to nothing at rest: below the slowest speed a window's experiences were
rolled at, the GP's mean is scaled by the speed over that speed (zero standing still).

The GP learns per-period residuals, and from data at one speed it cannot tell how they scale with
speed: below its data it holds them constant. A law that slows far below where it has driven (the speed
ladder of RC-LB-NMPC) then compensates, at a crawl, the whole per-period push a rut gave at speed,
although rolling a fifth of the distance the robot feels a fifth of it: on a rutted patch an Ackermann
steered full lock against a push that was not there and left its corridor. Pushes fixed to the place
(ruts, rough ground) scale with the distance rolled, so linearly; a slope's slide acts per second
instead, and the fade under-estimates it. Which of the two a window's push is, data at one speed cannot
tell: below the slowest speed the part the fade took away, (1 - f) |g|, is the mean's own uncertainty
(`gap`), which the variance adds. Without it a crawl onto a side slope looked safer than the speed
already driven there, and the speed ladder chose it (a ROC6 on a 14.5 deg slope slowed from 0.54 to
0.13 m/s and slid out sideways while its plan held the teach pass's crab). The speed is the rolled one,
a_3 (v_{j-1}): the push follows what the robot does, not the command its drive lags behind.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.gp import GaussianProcess

V_ACT = 3                    # a's rolled speed (experience.A_NAMES)
SLOWEST_PERCENTILE = 10.0    # a window's slowest speed: this percentile of its rolled speeds


@dataclass(frozen=True)
class RestFaded:
    """A window's GP with its mean faded below `v_floor` (m/s); its variance is the GP's."""
    gp: GaussianProcess
    v_floor: float

    @classmethod
    def of(cls, gp: GaussianProcess, A: np.ndarray) -> RestFaded:
        """`A` (n, 9): the window's inputs."""
        return cls(gp, float(np.percentile(np.abs(A[:, V_ACT]), SLOWEST_PERCENTILE)) if len(A) else 0.0)

    @property
    def hypers(self):
        return self.gp.hypers

    def factor(self, v: np.ndarray) -> np.ndarray:
        """The share of the mean kept at rolled speeds v."""
        if self.v_floor <= 0.0:
            return np.ones_like(v, dtype=float)
        return np.clip(np.asarray(v, dtype=float) / self.v_floor, 0.0, 1.0)

    def mean_and_grad(self, x) -> tuple[np.ndarray, np.ndarray]:
        g, dg = self.gp.mean_and_grad(x)
        v = float(x[V_ACT])
        if v >= self.v_floor:
            return g, dg
        f = max(v, 0.0) / self.v_floor
        dg = f * dg
        if v > 0.0:
            dg[:, V_ACT] += g / self.v_floor
        return f * g, dg

    def mean(self, A) -> np.ndarray:
        A = np.atleast_2d(np.asarray(A, dtype=float))
        return self.gp.mean(A) * self.factor(A[:, V_ACT])[:, None]

    def predict(self, A, coverage: bool = False):
        A = np.atleast_2d(np.asarray(A, dtype=float))
        mean, *rest = self.gp.predict(A, coverage)
        return (mean * self.factor(A[:, V_ACT])[:, None], *rest)

    def gap(self, A: np.ndarray, mean: np.ndarray) -> np.ndarray:
        """(n, 3) the part of the GP's mean the fade took away at inputs `A` (n, 9), whose faded mean is
        `mean` (n, 3): (1 - f) |g|; zero at and above the slowest speed."""
        A = np.atleast_2d(np.asarray(A, dtype=float))
        f = self.factor(A[:, V_ACT])[:, None]
        out = (1.0 - f) * np.abs(mean) / np.maximum(f, 1e-12)
        rest = f[:, 0] <= 0.0
        if rest.any():                      # nothing left of the mean to scale back: ask the GP
            out[rest] = np.abs(self.gp.mean(A[rest]))
        return out

    def capped(self, dims: tuple[int, ...], caps: tuple[float, ...]) -> RestFaded | GaussianProcess:
        """The GP under capped lengthscales, for its variance (uncertainty.variance_gp); itself where no
        lengthscale is capped, so that the variance and the mean still come from one prediction."""
        capped = self.gp.capped(dims, caps)
        return self if capped is self.gp else capped

    def mean_terms(self):
        """The GP's own mean terms (GaussianProcess.mean_terms); the fade is `factor` on a_3."""
        return self.gp.mean_terms()

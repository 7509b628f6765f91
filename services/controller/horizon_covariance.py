"""The covariance along the horizon (thesis 6.2.2, 7.3.2) for the uncertainty-aware laws: the
localizer's covariance carried through the localization delay (eq. 7.12), then the sigma-point
transform (uncertainty.py) along a planned mean sequence."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.controller.horizon import HorizonProblem, HorizonStart
from services.controller.settings import NMPCSettings
from services.controller.uncertainty import DisturbanceVariance, propagate, route_sigmas, sigma_point_step

DEFAULT_START_COV = np.diag([1e-4, 1e-4, 1e-4])   # when the localizer sends none


def variance_model(gp, s: NMPCSettings) -> DisturbanceVariance:
    return DisturbanceVariance(gp, s.prior_std(), s.process_std)


@dataclass(frozen=True)
class HorizonCovariance:
    """This step's covariance model: the disturbance variance, the covariance at the horizon's start, and
    the online calibration's factors on each step's predicted standard deviations (calibration.py)."""
    var: DisturbanceVariance
    Sigma0: np.ndarray
    dt: float
    gamma: float
    factors: np.ndarray | None = None

    @classmethod
    def at_start(cls, pose_cov: np.ndarray | None, start: HorizonStart, var: DisturbanceVariance, dt: float,
                 gamma: float, factors: tuple[float, ...] = ()) -> HorizonCovariance:
        """The localizer's covariance, carried through the periods of localization delay (eq. 7.12)."""
        Sigma = np.array(pose_cov, dtype=float) if pose_cov is not None else DEFAULT_START_COV.copy()
        if start.delay:
            G, V = var.with_mean(np.array([p.a for p in start.delay]))
            for p, g, vg in zip(start.delay, G, V):
                Sigma = sigma_point_step(p.pose, Sigma, g, vg, p.v_mps, p.w_radps, dt, gamma)
        return cls(var, Sigma, dt, gamma, np.asarray(factors, dtype=float) if factors else None)

    def widened(self, values: np.ndarray) -> np.ndarray:
        """Per-step standard deviations (or their derivatives), rows j = 1..K, times the calibration's factors."""
        if self.factors is None:
            return values
        f = np.ones(len(values))
        n = min(len(f), len(self.factors))
        f[:n] = self.factors[:n]
        return values * f.reshape((-1,) + (1,) * (values.ndim - 1))

    def along(self, problem: HorizonProblem, X: np.ndarray, A: np.ndarray, v: np.ndarray,
              w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Covariances (K+1, 3, 3) along the plan X with inputs A (K, 9), and the route-frame standard
        deviations (K, 3) of x_1..x_K (along, lateral, heading) as the model gives them (not widened)."""
        G, V = self.var.with_mean(A)
        vb, wb = problem.effective(v, w)          # the robot moves at these (the drive's lag)
        Sig = propagate(X, A, G, V, vb, wb, self.Sigma0, self.dt, self.gamma)
        return Sig, route_sigmas(Sig, problem.ref.direction_rad[1:])

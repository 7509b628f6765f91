"""The covariance along the horizon (thesis 6.2.2, 7.3.2) for the uncertainty-aware laws: the
localizer's covariance carried through the localization delay (eq. 7.12), then the sigma-point
transform (uncertainty.py) along a planned mean sequence.

The online calibration (calibration.py) widens only what the motion model adds: the localizer's own
covariance, carried rigidly along the plan, is not the model's to be wrong about. Widening the whole
spread would, at standstill, multiply the estimate's noise by factors learned from prediction errors
at speed, and a robot whose corridor is a few estimate-sigmas wide could never start again. The
calibration's floors (missed_variance.py) are variances in their own right, lateral and heading, added
to the model's share or under it; a plan sheds of them only what was missed faster than it drives."""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from services.controller.horizon import HorizonProblem, HorizonStart
from services.controller.missed_variance import SpreadFloors
from services.controller.settings import NMPCSettings
from services.controller.uncertainty import DisturbanceVariance, propagate, route_sigmas, sigma_point_step

DEFAULT_START_COV = np.diag([1e-4, 1e-4, 1e-4])   # when the localizer sends none


def variance_model(gp, s: NMPCSettings) -> DisturbanceVariance:
    return DisturbanceVariance(gp, s.prior_std(), s.process_std, s.vouch_lengthscales)


@dataclass(frozen=True)
class HorizonCovariance:
    """This step's covariance model: the disturbance variance, the covariance at the horizon's start, the
    online calibration's factors on each step's predicted standard deviations and its floors on each
    step's model share of the variance, lateral and heading (calibration.py)."""
    var: DisturbanceVariance
    Sigma0: np.ndarray
    dt: float
    gamma: float
    factors: np.ndarray | None = None
    Sigma_loc: np.ndarray = field(default_factory=DEFAULT_START_COV.copy)   # the localizer's, where captured
    captured_xy: tuple[float, float] = (0.0, 0.0)  # where it was captured (route frame)
    floors: SpreadFloors | None = None

    @classmethod
    def at_start(cls, pose_cov: np.ndarray | None, start: HorizonStart, var: DisturbanceVariance, dt: float,
                 gamma: float, factors: tuple[float, ...] = (),
                 floors: SpreadFloors | None = None) -> HorizonCovariance:
        """The localizer's covariance, carried through the periods of localization delay (eq. 7.12)."""
        Sigma = np.array(pose_cov, dtype=float) if pose_cov is not None else DEFAULT_START_COV.copy()
        loc, at = Sigma.copy(), (start.delay[0].pose if start.delay else start.x0)
        if start.delay:
            G, V = var.with_mean(np.array([p.a for p in start.delay]))
            for p, g, vg in zip(start.delay, G, V):
                Sigma = sigma_point_step(p.pose, Sigma, g, vg, p.v_mps, p.w_radps, dt, gamma)
        return cls(var, Sigma, dt, gamma, np.asarray(factors, dtype=float) if factors else None, loc,
                   (float(at[0]), float(at[1])), floors if floors is not None and floors.any() else None)

    def with_floors(self, floors: SpreadFloors | None) -> HorizonCovariance:
        """The same model with other floors (the calibration's at another plan speed)."""
        return replace(self, floors=floors if floors is not None and floors.any() else None)

    def localizer_part(self, X: np.ndarray, direction: np.ndarray) -> np.ndarray:
        """Route-frame standard deviations (K, 3) of x_1..x_K (measured along the route's `direction` (K,))
        that the localizer's covariance alone gives, carried rigidly along the plan X (K+1, 3): a heading
        error at the captured pose swings every later position about it,
        d(x, y)_j / d theta = (-(y_j - y_c), x_j - x_c)."""
        K = len(X) - 1
        J = np.zeros((K + 1, 3, 3))
        J[:, 0, 0] = J[:, 1, 1] = J[:, 2, 2] = 1.0
        J[:, 0, 2] = -(X[:, 1] - self.captured_xy[1])
        J[:, 1, 2] = X[:, 0] - self.captured_xy[0]
        return route_sigmas(J @ self.Sigma_loc @ J.transpose(0, 2, 1), direction)

    def _kappa(self, n_rows: int) -> np.ndarray:
        k = np.ones(n_rows)
        if self.factors is not None:
            n = min(n_rows, len(self.factors))
            k[:n] = np.square(self.factors[:n])
        return k

    def _floors(self, n_rows: int) -> tuple[np.ndarray, np.ndarray]:
        """(n_rows, 3) each: the calibration's added variance and least share per step, none along the route."""
        added, least = np.zeros((n_rows, 3)), np.zeros((n_rows, 3))
        if self.floors is not None:
            n = min(n_rows, len(self.floors.added))
            added[:n, 1:], least[:n, 1:] = self.floors.added[:n], self.floors.least[:n]
        return added, least

    def _model_var(self, sig: np.ndarray, loc: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(the localizer's variance, the model's, the model's widened: the largest of kappa_j share, share
        plus the added floor, and the least share)."""
        loc2 = np.minimum(np.square(loc), np.square(sig))
        share = np.square(sig) - loc2
        k = self._kappa(len(sig)).reshape(-1, 1)
        added, least = self._floors(len(sig))
        return loc2, share, np.maximum(np.maximum(k * share, share + added), least)

    def widened(self, sig: np.ndarray, loc: np.ndarray) -> np.ndarray:
        """Per-step standard deviations (K, 3): the model's share of the variance, sig^2 - loc^2, times the
        calibration's factor kappa_j or plus its added floor, whichever is larger, and at least its least
        share; plus the localizer's share `loc` as it is."""
        if self.factors is None and self.floors is None:
            return sig
        loc2, _, wide = self._model_var(sig, loc)
        return np.sqrt(loc2 + wide)

    def least(self, loc: np.ndarray) -> np.ndarray:
        """(K, 3): the least standard deviations of this model at any speed: the localizer's share `loc`
        and the calibration's floors (those of the plan speed they were taken at)."""
        added, least = self._floors(len(loc))
        return np.sqrt(np.square(loc) + np.maximum(added, least))

    def widened_derivative(self, dsig: np.ndarray, sig: np.ndarray, loc: np.ndarray) -> np.ndarray:
        """The derivative (rows j) of the widened lateral sigma from that of the model's, `dsig`, the
        localizer's share and the floors held fixed."""
        if self.factors is None and self.floors is None:
            return dsig
        loc2, share, wide = self._model_var(sig, loc)
        k = self._kappa(len(sig))
        added, least = self._floors(len(sig))
        slope = np.where(k * share[:, 1] >= share[:, 1] + added[:, 1], k, 1.0)
        slope = np.where(wide[:, 1] > least[:, 1], slope, 0.0)     # at the least share: no slope
        return dsig * (slope * sig[:, 1] / np.maximum(np.sqrt(loc2[:, 1] + wide[:, 1]), 1e-12)).reshape(-1, 1)

    def along(self, problem: HorizonProblem, X: np.ndarray, A: np.ndarray, v: np.ndarray,
              w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Covariances (K+1, 3, 3) along the plan X with inputs A (K, 9), and the route-frame standard
        deviations (K, 3) of x_1..x_K (along, lateral, heading) as the model gives them (not widened)."""
        G, V = self.var.with_mean(A)
        vb, wb = problem.effective(v, w)          # the robot moves at these (the drive's lag)
        Sig = propagate(X, A, G, V, vb, wb, self.Sigma0, self.dt, self.gamma)
        return Sig, route_sigmas(Sig, problem.ref.direction_rad[1:])

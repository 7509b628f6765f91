"""The predicted spread checked online against what happens, and widened where it is too narrow.

The uncertainty-aware laws (MM-, C-, RC-LB-NMPC) predict, at tick k, the robot's poses x_1..x_K with
their lateral and heading standard deviations along the route. When the estimate of tick k + j arrives,
the realized error of the prediction made for it, across the route and in heading, is normalized by
the spread the law expected plus the estimate's own:

    z_j = (x_estimate - x_predicted)_lateral, heading / sqrt(sigma_pred,j^2 + sigma_estimate^2)

A calibrated 3-sigma region holds all but ~0.3 % of them. The learned model can be over-confident (the
GP's posterior variance measures how well it knows its own data, not how well the world repeats), and
the a-priori one is a guess, so each horizon step j has a factor kappa_j >= 1 on its predicted
variance. Per step, because the errors of a wrong model are correlated in time: a bias grows linearly
over the horizon where independent disturbances grow with its square root, and one factor on the
per-period disturbance would widen the first steps (whose spread decides a stop) for the errors of
the last. A |z_j| > 3 raises kappa_j at once to what would have held it, 1.1 (z_j / 3)^2 times the
factor that prediction was made with (not compounded: the predictions in flight when a disturbance
appears all see it, and were all made before the first of them widened the spread); every contained
prediction lowers it by `DECAY`, down to 1. In equilibrium p ln(jump) = -(1 - p) ln(decay): with
decay = 0.999 and jumps >= 1.1 about 1 % of the predictions may leave their 3-sigma region.
Pure: inputs in, factors out.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

DECAY = 0.999            # per contained prediction
MAX_JUMP = 4.0           # the most a factor grows on one exceedance
MAX_SCALE = 400.0        # 20x the modelled standard deviation


@dataclass(frozen=True)
class Prediction:
    """One predicted pose (route frame) with its spread across the route and in heading."""
    step: int                 # j, 1..K: how many periods ahead it was predicted
    pose: tuple[float, float, float]
    normal: tuple[float, float]   # unit vector across the route there
    sigma_lat_m: float
    sigma_head_rad: float
    scale: float              # the factor of step j the spread was predicted with


class SpreadCalibration:
    def __init__(self, horizon: int, scales: np.ndarray | None = None):
        self.scales = np.ones(horizon) if scales is None else np.maximum(np.asarray(scales, dtype=float), 1.0)
        self.checked = np.zeros(horizon, dtype=int)
        self.outside = np.zeros(horizon, dtype=int)
        self._pending: dict[int, list[Prediction]] = {}

    def predict(self, tick: int, predictions: list[Prediction]) -> None:
        """The law's predictions of step k made at `tick`: prediction j is for the estimate of tick + j."""
        for p in predictions:
            self._pending.setdefault(tick + p.step, []).append(p)
        for old in [t for t in self._pending if t < tick - 200]:
            del self._pending[old]

    def realize(self, tick: int, pose, var_lat_m2: float, var_head_rad2: float) -> list[float]:
        """The estimate captured at `tick` (route frame) and its variances across the route and in
        heading: |z| of every prediction made for it."""
        out = []
        for p in self._pending.pop(tick, []):
            d = (pose[0] - p.pose[0]) * p.normal[0] + (pose[1] - p.pose[1]) * p.normal[1]
            z_lat = d / math.sqrt(p.sigma_lat_m ** 2 + var_lat_m2 + 1e-12)
            z_head = math.remainder(pose[2] - p.pose[2], 2 * math.pi) / math.sqrt(p.sigma_head_rad ** 2
                                                                                    + var_head_rad2 + 1e-12)
            out.append(self._update(p, max(abs(z_lat), abs(z_head))))
        return out

    def _update(self, p: Prediction, z: float) -> float:
        j = p.step - 1
        if j >= len(self.scales):
            return z
        self.checked[j] += 1
        if z > 3.0:
            self.outside[j] += 1
            needed = p.scale * min(MAX_JUMP, 1.1 * (z / 3.0) ** 2)
            self.scales[j] = min(MAX_SCALE, max(self.scales[j], needed))
        else:
            self.scales[j] = max(1.0, self.scales[j] * DECAY)
        return z

    def spread_factors(self) -> tuple[float, ...]:
        """sqrt(kappa_j): what each step's predicted standard deviations are multiplied by."""
        return tuple(float(x) for x in np.sqrt(self.scales))

"""The turn drive's acceleration limit, read off a repeat's own commands and wheel odometry.

The nominal model's turn drive is a first-order lag (actuator.py): a command step Delta w gets the
drive turning faster at Delta w / tau at once. A heavy skid-steer's drive also has a limit on that
acceleration (a 900 kg Grizzly: about 1 rad/s^2 where its 0.3 s lag alone would give 3 for a
1 rad/s step). A teach pass at walking pace hardly asks for it, so the teach pass's identification
(identification.py) rarely sees it; a repeat whose plans reverse the turn at a corner's exit does, and
there the model expects the turn to reverse several times faster than it does: the plan over-steers,
the heading overshoots and the next plans chase it (bench seed 6977, Grizzly s1602367998: 7-12 % of a
trial's periods asked for more than the limit, the heading swung to 10 deg on a straight).

Fit: with the model's lag tau held, the limit R of

    w' = clip((u - w) / tau, -R, R)

whose response to the trial's commands alone (each stretch started at its measured rate) is nearest
the odometry, by the output error over a grid of R; a finite R is taken only where it lowers that error
by FIT_GAIN against no limit (a drive that never met its limit fits as well without it). Holding tau
matters: fitted together, a small lag with a tight limit mimics a plain lag for small steps, and a Husky
that never met its 7.7 rad/s^2 read as 1.3 rad/s^2. Pure: arrays in, a fit out.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

GRID_RADPS2 = np.geomspace(0.2, 20.0, 47)   # candidate limits, ~10 % apart
SUBSTEPS = 10                                # the lag integrated within each period
FIT_GAIN = 0.15                              # a limit must lower the output error by this share
MIN_ASKING = 8                               # periods that asked for more than the fitted limit


@dataclass(frozen=True)
class TurnAccelFit:
    limit_radps2: float        # inf: no limit met
    rmse_radps: float          # output error with it (rad/s)
    rmse_free_radps: float     # and without a limit
    asking: int                # periods whose command asked the lag for more than the limit
    samples: int

    def describe(self) -> str:
        if math.isinf(self.limit_radps2):
            return (f"turn drive: no acceleration limit met ({self.samples} periods, output error "
                    f"{self.rmse_free_radps:.3f} rad/s)")
        return (f"turn drive: acceleration limit {self.limit_radps2:.2f} rad/s^2 met in {self.asking} of "
                f"{self.samples} periods (output error {self.rmse_free_radps:.3f} -> {self.rmse_radps:.3f} rad/s)")


def _runs(ok: np.ndarray) -> list[np.ndarray]:
    k = np.flatnonzero(ok)
    return np.split(k, np.flatnonzero(np.diff(k) != 1) + 1) if len(k) else []


def _responses(u: np.ndarray, y: np.ndarray, runs: list[np.ndarray], tau: float, dt: float,
               limits: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For every candidate limit (L,): the simulated rate at each step's end (L, n), the measured ones
    (n,), and the acceleration the lag asked for at each step's start (n,) (from the simulated rate of
    the unlimited drive)."""
    h = dt / SUBSTEPS
    sims, meas, asks = [], [], []
    for run in runs:
        w = np.full(len(limits), float(y[run[0]]))
        for k in run.tolist():
            asks.append(abs(u[k] - w[-1]) / tau)
            for _ in range(SUBSTEPS):
                w = w + h * np.clip((u[k] - w) / tau, -limits, limits)
            sims.append(w.copy())
            meas.append(y[k + 1])
    return np.array(sims).T, np.array(meas), np.array(asks)


def fit_turn_accel(u: np.ndarray, y: np.ndarray, dt: float, tau_s: float) -> TurnAccelFit | None:
    """u[k] the turn command held over period k, y[k] the odometry's turn rate at tick k (NaN: missing),
    tau_s the model's lag (> 0). None without enough data."""
    u, y = np.asarray(u, dtype=float), np.asarray(y, dtype=float)
    if tau_s <= 0.0 or len(u) < 2:
        return None
    ok = np.isfinite(u[:-1]) & np.isfinite(y[:-1]) & np.isfinite(y[1:])
    runs = _runs(ok)
    n = int(sum(len(r) for r in runs))
    if n < 5 * MIN_ASKING:
        return None
    limits = np.append(GRID_RADPS2, np.inf)
    sims, meas, asks = _responses(u, y, runs, tau_s, dt, limits)
    rmse = np.sqrt(np.mean((sims - meas[None, :]) ** 2, axis=1))
    free = float(rmse[-1])
    best = int(np.argmin(rmse[:-1]))
    asking = int(np.sum(asks > limits[best]))
    if rmse[best] > (1.0 - FIT_GAIN) * free or asking < MIN_ASKING:
        return TurnAccelFit(math.inf, free, free, 0, n)
    return TurnAccelFit(float(limits[best]), float(rmse[best]), free, asking, n)


@lru_cache(maxsize=8)
def _lead_matrix(beta: float, K: int) -> np.ndarray:
    j = np.arange(K)
    diff = j[:, None] - j[None, :]
    M = np.eye(K) - np.where(diff > 0, (1.0 - beta) * beta ** np.maximum(diff - 1, 0), 0.0)
    M.setflags(write=False)
    return M


@dataclass(frozen=True)
class TurnLead:
    """How far a turn command may lead the drive's state: the lag (time constant tau) answers a command
    u with the acceleration (u - xi) / tau, so |u_k - xi_k| <= R tau keeps it within the limit R, and the
    first-order model exact. Over a horizon xi_k = beta^k xi_0 + sum_{i<k} (1 - beta) beta^(k-1-i) u_i
    (actuator.py), so the leads are M u - beta^k xi_0, M = I - that sum's matrix."""
    beta: float
    max_radps: float

    @classmethod
    def of(cls, limit_radps2: float | None, tau_s: float, dt: float) -> TurnLead | None:
        """None where nothing limits the lead (no limit known, or no lag modelled)."""
        if limit_radps2 is None or not math.isfinite(limit_radps2) or tau_s <= 0.0:
            return None
        return cls(math.exp(-dt / tau_s), limit_radps2 * tau_s)

    def matrix(self, K: int) -> np.ndarray:
        """M (K, K): the leads' change per change of the commands (read-only: built once per drive and
        horizon, as every SQP iteration asks for it)."""
        return _lead_matrix(self.beta, K)

    def leads(self, w: np.ndarray, xi0: float) -> np.ndarray:
        """u_k - xi_k of the commands w (K,) from the drive's state xi0."""
        K = len(w)
        return self.matrix(K) @ np.asarray(w, dtype=float) - self.beta ** np.arange(K) * xi0

    def followable(self, w: np.ndarray, xi0: float) -> np.ndarray:
        """The commands w (K,) each brought within the lead of the drive's state they meet, in turn: where
        an SQP starts, so that it need not spend its iterations pulling a warm start back inside."""
        out, xi = np.array(w, dtype=float), float(xi0)
        for k in range(len(out)):
            out[k] = min(max(out[k], xi - self.max_radps), xi + self.max_radps)
            xi = self.beta * xi + (1.0 - self.beta) * out[k]
        return out

"""The drive's lag between commanded and achieved speeds, as the NMPC's nominal model sees it.

The thesis's nominal model (eq. 5.26) takes the command as the robot's speed within the same period and
leaves the drive's dynamics to the learned disturbance (a_k holds v_{k-1} and u_{k-1} for that). That is
fine for a 50 kg Husky whose drives settle within a period; a 900 kg Grizzly needs ~0.4 s to follow a
turn-rate command, so in the first trial (no experience) a unicycle NMPC expects four times the yaw it
gets, over-steers, and at 2 m/s the loop oscillates off the route. A first-order lag per axis, its time
constant found by a step test, is the standard remedy:

    xi_{k+1} = beta xi_k + (1 - beta) u_k,        beta = exp(-dt / tau)

with xi the achieved speed; over period k the robot moves at the period's average

    ubar_k = a xi_k + (1 - a) u_k,                a = (tau / dt)(1 - beta)

(exact for a continuous first-order lag under a held command). tau = 0 gives ubar_k = u_k: eq. 5.26.
Achieved speeds are never measured here: xi is the lag's response to the commands the controller has
sent, which both the horizon's start and the experiences (eq. 5.17, residuals of this same model) use.

An Ackermann robot turns by steering, and its steering angle moves at a limited rate: its curvature
changes by at most R_kappa per second (steering rate / wheelbase, a bound that holds at any angle), its
turn rate by v R_kappa, which at 2 m/s is a fraction of what the lag alone would allow. Unmodelled, an
NMPC plans turn-rate swings the steering cannot follow and the loop cycles (docs/results.md, MATS). With
the limit the turn-rate channel's step per period is softly saturated,

    xi_{k+1} = xi_k + sat((1 - beta)(u_k - xi_k)),    ubar_k = xi_k + rho sat(.),   rho = (1 - a) / (1 - beta)

sat(x) = x / (1 + (x / c)^6)^(1/6), c = R_kappa max(|vbar_k|, V_FLOOR) dt: the linear lag below about
half the limit (within 0.3 %), the limit beyond it, and smooth, so the Jacobian the solvers use is too.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np


V_FLOOR_MPS = 0.1         # the turn-rate limit of a robot (nearly) at rest: it turns little there anyway
SAT_POWER = 6
RATE_HISTORY_S = 3.0      # a rate-limited drive is replayed this far back (a full swing takes seconds)


def soft_clip(x, c):
    """sat(x) and its derivative: x below c, c beyond it, smooth in between (arrays or floats)."""
    z = (x / c) ** SAT_POWER
    return x * (1.0 + z) ** (-1.0 / SAT_POWER), (1.0 + z) ** (-1.0 / SAT_POWER - 1.0)


def _coeffs(tau: float, dt: float) -> tuple[float, float]:
    if tau <= 0.0:
        return 0.0, 0.0
    beta = math.exp(-dt / tau)
    return beta, (tau / dt) * (1.0 - beta)


@dataclass(frozen=True)
class ActuatorLag:
    tau_v_s: float = 0.0
    tau_w_s: float = 0.0
    dt: float = 0.1
    curvature_rate_max_per_ms: float = 0.0     # Ackermann: R_kappa, 1/(m s); 0: the turn rate is not limited

    def __post_init__(self):
        if self.tau_v_s < 0 or self.tau_w_s < 0 or self.dt <= 0 or self.curvature_rate_max_per_ms < 0:
            raise ValueError("actuator time constants and the curvature rate limit must be >= 0, the period > 0")

    @property
    def model_tag(self) -> str:
        """The nominal model the experiences' residuals are measured against (eq. 5.17 with this lag), as
        a name: the store keeps each model's experiences apart (common/messages.py Experience.model)."""
        ms = lambda x: int(round(1000 * x))     # noqa: E731
        tag = f"unicycle-dt{ms(self.dt)}ms-tauv{ms(self.tau_v_s)}ms-tauw{ms(self.tau_w_s)}ms"
        return tag + (f"-kr{ms(self.curvature_rate_max_per_ms)}m" if self.rate_limited else "")

    @property
    def rate_limited(self) -> bool:
        return self.curvature_rate_max_per_ms > 0.0

    @property
    def active(self) -> bool:
        return self.tau_v_s > 0.0 or self.tau_w_s > 0.0 or self.rate_limited

    @property
    def history_periods(self) -> int:
        """How many earlier commands `state_before` replays."""
        span = max(10.0 * max(self.tau_v_s, self.tau_w_s), RATE_HISTORY_S if self.rate_limited else 0.0)
        return int(math.ceil(span / self.dt)) + 1

    def w_step_limit(self, v_mps):
        """c of the turn-rate channel's saturation in a period moved at speed v_mps (float or array; inf
        without a limit)."""
        if not self.rate_limited:
            return np.full(np.shape(v_mps), math.inf)
        return self.curvature_rate_max_per_ms * self.dt * np.maximum(np.abs(v_mps), V_FLOOR_MPS)

    def _both(self) -> tuple[tuple[float, float], tuple[float, float]]:
        return _coeffs(self.tau_v_s, self.dt), _coeffs(self.tau_w_s, self.dt)

    def step(self, xi: tuple[float, float], u: tuple[float, float]) -> tuple[tuple[float, float], tuple[float, float]]:
        """One period under command u from achieved speeds xi: (the period's average speeds, the next xi)."""
        (bv, av), (bw, aw) = self._both()
        v_avg = av * xi[0] + (1 - av) * u[0]
        xi_v = bv * xi[0] + (1 - bv) * u[0]
        if not self.rate_limited:
            return (v_avg, aw * xi[1] + (1 - aw) * u[1]), (xi_v, bw * xi[1] + (1 - bw) * u[1])
        d = float(soft_clip((1 - bw) * (u[1] - xi[1]), self.w_step_limit(v_avg))[0])
        return (v_avg, xi[1] + (1 - aw) / (1 - bw) * d), (xi_v, xi[1] + d)

    def turn_rates(self, w: np.ndarray, v_avg: np.ndarray, xi_w0: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Over a horizon of commands w (K,) moved at average speeds v_avg (K,), from achieved turn rate
        xi_w0: the periods' average turn rates (K,) and their derivatives by w and by v_avg (each (K, K),
        lower triangular; the speeds set the limit). Without the limit these are `matrices`' L_w w + c_w
        xi_w0, L_w and zeros."""
        bw, aw = self._both()[1]
        g, rho = 1.0 - bw, (1.0 - aw) / (1.0 - bw)
        K = len(w)
        v_avg = np.asarray(v_avg, dtype=float)
        c = self.w_step_limit(v_avg)
        dc = np.where(np.abs(v_avg) > V_FLOOR_MPS, np.sign(v_avg), 0.0) * self.curvature_rate_max_per_ms * self.dt
        wb, Lw, Lv = np.empty(K), np.zeros((K, K)), np.zeros((K, K))
        dxi, dxi_v = np.zeros(K), np.zeros(K)          # d xi_j / d w, d xi_j / d v_avg
        xi = float(xi_w0)
        for j in range(K):
            e, cj = g * (float(w[j]) - xi), float(c[j])
            d, slope = soft_clip(e, cj)
            dd, dd_v = (-slope * g) * dxi, (-slope * g) * dxi_v
            dd[j] += slope * g
            if math.isfinite(cj):                     # d sat / d c = x z / c (1 + z)^(-1/p - 1)
                dd_v[j] += e * (e / cj) ** SAT_POWER / cj * slope * dc[j]
            wb[j] = xi + rho * d
            Lw[j], Lv[j] = dxi + rho * dd, dxi_v + rho * dd_v
            xi += d
            dxi += dd
            dxi_v += dd_v
        return wb, Lw, Lv

    def state_before(self, tick: int, command_at: Callable[[int], tuple[float, float] | None]) -> tuple[float, float]:
        """xi at the start of `tick`, from the commands applied before it (none known: standing still).
        The lag forgets (to exp(-10)) within 10 tau, so only that many periods are replayed, from the drive
        settled at the oldest of them. A period without a recorded command (a skipped tick) held the one
        before it; before the first recorded command the robot stood still."""
        n = self.history_periods
        u = command_at(tick - n) or (0.0, 0.0)
        xi = u
        for t in range(tick - n, tick):
            u = command_at(t) or u
            xi = self.step(xi, u)[1]
        return xi

    def matrices(self, K: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """For a horizon of K periods from achieved speeds xi_0: ubar = L u + c xi_0 per axis. Returns
        (L_v, c_v, L_w, c_w); L lower triangular (K, K), c (K,)."""
        out = []
        for beta, a in self._both():
            j = np.arange(K)
            diff = j[:, None] - j[None, :]
            L = np.where(diff > 0, a * (1.0 - beta) * beta ** np.maximum(diff - 1, 0), 0.0)
            L[j, j] = 1.0 - a
            out += [L, a * beta ** j]
        return tuple(out)

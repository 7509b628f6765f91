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
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np


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

    def __post_init__(self):
        if self.tau_v_s < 0 or self.tau_w_s < 0 or self.dt <= 0:
            raise ValueError("actuator time constants must be >= 0 and the period > 0")

    @property
    def model_tag(self) -> str:
        """The nominal model the experiences' residuals are measured against (eq. 5.17 with this lag), as
        a name: the store keeps each model's experiences apart (common/messages.py Experience.model)."""
        ms = lambda x: int(round(1000 * x))     # noqa: E731
        return f"unicycle-dt{ms(self.dt)}ms-tauv{ms(self.tau_v_s)}ms-tauw{ms(self.tau_w_s)}ms"

    @property
    def active(self) -> bool:
        return self.tau_v_s > 0.0 or self.tau_w_s > 0.0

    @property
    def history_periods(self) -> int:
        """How many earlier commands `state_before` replays."""
        return int(math.ceil(10.0 * max(self.tau_v_s, self.tau_w_s) / self.dt)) + 1

    def _both(self) -> tuple[tuple[float, float], tuple[float, float]]:
        return _coeffs(self.tau_v_s, self.dt), _coeffs(self.tau_w_s, self.dt)

    def step(self, xi: tuple[float, float], u: tuple[float, float]) -> tuple[tuple[float, float], tuple[float, float]]:
        """One period under command u from achieved speeds xi: (the period's average speeds, the next xi)."""
        (bv, av), (bw, aw) = self._both()
        avg = (av * xi[0] + (1 - av) * u[0], aw * xi[1] + (1 - aw) * u[1])
        return avg, (bv * xi[0] + (1 - bv) * u[0], bw * xi[1] + (1 - bw) * u[1])

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

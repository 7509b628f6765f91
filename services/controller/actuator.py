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
the limit, the turn channel's state is the curvature the steering has reached, commanded by
kappa_u = w / v (eq. 5.27's inverse, as the drive converts it), its step per period softly saturated:

    xi_{k+1} = xi_k + sat((1 - beta)(kappa_u - xi_k)),   kappabar_k = xi_k + rho sat(.),   wbar_k = vbar_k kappabar_k

with rho = (1 - a) / (1 - beta) and sat(x) = x / (1 + (x / c)^6)^(1/6), c = R_kappa dt: the linear lag
below about half the limit (within 0.3 %), the limit beyond it, and smooth, so the Jacobians the solvers
use are too. The turn rate follows the speed at a held steering angle, so a robot that slows down in a
turn turns less without steering, which a turn-rate lag would not know.

The ground turns the robot less than its drive does: a skid-steer's tracks slip sideways in a turn and
its heading follows a share of the turn rate its wheels make (0.6-0.9 for the heavy ones; ROS's
diff_drive_controller calls the inverse its wheel separation multiplier), an Ackermann's understeer does
the same. The lag's output is the drive's turn rate; the robot turns at `turn_gain` times it, a gain the
teach pass identifies against the localizer's heading (identification.py), not the wheel odometry, which
cannot see the slip. A law that wants the route's turn rate w commands w / turn_gain (`command_for`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Callable

import numpy as np


V_FLOOR_MPS = 0.02        # a speed command below this steers as at it (kappa_u = w / v)
SAT_POWER = 6
RATE_HISTORY_S = 3.0      # a rate-limited drive is replayed this far back (a full swing takes seconds)
MIN_TURN_GAIN, MAX_TURN_GAIN = 0.2, 2.0


def soft_clip(x, c):
    """sat(x) and its derivative: x below c, c beyond it, smooth in between (arrays or floats)."""
    z = (x / c) ** SAT_POWER
    return x * (1.0 + z) ** (-1.0 / SAT_POWER), (1.0 + z) ** (-1.0 / SAT_POWER - 1.0)


@lru_cache(maxsize=8)
def _strictly_lower(K: int) -> np.ndarray:
    return np.tri(K, K, -1, dtype=bool)


def _coeffs(tau: float, dt: float) -> tuple[float, float]:
    if tau <= 0.0:
        return 0.0, 0.0
    beta = math.exp(-dt / tau)
    return beta, (tau / dt) * (1.0 - beta)


@lru_cache(maxsize=16)
def _lag_matrices(v_coeffs: tuple[float, float], w_coeffs: tuple[float, float], turn_gain: float,
                  K: int) -> tuple[np.ndarray, ...]:
    """ActuatorLag.matrices, built once per lag and horizon (every step's problem needs them)."""
    out = []
    j = np.arange(K)
    diff = j[:, None] - j[None, :]
    for (beta, a), gain in ((v_coeffs, 1.0), (w_coeffs, turn_gain)):
        L = np.where(diff > 0, a * (1.0 - beta) * beta ** np.maximum(diff - 1, 0), 0.0)
        L[j, j] = 1.0 - a
        out += [gain * L, gain * a * beta ** j]
    for m in out:
        m.setflags(write=False)
    return tuple(out)


@dataclass(frozen=True)
class ActuatorLag:
    tau_v_s: float = 0.0
    tau_w_s: float = 0.0
    dt: float = 0.1
    curvature_rate_max_per_ms: float = 0.0     # Ackermann: R_kappa, 1/(m s); 0: the turn rate is not limited
    turn_gain: float = 1.0                     # the robot's turn rate over the drive's (ground slip, understeer)

    def __post_init__(self):
        if self.tau_v_s < 0 or self.tau_w_s < 0 or self.dt <= 0 or self.curvature_rate_max_per_ms < 0:
            raise ValueError("actuator time constants and the curvature rate limit must be >= 0, the period > 0")
        if not MIN_TURN_GAIN <= self.turn_gain <= MAX_TURN_GAIN:
            raise ValueError(f"turn_gain must be in [{MIN_TURN_GAIN}, {MAX_TURN_GAIN}]")

    @property
    def model_tag(self) -> str:
        """The nominal model the experiences' residuals are measured against (eq. 5.17 with this lag), as
        a name: the store keeps each model's experiences apart (common/messages.py Experience.model)."""
        ms = lambda x: int(round(1000 * x))     # noqa: E731
        tag = f"unicycle-dt{ms(self.dt)}ms-tauv{ms(self.tau_v_s)}ms-tauw{ms(self.tau_w_s)}ms"
        tag += f"-kr{ms(self.curvature_rate_max_per_ms)}m" if self.rate_limited else ""
        return tag + (f"-gw{ms(self.turn_gain)}" if self.turn_gain != 1.0 else "")

    @property
    def rate_limited(self) -> bool:
        return self.curvature_rate_max_per_ms > 0.0

    @property
    def active(self) -> bool:
        return self.tau_v_s > 0.0 or self.tau_w_s > 0.0 or self.rate_limited or self.turn_gain != 1.0

    def turn_rate(self, xi: tuple[float, float]) -> float:
        """The robot's turn rate with the drive at xi (a rate-limited steering turns at the speed
        times the curvature it has reached)."""
        return self.turn_gain * (xi[0] * xi[1] if self.rate_limited else xi[1])

    def turn_settling_s(self, change_radps: float, v_mps: float) -> float:
        """How long the robot's turn rate takes to change by `change_radps` once commanded, as the heading
        it turns meanwhile over the change: the lag's time constant tau; with a rate-limited steering
        (r = v R_kappa turn_gain), a change beyond r tau first ramps at r down to r tau, then lags:
        |change| / 2r + r tau^2 / 2|change|."""
        tau, d = self.tau_w_s, abs(change_radps)
        if not self.rate_limited:
            return tau
        r = self.turn_gain * max(abs(v_mps), V_FLOOR_MPS) * self.curvature_rate_max_per_ms
        return tau if d <= r * tau else 0.5 * d / r + 0.5 * r * tau * tau / d

    def command_for(self, w_radps):
        """The turn-rate command whose drive response turns the robot at w (settled; floats or arrays)."""
        return w_radps / self.turn_gain

    def turn_command_reaching(self, xi_w: float, target_radps: float) -> float:
        """The turn-rate command that brings a drive turning at xi_w to `target_radps` by the period's end
        (the lag inverted over one period; not for a rate-limited drive, whose xi is a curvature)."""
        beta = _coeffs(self.tau_w_s, self.dt)[0]
        return (target_radps - beta * xi_w) / (1.0 - beta)

    @property
    def history_periods(self) -> int:
        """How many earlier commands `state_before` replays."""
        span = max(10.0 * max(self.tau_v_s, self.tau_w_s), RATE_HISTORY_S if self.rate_limited else 0.0)
        return int(math.ceil(span / self.dt)) + 1

    def settled(self, u: tuple[float, float]) -> tuple[float, float]:
        """xi of a drive that has held command u for long: the speeds, or the speed and the curvature."""
        return (u[0], self._curvature(u[0], u[1])) if self.rate_limited else u

    @staticmethod
    def _curvature(v: float, w: float) -> float:
        return w / math.copysign(max(abs(v), V_FLOOR_MPS), v)

    def _both(self) -> tuple[tuple[float, float], tuple[float, float]]:
        return _coeffs(self.tau_v_s, self.dt), _coeffs(self.tau_w_s, self.dt)

    def step(self, xi: tuple[float, float], u: tuple[float, float]) -> tuple[tuple[float, float], tuple[float, float]]:
        """One period under command u from the drive's state xi: (the period's average speed and the
        robot's average turn rate, the next xi)."""
        (bv, av), (bw, aw) = self._both()
        v_avg = av * xi[0] + (1 - av) * u[0]
        xi_v = bv * xi[0] + (1 - bv) * u[0]
        g = self.turn_gain
        if not self.rate_limited:
            return (v_avg, g * (aw * xi[1] + (1 - aw) * u[1])), (xi_v, bw * xi[1] + (1 - bw) * u[1])
        c = self.curvature_rate_max_per_ms * self.dt
        d = float(soft_clip((1 - bw) * (self._curvature(*u) - xi[1]), c)[0])
        return (v_avg, g * v_avg * (xi[1] + (1 - aw) / (1 - bw) * d)), (xi_v, xi[1] + d)

    def turn_rates(self, w: np.ndarray, v: np.ndarray, v_avg: np.ndarray,
                   kappa0: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """A rate-limited drive over a horizon of commands (v, w) (K,) moved at average speeds v_avg (K,),
        from the curvature kappa0 the steering has reached: the robot's average turn rates (K,), their
        derivatives by w and by v (each (K, K), lower triangular, v_avg held) and the periods' average
        curvatures the robot turns at (K,), the derivative by v_avg (the turn rate is v_avg times them)."""
        bw, aw = self._both()[1]
        g, rho, c = 1.0 - bw, (1.0 - aw) / (1.0 - bw), self.curvature_rate_max_per_ms * self.dt
        K = len(w)
        v, v_avg = np.asarray(v, dtype=float), np.asarray(v_avg, dtype=float)
        v_eff = np.copysign(np.maximum(np.abs(v), V_FLOOR_MPS), v)
        ku = np.asarray(w, dtype=float) / v_eff
        dku_dv = np.where(np.abs(v) > V_FLOOR_MPS, -ku / v_eff, 0.0)
        # the recursion in scalars; then d xi_j / d ku_i = s_i prod_{i<l<j} (1 - s_l), s = sat' g
        xi, kb, sg = float(kappa0), np.empty(K), np.empty(K)
        for j, kj in enumerate(ku.tolist()):
            d, slope = soft_clip(g * (kj - xi), c)
            kb[j], sg[j] = xi + rho * d, slope * g
            xi += d
        log_m = np.cumsum(np.log(np.maximum(1.0 - sg, 1e-300)))
        log_m = np.concatenate([[0.0], log_m[:-1]])      # sum over l < j
        below = _strictly_lower(K)
        # d xi_j / d ku_i, then d kappabar_j / d ku_i (times the speed: the turn rate's)
        D = np.exp(np.where(below, log_m[:, None] - log_m[None, :], -np.inf)) * (sg / (1.0 - sg + 1e-300))[None, :]
        D *= ((1.0 - rho * sg) * v_avg)[:, None]
        D.flat[::K + 1] = rho * sg * v_avg
        D *= self.turn_gain
        kb *= self.turn_gain
        return v_avg * kb, D / v_eff[None, :], D * dku_dv[None, :], kb

    def state_before(self, tick: int, command_at: Callable[[int], tuple[float, float] | None]) -> tuple[float, float]:
        """xi (the speeds reached, or the speed and the curvature with a rate limit) at the start of
        `tick`, from the commands applied before it (none known: standing still). The lag forgets (to
        exp(-10)) within 10 tau, so only that many periods are replayed, from the drive settled at the
        oldest of them. A period without a recorded command (a skipped tick) held the one
        before it; before the first recorded command the robot stood still."""
        n = self.history_periods
        u = command_at(tick - n) or (0.0, 0.0)
        xi = self.settled(u)
        for t in range(tick - n, tick):
            u = command_at(t) or u
            xi = self.step(xi, u)[1]
        return xi

    def matrices(self, K: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """For a horizon of K periods from achieved speeds xi_0: ubar = L u + c xi_0 per axis. Returns
        (L_v, c_v, L_w, c_w), read-only; L lower triangular (K, K), c (K,)."""
        return _lag_matrices(*self._both(), self.turn_gain, K)

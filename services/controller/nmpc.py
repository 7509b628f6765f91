"""Learning-based NMPC (thesis 5.2, 5.3.1): the nominal unicycle plus a learned disturbance.

Prediction model over the horizon (eq. 5.14, 5.26), states in the route's frame:

    x_{j+1} = f(x_j, u_j) + R(theta_j) g(a_j),    a_j = (route coords of x_j, v_{j-1}, u_j, u_{j-1})

with g the GP posterior mean of the local window (body frame, as the experiences are built, see
experience.py) and v_{j-1} recomputed from consecutive predicted poses as in 5.3.1. The linear speed of
every step is fixed by the speed profile (schedule, end of route); the angular rates w_0..w_{K-1} are
optimized by Gauss-Newton (eq. 5.5-5.10) with the actuator (and Ackermann steering) limits as bounds,
warm-started from the previous solution shifted by one step.

Cost (eq. 5.16): for j = 1..K the error of x_j against the desired state x_{d,j}, the taught route's pose
where the schedule puts the robot after j periods: along and lateral along the route's direction there,
heading against the taught heading (the same definitions the experiences use), weighted by
Q = diag(q_along, q_lat, q_head); plus R times the deviation of w_j from the route's own turn rate
v_j kappa (the thesis penalizes u itself; the deviation keeps the optimum on curved routes from being
biased towards driving straight), an input-rate term, and a terminal term on the lateral error
`lookahead_m` ahead of x_K (a one-second horizon is too short to see a lateral correction pay off).
A delayed estimate is first carried forward to now through the commands applied since its capture
(the mean of eq. 7.12).

All Jacobians are analytic: forward sensitivities of the rollout with the GP's mean gradient
(`GaussianProcess.mean_and_grad`), no finite differences in the loop.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Protocol

import numpy as np

from services.controller.actuator import ActuatorLag
from services.controller.gauss_newton import gauss_newton
from services.controller.laws import LawResult, StepContext


class DisturbanceModel(Protocol):
    def mean_and_grad(self, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...

    def mean(self, A: np.ndarray) -> np.ndarray: ...


@dataclass(frozen=True, kw_only=True)
class NMPCSettings:
    """Weights and solver settings; also the controller config's [nmpc] table (one set of defaults)."""
    horizon: int = 10
    q_along: float = 1.0      # 1/m^2
    q_lat: float = 40.0       # 1/m^2
    q_head: float = 10.0      # 1/rad^2
    r_w: float = 0.2          # s^2/rad^2, on w - v kappa
    r_dw: float = 1.0         # s^2/rad^2, on w_j - w_{j-1}
    q_terminal: float = 100.0 # 1/m^2, on the lateral error lookahead_m ahead of the last predicted pose
    lookahead_m: float = 1.5
    max_iter: int = 10
    max_evals: int = 6        # residual evaluations per step at most: bounds the solve time
    tol: float = 1e-3         # rad/s: stop when no angular rate moves more than this
    delay_compensation: bool = True   # eq. 7.12: start from the estimate carried forward to now
    # --- MM-, C- and RC-LB-NMPC (chapters 6, 7) ---
    sp_gamma: float = 2.0     # sigma-point scaling (eq. 6.10-6.14; thesis 6.4.2)
    mm_sigmas: float = 3.0    # MM: boundary sequences at +-3 sigma (eq. 6.5)
    alpha: float = 3.0        # RC: corridor tightened by alpha * sigma (eq. 7.4); C-LB-NMPC uses 0
    r_v: float = 4.0          # s^2/m^2, on v - v_desired (eq. 7.2's u_d: the scheduled speed)
    r_dv: float = 2.0         # s^2/m^2, on v_j - v_{j-1}
    v_min_mps: float = 0.05   # RC/C: the slowest the law may choose while moving
    slack_weight: float = 2000.0    # C/RC: L1 price of violating a (tightened) corridor limit
    sqp_iter: int = 4         # C/RC: SQP iterations per step at most
    # the a-priori std of the unicycle model's error per period (body frame, before any experience):
    # base + per_mps |v| + per_radps |w| (slip and lag grow with speed and with turning)
    prior_std_base: tuple[float, float, float] = (0.001, 0.002, 0.003)
    prior_std_per_mps: tuple[float, float, float] = (0.004, 0.008, 0.008)
    prior_std_per_radps: tuple[float, float, float] = (0.002, 0.004, 0.015)
    # C/RC beyond the first step: the tightened band keeps at least this fraction of the corridor (the
    # open-loop covariance ignores the localization updates still to come; without a floor the far end of
    # the horizon is infeasible whenever uncertainty is high and the slack drives the solution)
    min_band_fraction: float = 0.2
    process_std: tuple[float, float, float] = (0.0005, 0.001, 0.002)
    # the drive's first-order lag (v, w) in seconds, from a step test (actuator.py); 0: eq. 5.26 as is
    actuator_tau_s: tuple[float, float] = (0.0, 0.0)
    # with a learned model, weigh the heading error against the crab angle the model needs to hold the
    # route at the planned speed (`crab_offsets`), not the taught heading (which holds the teach speed's
    # crab). For repeats well above the teach speed on ground that slides the robot sideways (the side
    # slope of examples/husky-sideslope.toml at 2.5x: trials 3-5 at 0.02-0.045 m instead of 0.04-0.07 m);
    # at the teach speed the taught heading is the better reference (the GP's lateral slide, mostly
    # below the localization noise, is shrunk towards 0: 0.06 instead of 0.02-0.05 m there), hence off
    crab_reference: bool = False

    def __post_init__(self):
        for name in ("prior_std_base", "prior_std_per_mps", "prior_std_per_radps", "process_std"):   # TOML gives lists
            value = tuple(float(x) for x in getattr(self, name))
            if len(value) != 3 or min(value) < 0:
                raise ValueError(f"{name}: three non-negative values (along, lateral, heading)")
            object.__setattr__(self, name, value)
        tau = tuple(float(x) for x in self.actuator_tau_s)
        if len(tau) != 2 or min(tau) < 0:
            raise ValueError("actuator_tau_s: two non-negative time constants (v, w) in seconds")
        object.__setattr__(self, "actuator_tau_s", tau)
        if self.horizon < 1 or self.max_iter < 1 or self.max_evals < 2 or min(
                self.q_along, self.q_lat, self.q_head, self.r_w, self.r_dw, self.q_terminal, self.lookahead_m) < 0:
            raise ValueError("horizon, max_iter >= 1, max_evals >= 2 and non-negative weights required")
        if self.r_w + self.r_dw <= 0:
            raise ValueError("r_w or r_dw must be > 0 (eq. 5.3 needs R positive definite)")
        if not 0.0 <= self.min_band_fraction < 1.0:
            raise ValueError("min_band_fraction must be in [0, 1)")

    def lag(self, dt: float) -> ActuatorLag:
        return ActuatorLag(self.actuator_tau_s[0], self.actuator_tau_s[1], dt)


@dataclass
class Plan:
    """What one solve produced, for status and for the next step's warm start."""
    w: np.ndarray
    poses: np.ndarray           # (K+1, 3) predicted, x_0 first
    desired: np.ndarray         # (K+1, 3)
    cost: float
    iterations: int
    converged: bool


class HorizonProblem:
    """One NMPC problem: fixed initial state, desired states, speeds, bounds and model."""

    def __init__(self, x0, desired: np.ndarray, s_desired: np.ndarray, v: np.ndarray, w_ref: np.ndarray,
                 dt: float, settings: NMPCSettings, model: DisturbanceModel | None,
                 v_prev_act: tuple[float, float], u_prev: tuple[float, float], tangent: np.ndarray | None = None,
                 lag: ActuatorLag | None = None, xi0: tuple[float, float] = (0.0, 0.0)):
        self.x0 = np.asarray(x0, dtype=float)
        self.D = desired            # (K+1, 3): D[0] is the route pose at the robot, D[j] the desired x_j
        self.sD = s_desired         # (K+1,) arc length of D[j]
        self.v = v                  # (K,) linear speed of each step
        self.w_ref = w_ref          # (K,)
        self.dt = dt
        self.s = settings
        self.model = model
        self.v_prev_act = v_prev_act
        self.u_prev = u_prev
        self.K = len(v)
        # (K,) what the cost's heading error of x_1..x_K is measured against, relative to the taught
        # heading D[1:, 2] (build_problem: `crab_offsets`); corridor limits stay on the taught heading
        self.head_offset = np.zeros(self.K)
        self.sqrt_q = np.sqrt([settings.q_along, settings.q_lat, settings.q_head])
        self.sqrt_r = math.sqrt(settings.r_w)
        self.sqrt_dr = math.sqrt(settings.r_dw)
        self.sqrt_qt = math.sqrt(settings.q_terminal)
        # along/lateral errors are taken along the route's direction (as experiences measure them);
        # the heading error against the taught heading D[:, 2]
        direction = self.D[:, 2] if tangent is None else tangent
        self.cD = np.cos(direction)
        self.sinD = np.sin(direction)
        self._memo: list[tuple] = []   # the last rollouts: a solver's final iterate is usually among them
        # the drive's lag (actuator.py): the robot moves at ubar = L u + c xi0 per axis, not at u
        self.lag = None
        if lag is not None and lag.active:
            Lv, cv, Lw, cw = lag.matrices(self.K)
            self.lag = (Lv, cv * xi0[0], Lw, cw * xi0[1])

    def effective(self, v: np.ndarray, w: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
        """The speeds the robot moves at over each period under commands (v, w)."""
        if self.lag is None:
            return v, w
        Lv, cv, Lw, cw = self.lag
        return Lv @ v + cv, None if w is None else Lw @ w + cw

    def rollout(self, w: np.ndarray, with_jac: bool, v: np.ndarray | None = None, with_v_jac: bool = False,
                a_out: np.ndarray | None = None):
        key = (np.asarray(w, dtype=float).tobytes(), None if v is None else np.asarray(v, dtype=float).tobytes())
        for k, jac, vjac, out, A in self._memo:
            if k == key and (jac or not with_jac) and (vjac or not with_v_jac):
                if a_out is not None:
                    a_out[:] = A
                X, S = out[0], out[1] if with_jac else None
                return (X, S, out[2]) if with_v_jac else (X, S)
        A = np.empty((self.K, 9)) if a_out is None else a_out
        out = self._rollout(w, with_jac, v, with_v_jac, A)
        self._memo = [(key, with_jac, with_v_jac, out if with_v_jac else (*out, None), A.copy())] + self._memo[:1]
        return out

    def _rollout(self, w: np.ndarray, with_jac: bool, v: np.ndarray | None, with_v_jac: bool, a_out: np.ndarray):
        """Predicted poses (K+1, 3) and, with_jac, their sensitivities dX/dw (K+1, 3, K); with_v_jac also
        dX/dv (the constrained laws optimize the speeds too; `v` overrides the profile's). `a_out`
        (K, 9) receives the disturbance inputs a_j (for the GP variance along the horizon).

        Per step, x_{j+1} = F(x_j, x_{j-1}, u_j, u_{j-1}) (x_{j-1} and u_{j-1} enter through v_{j-1} and
        u_{j-1} in a_j), so S_{j+1} = A_j S_j + C_j S_{j-1} + b_j e_j' + d_j e_{j-1}' with the 3x3 A_j, C_j
        and the 3-vectors b_j, d_j of `_step_jacobians`. The mean is rolled out point by point (the GP's
        input depends on the state); the per-step matrices are then built for all j at once, leaving two
        small products per step for the recursion."""
        K, dt = self.K, self.dt
        X = np.empty((K + 1, 3))
        X[0] = self.x0
        model = self.model
        jac = with_jac or with_v_jac
        a = np.zeros(9)
        xj, yj, thj = (float(v) for v in self.x0)
        xp = yp = thp = cp = sp = 0.0
        D, sD, cD, sinD = self.D, self.sD, self.cD, self.sinD
        v_all = self.v if v is None else v
        vb_all, wb_all = self.effective(v_all, np.asarray(w, dtype=float))
        # what the sensitivities need of each step: heading cos/sin, disturbance, previous-step geometry
        if jac:
            cs = np.empty((K, 2))
            gg = np.zeros((K, 2))
            prev = np.zeros((K, 4))                        # cos, sin of theta_{j-1}; x_j - x_{j-1}, y_j - y_{j-1}
            Dg_all = np.empty((K, 3, 9)) if model is not None else None
        for j in range(K):
            cd, sd = cD[j], sinD[j]
            dx, dy = xj - D[j, 0], yj - D[j, 1]
            c, s = math.cos(thj), math.sin(thj)
            v = v_all[j]
            wj = float(w[j])
            if model is not None:
                # a_j (experience.py A_NAMES): route coords, v_{j-1}, u_j, u_{j-1}
                a[0] = sD[j] + cd * dx + sd * dy
                a[1] = -sd * dx + cd * dy
                a[2] = math.remainder(thj - D[j, 2], 2 * math.pi)
                if j == 0:
                    a[3], a[4] = self.v_prev_act
                    a[7], a[8] = self.u_prev
                else:
                    a[3] = (cp * (xj - xp) + sp * (yj - yp)) / dt
                    a[4] = (thj - thp) / dt
                    a[7], a[8] = v_all[j - 1], w[j - 1]
                a[5], a[6] = v, wj
                if jac:
                    g, Dg_all[j] = model.mean_and_grad(a)
                else:
                    g, _ = model.mean_and_grad(a)
                gx, gy, gth = float(g[0]), float(g[1]), float(g[2])
            else:
                gx = gy = gth = 0.0
                a[5], a[6] = v, wj   # the inputs still matter to a prior that depends on the commands
            a_out[j] = a
            if jac:
                cs[j] = (c, s)
                gg[j] = (gx, gy)
                if j > 0:
                    prev[j] = (cp, sp, xj - xp, yj - yp)
            vb, wb = float(vb_all[j]), float(wb_all[j])   # what the robot moves at (= u without a lag)
            xn = xj + vb * dt * c + c * gx - s * gy
            yn = yj + vb * dt * s + s * gx + c * gy
            thn = thj + wb * dt + gth
            X[j + 1] = (xn, yn, thn)
            xp, yp, thp, cp, sp = xj, yj, thj, c, s
            xj, yj, thj = xn, yn, thn
        if not jac:
            return X, None
        Aj, Cj, b, bv, d_w, d_v = self._step_jacobians(cs, gg, prev, Dg_all, np.asarray(vb_all, dtype=float))
        lag = self.lag
        n_w = K if with_jac else 0
        # dX/dw and dX/dv side by side in one array (columns: w's, then v's): one product per step for both
        SS = np.zeros((K + 1, 3, n_w + (K if with_v_jac else 0)))
        for j in range(K):
            Sn = Aj[j] @ SS[j]
            if Cj is not None and j > 0:
                Sn += Cj[j] @ SS[j - 1]
            if with_jac:
                Sn[:, j] += b[j]
                if lag:
                    Sn[2, :j + 1] += dt * lag[2][j, :j + 1]
                if d_w is not None and j > 0:
                    Sn[:, j - 1] += d_w[j]
            if with_v_jac:
                Sn[:, n_w + j] += bv[j]
                if lag:
                    Sn[:2, n_w:n_w + j + 1] += np.outer(dt * cs[j], lag[0][j, :j + 1])
                if d_v is not None and j > 0:
                    Sn[:, n_w + j - 1] += d_v[j]
            SS[j + 1] = Sn
        S = SS[:, :, :K] if with_jac else None
        if not with_v_jac:
            return X, S
        return X, S, SS[:, :, n_w:]

    def _step_jacobians(self, cs: np.ndarray, gg: np.ndarray, prev: np.ndarray, Dg: np.ndarray | None,
                        vb: np.ndarray):
        """For every step j at once: A_j = dx_{j+1}/dx_j, C_j = dx_{j+1}/dx_{j-1} (None without a model),
        b_j, bv_j = dx_{j+1}/d(w_j, v_j) (the nominal part is left to the caller's lag terms when there is
        a lag), d_w, d_v = dx_{j+1}/d(w_{j-1}, v_{j-1}) through the GP's inputs (None without a model)."""
        K, dt = self.K, self.dt
        c, s = cs[:, 0], cs[:, 1]
        gx, gy = gg[:, 0], gg[:, 1]
        A = np.zeros((K, 3, 3))
        A[:, 0, 0] = A[:, 1, 1] = A[:, 2, 2] = 1.0
        # the nominal step and the rotation of g by theta_j
        A[:, 0, 2] = -vb * dt * s - s * gx - c * gy
        A[:, 1, 2] = vb * dt * c + c * gx - s * gy
        b = np.zeros((K, 3))
        bv = np.zeros((K, 3))
        if not self.lag:                       # with a lag the inputs reach back to earlier commands (caller)
            b[:, 2] = dt
            bv[:, 0], bv[:, 1] = dt * c, dt * s
        if Dg is None:
            return A, None, b, bv, None, None
        # R(theta_j) Dg_j: the GP's gradient in the world frame, (K, 3, 9)
        RDg = np.empty_like(Dg)
        RDg[:, 0] = c[:, None] * Dg[:, 0] - s[:, None] * Dg[:, 1]
        RDg[:, 1] = s[:, None] * Dg[:, 0] + c[:, None] * Dg[:, 1]
        RDg[:, 2] = Dg[:, 2]
        # d a_j / d x_j: route coordinates (rows 0-2) and, from j = 1, the measured previous velocity (3-4)
        cd, sd = self.cD[:K], self.sinD[:K]
        cp, sp, ddx, ddy = prev[:, 0], prev[:, 1], prev[:, 2], prev[:, 3]
        Ax = np.zeros((K, 5, 3))
        Ax[:, 0, 0], Ax[:, 0, 1] = cd, sd
        Ax[:, 1, 0], Ax[:, 1, 1] = -sd, cd
        Ax[:, 2, 2] = 1.0
        Ax[1:, 3, 0], Ax[1:, 3, 1] = cp[1:] / dt, sp[1:] / dt
        Ax[1:, 4, 2] = 1.0 / dt
        A += RDg[:, :, :5] @ Ax
        b += RDg[:, :, 6]
        bv += RDg[:, :, 5]
        # d a_j / d x_{j-1} (the previous velocity), from j = 1
        Ap = np.zeros((K, 2, 3))
        Ap[1:, 0, 0], Ap[1:, 0, 1] = -cp[1:] / dt, -sp[1:] / dt
        Ap[1:, 0, 2] = (-sp[1:] * ddx[1:] + cp[1:] * ddy[1:]) / dt
        Ap[1:, 1, 2] = -1.0 / dt
        C = RDg[:, :, 3:5] @ Ap
        return A, C, b, bv, RDg[:, :, 8], RDg[:, :, 7]

    def errors(self, X: np.ndarray) -> np.ndarray:
        """(K, 3) errors of x_1..x_K in the frames of their desired poses (along, lateral, heading)."""
        d = X[1:, :2] - self.D[1:, :2]
        cd, sd = self.cD[1:], self.sinD[1:]
        return np.column_stack([cd * d[:, 0] + sd * d[:, 1], -sd * d[:, 0] + cd * d[:, 1],
                                np.remainder(X[1:, 2] - self.D[1:, 2] + math.pi, 2 * math.pi) - math.pi])

    def _extra(self, w: np.ndarray, E: np.ndarray) -> np.ndarray:
        """Input-rate and terminal residuals."""
        dw = np.diff(np.concatenate([[self.u_prev[1]], w]))
        term = E[-1, 1] + self.s.lookahead_m * math.sin(E[-1, 2])
        return np.concatenate([self.sqrt_dr * dw, [self.sqrt_qt * term]])

    def cost_frame(self, E: np.ndarray) -> np.ndarray:
        """Errors (K, 3) as the cost weighs them: heading against the taught heading + `head_offset`."""
        if not self.head_offset.any():
            return E
        E = E.copy()
        E[:, 2] -= self.head_offset
        return E

    # the errors the cost weighs; MM-LB-NMPC replaces it with its worst-case boundary sequence
    cost_errors: Callable[[np.ndarray], np.ndarray] | None = None

    # further residuals r(E) with their Jacobians from (E, dE/dw (K, 3, K)); MM-LB-NMPC's worst case
    extra_residuals: Callable[[np.ndarray, np.ndarray | None], tuple[np.ndarray, np.ndarray | None]] | None = None

    def residual(self, w: np.ndarray):
        X, S = self.rollout(w, with_jac=True)
        E = self.cost_frame(self.errors(X))
        if self.cost_errors is not None:
            E = self.cost_errors(E)
        r = np.concatenate([(E * self.sqrt_q).ravel(), self.sqrt_r * (w - self.w_ref), self._extra(w, E)])
        K = self.K
        J = np.zeros((3 * K + 2 * K + 1, K))
        cd, sd = self.cD[1:], self.sinD[1:]
        Sx = S[1:]                                                              # (K, 3, K)
        dE = np.empty((K, 3, K))
        dE[:, 0] = cd[:, None] * Sx[:, 0] + sd[:, None] * Sx[:, 1]
        dE[:, 1] = -sd[:, None] * Sx[:, 0] + cd[:, None] * Sx[:, 1]             # d e_lat_j / dw
        dE[:, 2] = Sx[:, 2]
        J[:3 * K] = (dE * self.sqrt_q[None, :, None]).reshape(3 * K, K)
        J[3 * K:4 * K] = self.sqrt_r * np.eye(K)
        J[4 * K:5 * K] = self.sqrt_dr * (np.eye(K) - np.eye(K, k=-1))
        J[5 * K] = self.sqrt_qt * (dE[-1, 1] + self.s.lookahead_m * math.cos(E[-1, 2]) * dE[-1, 2])
        self.last_dE = dE         # d(errors)/dw of this residual (MM-LB-NMPC's boundary sequences reuse it)
        if self.extra_residuals is not None:
            r2, J2 = self.extra_residuals(E, dE)
            r, J = np.concatenate([r, r2]), np.vstack([J, J2])
        return r, J

    def cost(self, w: np.ndarray) -> float:
        E = self.cost_frame(self.errors(self.rollout(w, with_jac=False)[0]))
        if self.cost_errors is not None:
            E = self.cost_errors(E)
        extra = self._extra(w, E)
        if self.extra_residuals is not None:
            extra = np.concatenate([extra, self.extra_residuals(E, None)[0]])
        return 0.5 * float(np.sum((E * self.sqrt_q) ** 2) + self.s.r_w * np.sum((w - self.w_ref) ** 2)
                           + extra @ extra)


def _propagate_delay(ctx: StepContext, dt: float, model: DisturbanceModel | None,
                     v_prev: tuple[float, float], lag: ActuatorLag):
    """Eq. 7.12 (its mean): carry the estimate, captured D periods ago, forward through the D commands
    applied since, with the same model the horizon uses, so that the problem starts from now and its
    first a-vector pairs the right pose, velocities and commands (as experiences were built)."""
    x = np.array(ctx.pose, dtype=float)
    u_before = ctx.cmd_before_capture if ctx.cmd_before_capture is not None else ctx.delayed_cmds[0]
    hint = ctx.vertex
    xi = ctx.xi_capture
    trace = []      # (x, a, vbar, wbar) per delayed period: the robust laws carry the covariance along too
    for v_i, w_i in ctx.delayed_cmds:
        g = np.zeros(3)
        pr = ctx.path.project(x, hint)
        hint = pr.vertex
        a = np.array([pr.distance_m, pr.lateral_m, pr.heading_rad, *v_prev, v_i, w_i, *u_before])
        (vb, wb), xi = lag.step(xi, (v_i, w_i))
        trace.append((x.copy(), a, vb, wb))
        if model is not None:
            g = model.mean_and_grad(a)[0]
        c, s = math.cos(x[2]), math.sin(x[2])
        x_next = np.array([x[0] + vb * dt * c + c * g[0] - s * g[1], x[1] + vb * dt * s + s * g[0] + c * g[1],
                           x[2] + wb * dt + g[2]])
        v_prev = ((c * (x_next[0] - x[0]) + s * (x_next[1] - x[1])) / dt, (x_next[2] - x[2]) / dt)
        u_before = (v_i, w_i)
        x = x_next
    return x, ctx.path.project(x, hint).distance_m, v_prev, u_before, trace


def crab_offsets(model: DisturbanceModel, s_d: np.ndarray, taught: np.ndarray, tangent: np.ndarray, v: np.ndarray,
                 w_ref: np.ndarray, dt: float, passes: int = 3, min_speed_mps: float = 0.2,
                 max_offset_rad: float = 0.2) -> np.ndarray:
    """(K,) the heading, relative to the taught heading, at which the learned model has x_1..x_K move
    along the route. Where the robot slides sideways (a side slope), holding the route takes a crab
    angle -atan2(g_lat, v dt + g_along) that shrinks as the speed grows; the taught heading holds the
    crab of the teach speed. Weighed against it, a robot repeating faster is pulled uphill of the route
    (and the terminal lookahead, extrapolating along a heading that is not its course, adds to it): a
    steady offset that appeared exactly when the model became accurate. Per desired pose the model is
    asked at the route pose (lateral error 0) driving the route's turn rate with its heading
    disturbance compensated; crab, command and speed are settled by a few fixed-point passes (all
    poses in one batch each). Below `min_speed_mps` (stopping) there is no course to hold: 0."""
    K = len(v)
    idx = np.minimum(np.arange(1, K + 1), K - 1)     # the inputs leaving x_j (the last repeats)
    vj, wr = np.asarray(v, dtype=float)[idx], np.asarray(w_ref, dtype=float)[idx]
    A = np.zeros((K, 9))
    A[:, 0] = s_d[1:]
    A[:, 3], A[:, 4], A[:, 5], A[:, 6], A[:, 7], A[:, 8] = vj, wr, vj, wr, vj, wr
    e_h = np.zeros(K)
    for _ in range(passes):
        g = model.mean(A)
        crab = -np.arctan2(g[:, 1], np.maximum(vj * dt + g[:, 0], 0.5 * vj * dt))
        e_h = np.remainder(tangent[1:] + crab - taught[1:, 2] + math.pi, 2 * math.pi) - math.pi
        A[:, 2] = e_h
        A[:, 6] = A[:, 8] = wr - g[:, 2] / dt          # the command that cancels the heading disturbance
        A[:, 3] = vj + g[:, 0] / dt
    e_h = np.clip(e_h, -max_offset_rad, max_offset_rad)
    e_h[vj < min_speed_mps] = 0.0
    return e_h


def build_problem(ctx: StepContext, settings: NMPCSettings, dt: float,
                  model: DisturbanceModel | None) -> tuple[HorizonProblem, np.ndarray]:
    """Desired states, speeds, reference turn rates and bounds for this step; returns (problem, w_limit)."""
    K = settings.horizon
    path = ctx.path
    if ctx.prev_pose is not None:
        pp, x0 = ctx.prev_pose, ctx.pose
        c, s = math.cos(pp[2]), math.sin(pp[2])
        v_prev = ((c * (x0[0] - pp[0]) + s * (x0[1] - pp[1])) / dt,
                  math.remainder(x0[2] - pp[2], 2 * math.pi) / dt)
    else:
        v_prev = ctx.cmd_before_capture or ctx.prev_cmd   # no earlier estimate: as commanded
    x0, s0, u_prev = np.array(ctx.pose, dtype=float), ctx.s_m, ctx.prev_cmd
    trace = []
    lag = settings.lag(dt)
    if ctx.delayed_cmds and settings.delay_compensation:
        x0, s0, v_prev, u_prev, trace = _propagate_delay(ctx, dt, model, v_prev, lag)
    s_d = np.empty(K + 1)
    v = np.empty(K)
    s_d[0] = s0
    xi = ctx.xi_now
    for j in range(K):
        v[j] = ctx.v_mps if j == 0 else ctx.speed_at(s_d[j])
        (vb, _), xi = lag.step(xi, (v[j], 0.0))
        s_d[j + 1] = s_d[j] + vb * dt     # where the robot gets to at these speeds (its lag included)
    # taught headings: what the heading error is measured against; route direction: what along and
    # lateral errors are measured along
    desired, tangent, _ = path.frames_at(s_d)
    kappa = np.interp(s_d[:-1], path.s, path.curvature)
    w_ref = v * kappa
    w_limit = np.array([ctx.w_limit_at(vj) for vj in v])
    # keep headings continuous with the desired ones (no 2*pi jumps inside the rollout)
    x0[2] = desired[0, 2] + math.remainder(x0[2] - desired[0, 2], 2 * math.pi)
    desired[:, 2] = desired[0, 2] + np.unwrap(desired[:, 2] - desired[0, 2])
    problem = HorizonProblem(x0, desired, s_d, v, w_ref, dt, settings, model, v_prev, u_prev, tangent,
                             lag, ctx.xi_now)
    problem.delay_trace = trace
    if model is not None and settings.crab_reference:
        problem.head_offset = crab_offsets(model, s_d, desired, tangent, v, w_ref, dt)
    problem.kappa = kappa
    problem.path = path
    return problem, w_limit


class LBNMPCLaw:
    """The LB-NMPC steering law. `model_for(ctx)` gives the disturbance model of the local window (None:
    the nominal model, as before any experience exists or when learning is off)."""
    name = "lb-nmpc"

    def __init__(self, settings: NMPCSettings, dt: float,
                 model_for: Callable[[StepContext], DisturbanceModel | None] = lambda ctx: None):
        self.settings = settings
        self.dt = dt
        self.model_for = model_for
        self._prev: np.ndarray | None = None
        self.last_plan: Plan | None = None

    def angular(self, ctx: StepContext) -> LawResult:
        model = self.model_for(ctx)
        problem, w_limit = build_problem(ctx, self.settings, self.dt, model)
        if self._prev is not None:
            u0 = np.concatenate([self._prev[1:], self._prev[-1:]])   # warm start: shift by one period
        else:
            u0 = problem.w_ref.copy()
        res = gauss_newton(problem.residual, u0, -w_limit, w_limit, max_iter=self.settings.max_iter,
                           tol=self.settings.tol, max_evals=self.settings.max_evals)
        self._prev = res.u
        X, _ = problem.rollout(res.u, with_jac=False)
        self.last_plan = Plan(res.u, X, problem.D, res.cost, res.iterations, res.converged)
        return LawResult(float(res.u[0]), res.iterations, X[1:],
                         {"cost": res.cost, "converged": res.converged, "status": res.status,
                          "evaluations": res.evaluations, "learned": model is not None})

"""The prediction and the cost along the horizon, shared by every NMPC law (thesis 5.2, 5.3.1, 7.2).

Prediction model (eq. 5.14, 5.26), states in the route's frame:

    x_{j+1} = f(x_j, u_j) + R(theta_j) g(a_j),    a_j = (route coords of x_j, v_{j-1}, u_j, u_{j-1})

with g the GP posterior mean of the local window (body frame, as the experiences are built, see
experience.py) and v_{j-1} recomputed from consecutive predicted poses as in 5.3.1. With a drive lag
(actuator.py) the robot moves at ubar = L u + c xi0 per axis instead of at u; with an Ackermann
steering's rate limit the turn rate is v times a rate-limited curvature (nonlinear, its Jacobians exact).

Errors (eq. 5.16): x_j against the desired state x_{d,j} of the `HorizonReference`, along and lateral
along the route's direction there, heading against the taught heading (the same definitions the
experiences use); the cost measures the heading against the taught heading plus `head_offset` (the
learned crab, nmpc.crab_offsets) plus `route_offset` (the route's averaged heading where the robot
cannot steer the teach pass's wiggles: Path.heading_offset_at), the corridor limits against the taught
heading itself. The cost adds
R on the deviation of w from the route's own turn rate, an input-rate term and a terminal term on the
lateral error `lookahead_m` ahead of x_K.

All Jacobians are analytic: forward sensitivities of the rollout with the GP's mean gradient
(`GaussianProcess.mean_and_grad`), no finite differences in the loop.
"""
from __future__ import annotations

import copy
import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Protocol

import numpy as np

from common.path import Path
from services.controller.actuator import ActuatorLag

if TYPE_CHECKING:
    from services.controller.settings import NMPCSettings


class DisturbanceModel(Protocol):
    def mean_and_grad(self, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...

    def mean(self, A: np.ndarray) -> np.ndarray: ...


@dataclass(frozen=True)
class HorizonReference:
    """Where the robot should be after each period, and the frames its errors are measured in."""
    s_m: np.ndarray            # (K+1,) arc length of the desired poses; s_m[0] is the robot's own
    poses: np.ndarray          # (K+1, 3) taught poses there, headings continuous along the horizon
    direction_rad: np.ndarray  # (K+1,) the route's direction there: along/lateral errors are taken along it
    cos_dir: np.ndarray        # (K+1,) its cosine and sine
    sin_dir: np.ndarray
    kappa: np.ndarray          # (K,) route curvature at s_m[:-1]
    heading_slope: np.ndarray  # (K,) d(taught heading)/ds at s_m[1:], rad/m
    head_offset: np.ndarray    # (K,) the cost's heading reference of x_1..x_K minus the taught heading
    route_offset: np.ndarray   # (K,) ... and the route's own part of it (Path.heading_offset_at)


def reference_at(path: Path, s_d: np.ndarray, head_offset: np.ndarray | None = None) -> HorizonReference:
    """The reference at arc lengths s_d (K+1,): the one way every law builds it."""
    poses, direction, slope = path.frames_at(s_d)
    poses[:, 2] = poses[0, 2] + np.unwrap(poses[:, 2] - poses[0, 2])   # no 2 pi jumps inside the rollout
    K = len(s_d) - 1
    return HorizonReference(s_m=s_d, poses=poses, direction_rad=direction, cos_dir=np.cos(direction),
                            sin_dir=np.sin(direction),
                            kappa=np.interp(s_d[:-1], path.s, path.curvature), heading_slope=slope[1:],
                            head_offset=np.zeros(K) if head_offset is None else np.asarray(head_offset, float),
                            route_offset=path.heading_offset_at(s_d[1:]))


@dataclass(frozen=True)
class DelayedPeriod:
    """One period of localization delay, as the estimate was carried through it (eq. 7.12)."""
    pose: np.ndarray     # (3,) at the start of the period
    a: np.ndarray        # (9,) the disturbance input of the period
    v_mps: float         # what the robot moved at (the drive's lag applied)
    w_radps: float


@dataclass(frozen=True)
class HorizonStart:
    """Where the horizon starts: the estimate carried forward to now and what came before it."""
    x0: np.ndarray                      # (3,) pose in the route frame, heading continuous with the reference
    v_prev_act: tuple[float, float]     # body velocities over the period before (thesis 5.3.1)
    u_prev: tuple[float, float]         # the command of the period before
    xi0: tuple[float, float] = (0.0, 0.0)     # the drive's state: speeds (or speed, curvature) reached (actuator.py)
    delay: tuple[DelayedPeriod, ...] = ()     # the periods the estimate was carried through


@dataclass(frozen=True)
class LagTerms:
    """ubar = L u + c per axis over the horizon (actuator.py), c already times the drive's state."""
    Lv: np.ndarray
    cv: np.ndarray
    Lw: np.ndarray
    cw: np.ndarray


@dataclass(frozen=True)
class _StepTerms:
    """What the sensitivities need of each step of a mean rollout."""
    cs: np.ndarray            # (K, 2) cos, sin of theta_j
    gg: np.ndarray            # (K, 2) disturbance x, y (body frame)
    prev: np.ndarray          # (K, 4) cos, sin of theta_{j-1}; x_j - x_{j-1}, y_j - y_{j-1}
    Dg: np.ndarray | None     # (K, 3, 9) the GP mean's gradients


class HorizonProblem:
    """One NMPC problem: start, reference, speed profile, model. Its reference never changes;
    `following` and `with_head_offset` give new problems."""

    def __init__(self, start: HorizonStart, ref: HorizonReference, v: np.ndarray, w_ref: np.ndarray, dt: float,
                 settings: NMPCSettings, model: DisturbanceModel | None, path: Path,
                 lag: ActuatorLag | None = None):
        self.start = start
        self.ref = ref
        self.v = v                  # (K,) the profile's linear speeds (the desired inputs)
        self.w_ref = w_ref          # (K,) the route's own turn rates at them
        self.dt = dt
        self.s = settings
        self.model = model
        self.path = path
        self.K = len(v)
        self.sqrt_q = np.sqrt([settings.q_along, settings.q_lat, settings.q_head])
        self.sqrt_r = math.sqrt(settings.r_w)
        self.sqrt_dr = math.sqrt(settings.r_dw)
        self.sqrt_qt = math.sqrt(settings.q_terminal)
        self.lag: LagTerms | None = None
        self._rate_lag = lag if lag is not None and lag.rate_limited else None   # the turn rate is nonlinear
        self.turn_gain = 1.0 if lag is None else lag.turn_gain     # the robot's turn rate per commanded
        if lag is not None and lag.active:
            Lv, cv, Lw, cw = lag.matrices(self.K)
            self.lag = LagTerms(Lv, cv * start.xi0[0], Lw, cw * start.xi0[1])
        K = self.K
        self._J_in = np.vstack([self.sqrt_r * np.eye(K), self.sqrt_dr * (np.eye(K) - np.eye(K, k=-1))])
        self._memo: list[tuple] = []   # the last rollouts: a solver's final iterate is usually among them

    @property
    def curvature_steered(self) -> bool:
        """The robot turns by the curvature w / v of its command (an Ackermann's steering, with its rate limit)."""
        return self._rate_lag is not None

    @property
    def x0(self) -> np.ndarray:
        return self.start.x0

    @property
    def u_prev(self) -> tuple[float, float]:
        return self.start.u_prev

    def _with_ref(self, ref: HorizonReference, keep_memo: bool) -> HorizonProblem:
        clone = copy.copy(self)
        clone.ref = ref
        clone._memo = list(self._memo) if keep_memo else []
        return clone

    def with_model(self, model: DisturbanceModel | None) -> HorizonProblem:
        """This problem planned with another disturbance model (held_turn.py)."""
        clone = copy.copy(self)
        clone.model = model
        clone._memo = []
        return clone

    def following(self, v: np.ndarray) -> HorizonProblem:
        """This problem with the desired poses where speeds v take the robot (C-/RC-LB-NMPC): measured
        against poses placed at the scheduled speed, a plan that slows down would be judged against
        route points ahead of it, a phantom error in turns that the corridor limits then fight."""
        s_d = self.ref.s_m[0] + np.concatenate([[0.0], np.cumsum(self.effective(v)[0]) * self.dt])
        if np.array_equal(s_d, self.ref.s_m):
            return self
        return self._with_ref(reference_at(self.path, s_d, self.ref.head_offset), keep_memo=False)

    def with_head_offset(self, head_offset: np.ndarray) -> HorizonProblem:
        """This problem with the cost's heading measured against taught heading + head_offset (K,);
        rollouts do not depend on it and stay memoized."""
        return self._with_ref(replace(self.ref, head_offset=np.asarray(head_offset, float)), keep_memo=True)

    def effective(self, v: np.ndarray, w: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
        """The speeds the robot moves at over each period under commands (v, w)."""
        if self.lag is None:
            return v, w
        vb = self.lag.Lv @ v + self.lag.cv
        return vb, None if w is None else self._turn_rates(np.asarray(w, dtype=float), v, vb)[0]

    def _turn_rates(self, w: np.ndarray, v: np.ndarray, vb: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """The periods' average turn rates under commands (v, w) at average speeds vb, their derivatives
        by w (None: the identity) and by v (None: none; an Ackermann robot turns at v times its curvature)."""
        lag = self.lag
        if lag is None:
            return w, None, None
        if self._rate_lag is None:
            return lag.Lw @ w + lag.cw, lag.Lw, None
        wb, Lw, by_v, by_vb = self._rate_lag.turn_rates(w, v, vb, self.start.xi0[1])
        return wb, Lw, by_v + by_vb[:, None] * lag.Lv

    # --- prediction ------------------------------------------------------------------------------
    def rollout(self, w: np.ndarray, with_jac: bool, v: np.ndarray | None = None, with_v_jac: bool = False,
                a_out: np.ndarray | None = None):
        """Predicted poses X (K+1, 3) and, with_jac, dX/dw (K+1, 3, K); with_v_jac also dX/dv (`v`
        overrides the profile's speeds). `a_out` (K, 9) receives the disturbance inputs a_j.
        Returns (X, dX/dw) or, with_v_jac, (X, dX/dw, dX/dv)."""
        key = (np.asarray(w, dtype=float).tobytes(), None if v is None else np.asarray(v, dtype=float).tobytes())
        for k, jac, vjac, out, A, _ in self._memo:
            if k == key and (jac or not with_jac) and (vjac or not with_v_jac):
                if a_out is not None:
                    a_out[:] = A
                X, S = out[0], out[1] if with_jac else None
                return (X, S, out[2]) if with_v_jac else (X, S)
        A = np.empty((self.K, 9)) if a_out is None else a_out
        v_all = self.v if v is None else v
        vb = self.effective(v_all)[0]
        wb, Lw, Wv = self._turn_rates(np.asarray(w, dtype=float), v_all, vb)
        X, terms = self._mean(w, v_all, vb, wb, A, with_jac or with_v_jac)
        Sw = Sv = None
        if terms is not None:
            Sw, Sv = self._sensitivities(terms, np.asarray(vb, dtype=float), (Lw, Wv), with_jac, with_v_jac)
        out = (X, Sw, Sv)
        Dg = terms.Dg if terms is not None else None
        self._memo = [(key, with_jac, with_v_jac, out, A.copy(), Dg)] + self._memo[:1]
        return out if with_v_jac else (X, Sw)

    def model_gradients(self, w: np.ndarray) -> np.ndarray:
        """The disturbance model's gradients dg/da (K, 3, 9) along the rollout of turn rates w at the
        profile's speeds (no sensitivities: one pass of the model)."""
        if self.model is None:
            raise ValueError("no disturbance model")
        key = (np.asarray(w, dtype=float).tobytes(), None)
        for k, _, _, _, _, Dg in self._memo:
            if k == key and Dg is not None:     # a solver's iterate: its rollout had them already
                return Dg
        vb = self.effective(self.v)[0]
        wb = self._turn_rates(np.asarray(w, dtype=float), self.v, vb)[0]
        return self._mean(w, self.v, vb, wb, np.empty((self.K, 9)), True)[1].Dg

    def _mean(self, w: np.ndarray, v_all: np.ndarray, vb_all: np.ndarray, wb_all: np.ndarray, a_out: np.ndarray,
              jac: bool) -> tuple[np.ndarray, _StepTerms | None]:
        """The mean rolled out point by point (the GP's input depends on the state)."""
        K, dt, model = self.K, self.dt, self.model
        ref = self.ref
        D, sD, cD, sinD = ref.poses, ref.s_m, ref.cos_dir, ref.sin_dir
        X = np.empty((K + 1, 3))
        X[0] = self.x0
        a = np.zeros(9)
        xj, yj, thj = (float(x) for x in self.x0)
        xp = yp = thp = cp = sp = 0.0
        if jac:
            cs, gg, prev = np.empty((K, 2)), np.zeros((K, 2)), np.zeros((K, 4))
            Dg_all = np.empty((K, 3, 9)) if model is not None else None
        for j in range(K):
            c, s = math.cos(thj), math.sin(thj)
            v, wj = v_all[j], float(w[j])
            gx = gy = gth = 0.0
            a[5], a[6] = v, wj        # the inputs matter to a prior that depends on the commands
            if model is not None:
                # a_j (experience.py A_NAMES): route coords, v_{j-1}, u_j, u_{j-1}
                cd, sd = cD[j], sinD[j]
                dx, dy = xj - D[j, 0], yj - D[j, 1]
                a[0] = sD[j] + cd * dx + sd * dy
                a[1] = -sd * dx + cd * dy
                a[2] = math.remainder(thj - D[j, 2], 2 * math.pi)
                if j == 0:
                    a[3], a[4] = self.start.v_prev_act
                    a[7], a[8] = self.start.u_prev
                else:
                    a[3] = (cp * (xj - xp) + sp * (yj - yp)) / dt
                    a[4] = (thj - thp) / dt
                    a[7], a[8] = v_all[j - 1], w[j - 1]
                g, dg = model.mean_and_grad(a)
                if jac:
                    Dg_all[j] = dg
                gx, gy, gth = float(g[0]), float(g[1]), float(g[2])
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
        return X, (_StepTerms(cs, gg, prev, Dg_all) if jac else None)

    def _sensitivities(self, t: _StepTerms, vb: np.ndarray, turn: tuple[np.ndarray | None, np.ndarray | None],
                       with_w: bool, with_v: bool):
        """dX/dw and dX/dv (each (K+1, 3, K) or None). Per step x_{j+1} = F(x_j, x_{j-1}, u_j, u_{j-1}),
        so S_{j+1} = A_j S_j + C_j S_{j-1} + b_j e_j' + d_j e_{j-1}'; both computed side by side in one
        array (columns: w's, then v's), one product per step. `turn`: the average turn rates' derivatives
        by w and v (`_turn_rates`)."""
        K, dt, lag = self.K, self.dt, self.lag
        Lw, Wv = turn
        Aj, Cj, b, bv, d_w, d_v = self._step_jacobians(t, vb)
        n_w = K if with_w else 0
        SS = np.zeros((K + 1, 3, n_w + (K if with_v else 0)))
        for j in range(K):
            Sn = Aj[j] @ SS[j]
            if Cj is not None and j > 0:
                Sn += Cj[j] @ SS[j - 1]
            if with_w:
                Sn[:, j] += b[j]
                if lag:
                    Sn[2, :j + 1] += dt * Lw[j, :j + 1]
                if d_w is not None and j > 0:
                    Sn[:, j - 1] += d_w[j]
            if with_v:
                Sn[:, n_w + j] += bv[j]
                if lag:
                    Sn[:2, n_w:n_w + j + 1] += np.outer(dt * t.cs[j], lag.Lv[j, :j + 1])
                if Wv is not None:
                    Sn[2, n_w:n_w + j + 1] += dt * Wv[j, :j + 1]
                if d_v is not None and j > 0:
                    Sn[:, n_w + j - 1] += d_v[j]
            SS[j + 1] = Sn
        return (SS[:, :, :K] if with_w else None), (SS[:, :, n_w:] if with_v else None)

    def _step_jacobians(self, t: _StepTerms, vb: np.ndarray):
        """For every step j at once: A_j = dx_{j+1}/dx_j, C_j = dx_{j+1}/dx_{j-1} (None without a model),
        b_j, bv_j = dx_{j+1}/d(w_j, v_j) (the nominal part is left to the caller's lag terms when there is
        a lag), d_w, d_v = dx_{j+1}/d(w_{j-1}, v_{j-1}) through the GP's inputs (None without a model)."""
        K, dt = self.K, self.dt
        c, s = t.cs[:, 0], t.cs[:, 1]
        gx, gy = t.gg[:, 0], t.gg[:, 1]
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
        if t.Dg is None:
            return A, None, b, bv, None, None
        Dg = t.Dg
        # R(theta_j) Dg_j: the GP's gradient in the world frame, (K, 3, 9)
        RDg = np.empty_like(Dg)
        RDg[:, 0] = c[:, None] * Dg[:, 0] - s[:, None] * Dg[:, 1]
        RDg[:, 1] = s[:, None] * Dg[:, 0] + c[:, None] * Dg[:, 1]
        RDg[:, 2] = Dg[:, 2]
        # d a_j / d x_j: route coordinates (rows 0-2) and, from j = 1, the measured previous velocity (3-4)
        cd, sd = self.ref.cos_dir[:K], self.ref.sin_dir[:K]
        cp, sp, ddx, ddy = t.prev[:, 0], t.prev[:, 1], t.prev[:, 2], t.prev[:, 3]
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

    # --- errors and cost -------------------------------------------------------------------------
    def errors(self, X: np.ndarray) -> np.ndarray:
        """(K, 3) errors of x_1..x_K in the frames of their desired poses (along, lateral, heading)."""
        D, cd, sd = self.ref.poses, self.ref.cos_dir[1:], self.ref.sin_dir[1:]
        d = X[1:, :2] - D[1:, :2]
        return np.column_stack([cd * d[:, 0] + sd * d[:, 1], -sd * d[:, 0] + cd * d[:, 1],
                                np.remainder(X[1:, 2] - D[1:, 2] + math.pi, 2 * math.pi) - math.pi])

    def error_jacobian(self, S: np.ndarray) -> np.ndarray:
        """d errors / d inputs (K, 3, n) from the rollout's sensitivities S (K+1, 3, n)."""
        cd, sd = self.ref.cos_dir[1:, None], self.ref.sin_dir[1:, None]
        Sx = S[1:]
        dE = np.empty(Sx.shape)
        dE[:, 0] = cd * Sx[:, 0] + sd * Sx[:, 1]
        dE[:, 1] = -sd * Sx[:, 0] + cd * Sx[:, 1]
        dE[:, 2] = Sx[:, 2]
        return dE

    def cost_frame(self, E: np.ndarray) -> np.ndarray:
        """Errors (K, 3) as the cost weighs them: heading against the taught heading + head_offset."""
        off = self.ref.head_offset + self.ref.route_offset
        if not off.any():
            return E
        E = E.copy()
        E[:, 2] -= off
        return E

    def tracking(self, w: np.ndarray, with_jac: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """The errors the cost weighs (K, 3) and, with_jac, their derivatives by w (K, 3, K)."""
        X, S = self.rollout(w, with_jac=with_jac)
        return self.cost_frame(self.errors(X)), (self.error_jacobian(S) if with_jac else None)

    def input_residuals(self, w: np.ndarray) -> np.ndarray:
        """(2K,) sqrt(R) (w - w_ref) and the input-rate term; their Jacobian is `input_jacobian`."""
        dw = np.diff(np.concatenate([[self.start.u_prev[1]], w]))
        return np.concatenate([self.sqrt_r * (w - self.w_ref), self.sqrt_dr * dw])

    def input_jacobian(self) -> np.ndarray:
        return self._J_in

    def terminal(self, E: np.ndarray) -> float:
        """The terminal residual: the lateral error `lookahead_m` ahead of x_K."""
        return self.sqrt_qt * (E[-1, 1] + self.s.lookahead_m * math.sin(E[-1, 2]))

    def terminal_jacobian(self, E: np.ndarray, dE: np.ndarray) -> np.ndarray:
        return self.sqrt_qt * (dE[-1, 1] + self.s.lookahead_m * math.cos(E[-1, 2]) * dE[-1, 2])

    def residual(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """LB-NMPC's least-squares residual r(w) (5K + 1) and its Jacobian (5K + 1, K)."""
        E, dE = self.tracking(w)
        K = self.K
        r = np.concatenate([(E * self.sqrt_q).ravel(), self.input_residuals(w), [self.terminal(E)]])
        J = np.empty((5 * K + 1, K))
        J[:3 * K] = (dE * self.sqrt_q[None, :, None]).reshape(3 * K, K)
        J[3 * K:5 * K] = self.input_jacobian()
        J[5 * K] = self.terminal_jacobian(E, dE)
        return r, J

    def cost(self, w: np.ndarray, error_offset: np.ndarray | None = None) -> float:
        """1/2 |r(w)|^2; with `error_offset` (K, 3) added to the errors first (a boundary sequence of
        MM-LB-NMPC, eq. 6.5)."""
        E, _ = self.tracking(w, with_jac=False)
        if error_offset is not None:
            E = E + error_offset
        r_in = self.input_residuals(w)
        return 0.5 * float(np.sum((E * self.sqrt_q) ** 2) + r_in @ r_in + self.terminal(E) ** 2)

"""The uncertainty-aware LB-NMPC laws: Min-Max (thesis ch. 6) and (Robust) Constrained (ch. 7).

Both start like LB-NMPC (nmpc.py: desired states from the schedule, the delayed estimate carried to now,
the GP mean of the local window in the model) and add the horizon's covariance from the sigma-point
transform (uncertainty.py), started from the localizer's covariance carried through the delay (7.12).

MM-LB-NMPC (eq. 6.2-6.9): the cost is that of the worst of the 2^3 boundary sequences
xbar_j + Gamma_l 3 sigma_j (eq. 6.5; errors along, lateral and heading in the route frame), with the
mean's Jacobian for all of them (eq. 6.7-6.8). It is minimized as a min-max (minmax.py): each iteration
linearizes all eight sequences and solves a small epigraph QP, then takes the damped step beta of eq. 6.9
that lowers the true worst-case cost; it stops when the step is below tol (the thesis's alpha). The
thesis's iteration on the single worst sequence stalls where several are worst at once. The covariance
is computed once per step at the warm start (it moves little within a solve).

C-/RC-LB-NMPC (eq. 7.2-7.6): linear and angular speeds are both optimized; the cost weighs the
errors of the mean sequence and the deviation from the desired inputs (scheduled speed, route turn
rate), the errors measured against the route poses the planned speeds reach; the lateral and heading
errors of the mean must stay inside the corridor tightened by alpha * sigma (eq. 7.4; alpha = 0 is
C-LB-NMPC); speeds and rates stay inside the actuator limits (eq. 7.5). RC first caps the speeds with
the fastest of a ladder of slowed-down profiles whose 3-sigma region fits the corridor (`_speed_cap`).
Solved as SQP: the covariance is propagated once per step around that profile, and each
iteration linearizes the rollout (analytic sensitivities for v and w) and the lateral sigma's dependence
on speed and solves the QP with one warm-started OSQP workspace (sqp_qp.py); violating a tightened limit
is possible only through a slack with a heavy L1 price, so the QP is always feasible and the law says
when it had to use it. When even the first predicted step's 3-sigma region does not fit inside the
corridor, or the robot is already outside it, the law stops the robot and says why.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Callable

import numpy as np

from services.controller.laws import LawResult, StepContext
from services.controller.minmax import MinMaxQP, boundary_costs, solve_minmax
from services.controller.nmpc import HorizonProblem, NMPCSettings, Plan, build_problem, crab_offsets
from services.controller.sqp_qp import CorridorQP
from services.controller.uncertainty import (DisturbanceVariance, PriorStd, lateral_sigma_speed_jacobian, propagate,
                                             route_sigmas, sigma_point_step, variance_speed_derivatives)



def _variance_model(gp, s: NMPCSettings) -> DisturbanceVariance:
    return DisturbanceVariance(gp, PriorStd(base=s.prior_std_base, per_mps=s.prior_std_per_mps,
                                            per_radps=s.prior_std_per_radps), s.process_std)


def initial_covariance(ctx: StepContext, problem: HorizonProblem, var: DisturbanceVariance,
                       s: NMPCSettings, dt: float) -> np.ndarray:
    """The localizer's covariance, carried through the periods of localization delay (eq. 7.12)."""
    Sigma = np.array(ctx.pose_cov, dtype=float) if ctx.pose_cov is not None else np.diag([1e-4, 1e-4, 1e-4])
    trace = getattr(problem, "delay_trace", [])
    if trace:
        A = np.array([t[1] for t in trace])
        G, V = var.with_mean(A)
        for (x, _a, v, w), g, vg in zip(trace, G, V):
            Sigma = sigma_point_step(x, Sigma, g, vg, v, w, dt, s.sp_gamma)
    return Sigma


def horizon_sigmas(problem: HorizonProblem, X: np.ndarray, A: np.ndarray, v: np.ndarray, w: np.ndarray,
                   var: DisturbanceVariance, Sigma0: np.ndarray, s: NMPCSettings, dt: float):
    """Covariances (K+1, 3, 3) and the route-frame standard deviations (K, 3) of x_1..x_K."""
    G, V = var.with_mean(A)
    vb, wb = problem.effective(v, w)          # the robot moves at these (the drive's lag)
    Sig = propagate(X, A, G, V, vb, wb, Sigma0, dt, s.sp_gamma)
    direction = np.arctan2(problem.sinD[1:], problem.cD[1:])
    return Sig, route_sigmas(Sig, direction)


class MMLBNMPCLaw:
    """Min-Max LB-NMPC (thesis ch. 6). `model_for(ctx)`: the GP of the local window or None."""
    name = "mm-lb-nmpc"

    def __init__(self, settings: NMPCSettings, dt: float, model_for: Callable[[StepContext], object] = lambda c: None):
        self.settings = settings
        self.dt = dt
        self.model_for = model_for
        self._prev: np.ndarray | None = None
        self.last_plan: Plan | None = None
        self.last_problem: dict | None = None
        self._qp: MinMaxQP | None = None

    def angular(self, ctx: StepContext) -> LawResult:
        s = self.settings
        gp = self.model_for(ctx)
        problem, w_limit = build_problem(ctx, s, self.dt, gp)
        var = _variance_model(gp, s)
        u0 = np.concatenate([self._prev[1:], self._prev[-1:]]) if self._prev is not None else problem.w_ref.copy()
        u0 = np.clip(u0, -w_limit, w_limit)
        A = np.empty((problem.K, 9))
        X0, _ = problem.rollout(u0, with_jac=True, a_out=A)     # Gauss-Newton's first residual reuses it
        Sigma0 = initial_covariance(ctx, problem, var, s, self.dt)
        _, sig = horizon_sigmas(problem, X0, A, problem.v, u0, var, Sigma0, s, self.dt)
        bound = s.mm_sigmas * sig                                   # (K, 3)
        self.last_sigmas = sig
        # eq. 6.3-6.6: the min-max over all eight boundary sequences at once, from the warm start
        # (minmax.py: an SQP in epigraph form; Gauss-Newton on whichever sequence is worst, as the thesis
        # iterates, stalls where several are, well above the optimum)
        if self._qp is None or self._qp.K != problem.K:
            self._qp = MinMaxQP(problem.K)
        res = solve_minmax(problem, bound, u0, -w_limit, w_limit, self._qp, s.max_iter, s.tol, s.max_evals)
        worst_case = int(np.argmax(boundary_costs(problem, bound, res.u, False)))
        self._prev = res.u
        X, _ = problem.rollout(res.u, with_jac=False)
        self.last_plan = Plan(res.u, X, problem.D, res.cost, res.iterations, res.converged)
        # what this step's min-max problem was, for re-solving it elsewhere (bench: CasADi/IPOPT)
        self.last_problem = dict(problem=problem, bound=bound, u0=u0, w_limit=w_limit, model=gp, w=res.u)
        return LawResult(float(res.u[0]), res.iterations, X[1:],
                         {"cost": res.cost, "converged": res.converged, "status": res.status,
                          "evaluations": res.evaluations, "learned": gp is not None,
                          "worst_case": worst_case, "sigma_lat_max_m": float(sig[:, 1].max()),
                          "sigma_head_max_rad": float(sig[:, 2].max())})


class RCLBNMPCLaw:
    """(Robust) Constrained LB-NMPC (thesis ch. 7); alpha = 0 gives C-LB-NMPC."""

    def __init__(self, settings: NMPCSettings, dt: float, model_for: Callable[[StepContext], object] = lambda c: None,
                 alpha: float | None = None):
        self.settings = settings
        self.dt = dt
        self.model_for = model_for
        self.alpha = settings.alpha if alpha is None else alpha
        self.name = "rc-lb-nmpc" if self.alpha > 0 else "c-lb-nmpc"
        self._prev: tuple[np.ndarray, np.ndarray] | None = None
        self._qp: CorridorQP | None = None
        self._rung = 0                       # the speed ladder's rung of the last step
        self.last_plan: Plan | None = None
        self.last_problem: dict | None = None

    @staticmethod
    def _follow_speeds(p: HorizonProblem, v: np.ndarray) -> None:
        """Desired poses where the planned speeds take the robot. Measured against poses placed at the
        scheduled speed, a plan that slows down would be judged against route points ahead of it: in a
        turn their direction differs from the robot's by the turn angle still to come, a phantom lateral
        and heading error that the corridor limits then fight (the law slowed and sped up in turns).
        The cost's heading offsets (the learned crab) are set once per step, after the speed cap; within
        the solve they stay per index (they vary slowly along the route)."""
        s_d = p.sD[0] + np.concatenate([[0.0], np.cumsum(p.effective(v)[0]) * p.dt])
        if np.array_equal(s_d, p.sD) and hasattr(p, "heading_slope"):
            return
        D, direction, slope = p.path.frames_at(s_d)
        D[:, 2] = p.D[0, 2] + np.unwrap(D[:, 2] - p.D[0, 2])
        p.D, p.sD, p.cD, p.sinD = D, s_d, np.cos(direction), np.sin(direction)
        p.kappa = np.interp(s_d[:-1], p.path.s, p.path.curvature)
        p.heading_slope = slope[1:]
        p._memo = []

    SPEED_LADDER = (1.0, 0.85, 0.7, 0.58, 0.48, 0.4, 0.32, 0.25, 0.18, 0.12)

    TURN_HEADROOM = 0.9      # a rung's turn rates stay below this share of the drive's turn-rate limit

    def _speed_cap(self, p: HorizonProblem, v, w, A, var, Sigma0, cap, w_rate_cap: float):
        """(v, w, scale, covariances, route sigmas) of the fastest rung that fits, starting from last step's.
        A rung fits when its 3-sigma region stays inside the corridor and the turn rates that follow the
        route at its speeds (with last step's corrections, scaled) keep some headroom below the drive's
        turn-rate limit `w_rate_cap`: a plan pinned at the limit cannot correct anything (in the deepening
        rut of exp. 2 the law held 2 m/s with its turn rate saturated and was carried off the route). Only
        the rate limit counts here, the one slowing down relieves; an Ackermann's curvature limit binds
        at every speed alike (the SQP keeps to it), and testing it would send the ladder to its bottom."""
        s = self.settings
        ladder = self.SPEED_LADDER
        k_prev = self._rung if self._prev is not None else 0
        kappa0 = p.kappa.copy()
        v0 = np.maximum(v, 1e-3)

        def attempt(k: int):
            # the rung's own profile: tested at the warm start's speeds when those were slower, a rung
            # "fitted" that did not, the SQP drove at it, and the next step fell back (2-step chatter)
            vk = np.clip(ladder[k] * p.v, s.v_min_mps, None)
            self._follow_speeds(p, vk)
            wk = vk * p.kappa + (w - v * kappa0) * vk / v0     # same path, corrections scaled with speed
            # with the sensitivities: the rung that fits is the SQP's first iterate (rollout's memo)
            X = p.rollout(wk, with_jac=True, v=vk, with_v_jac=True, a_out=A)[0]
            Sig, sig = horizon_sigmas(p, X, A, vk, wk, var, Sigma0, s, self.dt)
            t = self.alpha * sig[1:]
            fits = bool(np.all(t[:, 1] <= cap[1:, 1]) and np.all(t[:, 2] <= cap[1:, 2])    # lateral, heading
                        and np.all(np.abs(wk) <= self.TURN_HEADROOM * w_rate_cap))
            return fits, (vk, wk, ladder[k], Sig, sig)

        k = max(k_prev - 1, 0)                 # try one rung faster than last step first
        fits, best = attempt(k)
        while not fits and k + 1 < len(ladder):
            k += 1
            fits, best = attempt(k)
        self._rung = k
        return best

    # --- residuals of eq. 7.2 with both inputs -------------------------------------------------------
    def _residual(self, p: HorizonProblem, v: np.ndarray, w: np.ndarray, A: np.ndarray | None):
        s = self.settings
        K = p.K
        self._follow_speeds(p, v)
        X, Sw, Sv = p.rollout(w, with_jac=True, v=v, with_v_jac=True, a_out=A)
        E = p.errors(X)                 # the corridor's frame (taught heading)
        Ec = p.cost_frame(E)            # the cost's (heading against the learned crab: build_problem)
        kappa = p.kappa
        u_prev_v, u_prev_w = p.u_prev
        sr, srv, sdr, sdv, sqt = math.sqrt(s.r_w), math.sqrt(s.r_v), math.sqrt(s.r_dw), math.sqrt(s.r_dv), p.sqrt_qt
        term = Ec[-1, 1] + s.lookahead_m * math.sin(Ec[-1, 2])
        r = np.concatenate([(Ec * p.sqrt_q).ravel(), sr * (w - v * kappa), srv * (v - p.v),
                            sdr * np.diff(np.concatenate([[u_prev_w], w])),
                            sdv * np.diff(np.concatenate([[u_prev_v], v])), [sqt * term]])
        J = np.zeros((len(r), 2 * K))                    # columns: v_0..v_{K-1}, w_0..w_{K-1}
        cd, sd = p.cD[1:], p.sinD[1:]
        dE = np.zeros((K, 3, 2 * K))                     # d(along, lat, head)_j / d(v, w)
        for cols, S in ((slice(0, K), Sv), (slice(K, 2 * K), Sw)):
            Sx = S[1:]
            dE[:, 0, cols] = cd[:, None] * Sx[:, 0] + sd[:, None] * Sx[:, 1]
            dE[:, 1, cols] = -sd[:, None] * Sx[:, 0] + cd[:, None] * Sx[:, 1]
            dE[:, 2, cols] = Sx[:, 2]
        # the desired pose of x_j moves on by dt per unit of each earlier speed, along the (piecewise
        # straight) route: the along error falls by as much, the heading error by the taught heading's slope
        M = self.dt * np.tril(np.ones((K, K)))
        if p.lag is not None:
            M = M @ p.lag[0]              # ... of each earlier speed the robot reaches (the drive's lag)
        dE[:, 0, :K] -= M
        dE[:, 2, :K] -= p.heading_slope[:, None] * M
        J[:3 * K] = (dE * p.sqrt_q[None, :, None]).reshape(3 * K, 2 * K)
        eye, diff = np.eye(K), np.eye(K) - np.eye(K, k=-1)
        J[3 * K:4 * K, K:] = sr * eye
        J[3 * K:4 * K, :K] = -sr * np.diag(kappa)
        J[4 * K:5 * K, :K] = srv * eye
        J[5 * K:6 * K, K:] = sdr * diff
        J[6 * K:7 * K, :K] = sdv * diff
        J[7 * K] = sqt * (dE[-1, 1] + s.lookahead_m * math.cos(Ec[-1, 2]) * dE[-1, 2])
        return X, E, dE, r, J

    def angular(self, ctx: StepContext) -> LawResult:
        s = self.settings
        corridor = ctx.corridor
        if corridor is None:
            raise ValueError(f"{self.name} needs a corridor ([constraints])")
        why = corridor.contains(ctx.s_m, ctx.e_lat_m, ctx.e_head_rad)
        if why:
            return LawResult(0.0, 0, None, {"learned": False}, v_mps=0.0, stop_reason=f"{why}: stopped")
        # the local window is drawn around the speed the law commands (thesis 5.3.2: l from v_cmd), not the
        # schedule's: this law may drive well below the schedule, and experience there is what it needs
        # (the node's LocalModels moves the window's speed bin with hysteresis: local_model.py)
        v_cmd = float(self._prev[0][min(1, len(self._prev[0]) - 1)]) if self._prev is not None else ctx.v_mps
        gp = self.model_for(dataclasses.replace(ctx, v_mps=v_cmd))
        p, _ = build_problem(ctx, s, self.dt, gp)
        K, dt = p.K, self.dt
        var = _variance_model(gp, s)
        Sigma0 = initial_covariance(ctx, p, var, s, dt)
        v_max = np.minimum(np.full(K, ctx.v_max_mps), np.maximum(p.v, s.v_min_mps))   # never above the desired
        if self._prev is not None:
            v = np.clip(np.concatenate([self._prev[0][1:], self._prev[0][-1:]]), s.v_min_mps, v_max)
            w = np.concatenate([self._prev[1][1:], self._prev[1][-1:]])
        else:
            v, w = p.v.copy(), p.w_ref.copy()
        self._follow_speeds(p, v)
        lo_lat, hi_lat, head_lim = corridor.at(p.sD[1:])
        alpha = self.alpha
        def w_lim_of(v: np.ndarray) -> np.ndarray:
            return np.array([ctx.w_limit_at(max(vj, s.v_min_mps)) for vj in v.tolist()])
        v_start = v
        # the covariance is propagated once per step, around the warm start; within the solve the lateral
        # sigma follows the speeds to first order (it moves little otherwise, and this keeps the per-step
        # cost at one sigma-point pass and one GP variance batch)
        sig_start = np.zeros((K, 3))
        dsig_v = np.zeros((K, K))

        # beyond the first step the band never closes below min_band_fraction of the corridor
        f = 1.0 - s.min_band_fraction
        cap = np.column_stack([np.full(K, np.inf), f * 0.5 * (hi_lat - lo_lat), f * head_lim])
        cap[0] = np.inf

        def tighten(sig: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            """alpha * sigma, capped; and whether each lateral tightening still follows sigma."""
            t = alpha * sig
            return np.minimum(t, cap), t[:, 1] < cap[:, 1]

        def score(it: dict) -> dict:
            """The iterate's merit: cost + slack price of the tightened-corridor violations."""
            E, sig = it["E"], sig_start.copy()
            sig[:, 1] = np.maximum(sig_start[:, 1] + dsig_v @ (it["v"] - v_start), 0.0)
            t, _ = tighten(sig)
            viol = (np.maximum(E[:, 1] + t[:, 1] - hi_lat, 0) + np.maximum(lo_lat - E[:, 1] + t[:, 1], 0)
                    + np.maximum(np.abs(E[:, 2]) + t[:, 2] - head_lim, 0))
            it.update(sig=sig, merit=0.5 * float(it["r"] @ it["r"]) + s.slack_weight * float(viol.sum()),
                      viol=float(viol.max()))
            return it

        def evaluate(v, w, A=None):
            """Everything one SQP iterate needs."""
            X, E, dE, r, J = self._residual(p, v, w, A)
            return score(dict(v=v, w=w, X=X, E=E, dE=dE, r=r, J=J))

        A = np.empty((K, 9))
        speed_scale = 1.0
        if alpha > 0:
            # the fastest of a ladder of speed profiles whose 3-sigma region fits the corridor (with the
            # band left to the mean) over the whole horizon: uncertainty grows with speed, so this is the
            # chapter's "slows down while uncertain". One rung up per step at most, as many down as needed;
            # the SQP then fine-tunes below this cap. Without it the band is infeasible at the scheduled
            # speed, the slack price dominates the cost and the plan flips between steps.
            # the drive's turn-rate limit at any speed (its curvature limit, if any, left out: w_limit_at(inf))
            w_rate_cap = ctx.w_limit_at(math.inf)
            v, w, speed_scale, Sig, sig_start = self._speed_cap(p, v, w, A, var, Sigma0, cap, w_rate_cap)
            v_max = np.maximum(np.minimum(v_max, speed_scale * p.v), s.v_min_mps)
            v_start = v
        w_start = w
        if gp is not None and s.crab_reference:
            # the learned crab at the speeds this step starts from (build_problem's is the schedule's)
            p.head_offset = crab_offsets(gp, p.sD, p.D, np.arctan2(p.sinD, p.cD), v, v * p.kappa, dt)
        cur = evaluate(v, w, A)
        if alpha > 0:
            dvar_dv, dvar_dvprev = variance_speed_derivatives(var, A)
            direction = np.arctan2(p.sinD[1:], p.cD[1:])
            dsig_v = lateral_sigma_speed_jacobian(cur["X"], Sig, p.effective(v)[0], direction, sig_start[:, 1], dt,
                                                  dvar_dv, dvar_dvprev, None if p.lag is None else p.lag[0])
            cur = score(cur)
        sig0 = sig_start[0]
        if alpha > 0 and min(hi_lat[0] - lo_lat[0] - 2 * alpha * sig0[1], head_lim[0] - alpha * sig0[2]) <= 0:
            return LawResult(0.0, 0, cur["X"][1:], {"learned": gp is not None, "sigma_lat_max_m": float(sig0[1])},
                             v_mps=0.0, stop_reason=f"predicted uncertainty no longer fits the corridor "
                                                    f"({alpha:g} sigma: {alpha * sig0[1]:.3f} m lateral, "
                                                    f"{math.degrees(alpha * sig0[2]):.1f} deg heading): stopped")
        if self._qp is None or self._qp.K != K:
            self._qp = CorridorQP(K, s.slack_weight)
        trust_v, trust_w = 0.5, 1.0
        iters, status = 0, "budget"
        evals = 1                       # residual evaluations: max_evals bounds the step's time, as for LB/MM
        for it in range(s.sqp_iter):
            if evals >= s.max_evals:
                break
            iters = it + 1
            v, w = cur["v"], cur["w"]
            w_lim = w_lim_of(v)
            lo_d = np.concatenate([np.maximum(s.v_min_mps - v, -trust_v), np.maximum(-w_lim - w, -trust_w)])
            hi_d = np.concatenate([np.minimum(v_max - v, trust_v), np.minimum(w_lim - w, trust_w)])
            tight, free = tighten(cur["sig"])
            dx, _ = self._qp.solve(cur["r"], cur["J"], cur["E"], cur["dE"], tight, alpha * dsig_v * free[:, None],
                                   lo_lat, hi_lat, head_lim, lo_d, np.maximum(hi_d, lo_d))
            if dx is None:
                status = "qp-failed"
                break
            accepted = None
            for beta in (1.0, 0.5, 0.25):                 # eq. 7.11's beta, by the merit function
                if evals >= s.max_evals:
                    break
                cand = evaluate(np.clip(v + beta * dx[:K], s.v_min_mps, v_max), w + beta * dx[K:])
                evals += 1
                if cand["merit"] < cur["merit"] - 1e-12:
                    accepted = cand
                    break
            if accepted is None:
                if np.max(np.abs(dx)) < 10 * s.tol:
                    status = "converged"
                elif evals < s.max_evals:
                    status = "stalled"
                break
            step = max(np.max(np.abs(accepted["v"] - v)), np.max(np.abs(accepted["w"] - w)))
            cur = accepted
            if step < s.tol:
                status = "converged"
                break
        v, w, sig, r = cur["v"], cur["w"], cur["sig"], cur["r"]
        slack_used = cur["viol"]
        X = p.rollout(w, with_jac=False, v=v)[0]
        self._prev = (v, w)
        # what this step's NLP was, for re-solving it elsewhere (bench: the same problem in CasADi/IPOPT)
        self.last_problem = dict(problem=p, v0=v_start, w0=w_start, sig=sig_start, dsig=dsig_v, cap=cap,
                                 lo=lo_lat, hi=hi_lat, head=head_lim, v_max=v_max, w_lim=w_lim_of(v),
                                 alpha=alpha, merit=cur["merit"], model=gp)
        self.last_plan = Plan(w, X, p.D, float(0.5 * r @ r), iters, status == "converged")
        return LawResult(float(w[0]), iters, X[1:],
                         {"cost": float(0.5 * r @ r), "converged": status == "converged", "status": status,
                          "evaluations": evals,
                          "learned": gp is not None, "violation": slack_used, "speed_scale": speed_scale,
                          "sigma_lat_max_m": float(sig[:, 1].max()), "sigma_head_max_rad": float(sig[:, 2].max())},
                         v_mps=float(v[0]))

"""The SQP of C-/RC-LB-NMPC (eq. 7.2-7.6, 7.11): linear and angular speeds both optimized.

    minimize   1/2 |r(v, w)|^2 + slack_weight * (violation of the tightened corridor)
    r = (Q^1/2 errors of the mean sequence, R^1/2 (w - v kappa), R_v^1/2 (v - v_d), input rates, terminal)

The errors are measured against the route poses the planned speeds reach (`HorizonProblem.following`);
the lateral and heading errors of the mean must stay inside the corridor tightened by alpha * sigma
(eq. 7.4; alpha = 0 is C-LB-NMPC), the tightening capped so that beyond the first step the band keeps
`min_band_fraction` of the corridor; speeds and rates stay inside the actuator limits (eq. 7.5). The
covariance is propagated once per step around the starting plan; within the solve the lateral sigma
follows the speeds to first order (`dsig_v`). Each iteration linearizes the rollout (analytic
sensitivities for v and w) and solves the QP of sqp_qp.py, then takes the damped step beta of eq. 7.11
that lowers the merit (cost + slack price); a step below tol ends the solve. A curvature-steered robot
(an Ackermann) steps in speed and curvature c = w / v instead: its turn-rate bound is its curvature limit
times each step's own speed, and a plan that slows down keeps its curvatures instead of turning the
turn rates of a faster plan into curves tighter than its steering has.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from services.controller.horizon import HorizonProblem, HorizonReference
from services.controller.sqp_qp import CorridorQP
from services.controller.turn_accel import TurnLead


@dataclass(frozen=True)
class Iterate:
    """One SQP iterate and everything the next QP needs."""
    v: np.ndarray          # (K,) speeds
    w: np.ndarray          # (K,) turn rates
    X: np.ndarray          # (K+1, 3) predicted mean
    E: np.ndarray          # (K, 3) errors in the corridor's frame (taught heading)
    dE: np.ndarray         # (K, 3, 2K) their derivatives by (v, w)
    r: np.ndarray          # residual of the cost
    J: np.ndarray          # its Jacobian by (v, w)
    sig: np.ndarray        # (K, 3) route-frame sigmas at these speeds
    merit: float           # 1/2 |r|^2 + slack price of the tightened-corridor violations
    violation: float       # the largest of those violations, m or rad
    reference: HorizonReference   # where (v) takes the robot: what E is measured against


@dataclass(frozen=True)
class CorridorResult:
    iterate: Iterate
    iterations: int
    evaluations: int
    status: str            # converged | budget | stalled | qp-failed


def constrained_residual(p: HorizonProblem, v: np.ndarray, w: np.ndarray, a_out: np.ndarray | None = None):
    """(reference, X, E, dE, r, J) of eq. 7.2 at (v, w), the reference following v; J's columns are v's
    then w's."""
    s, K, dt = p.s, p.K, p.dt
    q = p.following(v)
    X, Sw, Sv = q.rollout(w, with_jac=True, v=v, with_v_jac=True, a_out=a_out)
    E = q.errors(X)                 # the corridor's frame (taught heading)
    Ec = q.cost_frame(E)            # the cost's (heading against the learned crab)
    kappa = q.ref.kappa / p.turn_gain      # the commanded turn rate per speed that turns the robot along the route
    u_prev_v, u_prev_w = p.u_prev
    sr, srv, sdr, sdv = math.sqrt(s.r_w), math.sqrt(s.r_v), math.sqrt(s.r_dw), math.sqrt(s.r_dv)
    r = np.concatenate([(Ec * p.sqrt_q).ravel(), sr * (w - v * kappa), srv * (v - p.v),
                        sdr * np.diff(np.concatenate([[u_prev_w], w])),
                        sdv * np.diff(np.concatenate([[u_prev_v], v])), [q.terminal(Ec)]])
    dE = np.concatenate([q.error_jacobian(Sv), q.error_jacobian(Sw)], axis=2)
    # the desired pose of x_j moves on by dt per unit of each earlier speed (each earlier speed the robot
    # reaches, with a lag), along the piecewise straight route: the along error falls by as much, the
    # heading error by the taught heading's slope
    M = dt * np.tril(np.ones((K, K)))
    if p.lag is not None:
        M = M @ p.lag.Lv
    dE[:, 0, :K] -= M
    dE[:, 2, :K] -= q.ref.heading_slope[:, None] * M
    J = np.zeros((len(r), 2 * K))
    J[:3 * K] = (dE * p.sqrt_q[None, :, None]).reshape(3 * K, 2 * K)
    eye, diff = np.eye(K), np.eye(K) - np.eye(K, k=-1)
    J[3 * K:4 * K, K:] = sr * eye
    J[3 * K:4 * K, :K] = -sr * np.diag(kappa)
    J[4 * K:5 * K, :K] = srv * eye
    J[5 * K:6 * K, K:] = sdr * diff
    J[6 * K:7 * K, :K] = sdv * diff
    J[7 * K] = q.terminal_jacobian(Ec, dE)
    return q.ref, X, E, dE, r, J


@dataclass(frozen=True)
class CorridorNLP:
    """One step's constrained problem, fixed for the solve."""
    problem: HorizonProblem   # the schedule's speeds are its desired inputs; its reference follows the plan
    lo_lat: np.ndarray        # (K,) the corridor at the desired poses of the starting plan, m
    hi_lat: np.ndarray
    head_lim: np.ndarray      # (K,) rad
    cap: np.ndarray           # (K, 3) the most alpha * sigma may take of the corridor
    alpha: float
    sig_start: np.ndarray     # (K, 3) route-frame sigmas of the starting plan
    dsig_v: np.ndarray        # (K, K) d sigma_lat / d v around v_start
    v_start: np.ndarray
    v_max: np.ndarray         # (K,) never above the desired speeds (nor the speed cap's)
    w_limit_at: Callable[[float], float]   # |w| bound at a speed (actuator, Ackermann steering)
    sig_floor: np.ndarray | None = None    # (K,) the least lateral sigma at any speed (the localizer's share)
    turn_lead: TurnLead | None = None      # a skid-steer's turn commands kept within its drive's acceleration

    def w_limits(self, v: np.ndarray) -> np.ndarray:
        v_min = self.problem.s.v_min_mps
        return np.array([self.w_limit_at(max(vj, v_min)) for vj in v.tolist()])

    def tighten(self, sig: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """alpha * sigma, capped; and whether each lateral tightening still follows sigma."""
        t = self.alpha * sig
        return np.minimum(t, self.cap), t[:, 1] < self.cap[:, 1]

    def evaluate(self, v: np.ndarray, w: np.ndarray, a_out: np.ndarray | None = None) -> Iterate:
        ref, X, E, dE, r, J = constrained_residual(self.problem, v, w, a_out)
        sig = self.sig_start.copy()
        # first order in the speeds, never below what slowing down cannot remove: far below the starting
        # speeds the line would reach zero, and a crawl would look free of uncertainty
        floor = 0.0 if self.sig_floor is None else self.sig_floor
        sig[:, 1] = np.maximum(self.sig_start[:, 1] + self.dsig_v @ (v - self.v_start), floor)
        t, _ = self.tighten(sig)
        viol = (np.maximum(E[:, 1] + t[:, 1] - self.hi_lat, 0) + np.maximum(self.lo_lat - E[:, 1] + t[:, 1], 0)
                + np.maximum(np.abs(E[:, 2]) + t[:, 2] - self.head_lim, 0))
        merit = 0.5 * float(r @ r) + self.problem.s.slack_weight * float(viol.sum())
        return Iterate(v, w, X, E, dE, r, J, sig, merit, float(viol.max()), ref)

    def step(self, it: Iterate, qp: CorridorQP, trust_v: float, trust_w: float) -> np.ndarray | None:
        """The QP's step (2K,) from `it` inside the actuator limits and the trust region, or None: (dv, dw),
        or (dv, dc) in the curvature c = w / v for a curvature-steered robot (`moved`)."""
        s = self.problem.s
        w_lim = self.w_limits(it.v)
        J, dE = it.J, it.dE
        if self.problem.curvature_steered:
            J, dE = _by_curvature(J, it.v, it.w), _by_curvature(dE, it.v, it.w)
            c, c_lim, trust_c = it.w / it.v, w_lim / it.v, trust_w / it.v
            lo_w, hi_w = np.maximum(-c_lim - c, -trust_c), np.minimum(c_lim - c, trust_c)
        else:
            lo_w, hi_w = np.maximum(-w_lim - it.w, -trust_w), np.minimum(w_lim - it.w, trust_w)
        lo_d = np.concatenate([np.maximum(s.v_min_mps - it.v, -trust_v), lo_w])
        hi_d = np.concatenate([np.minimum(self.v_max - it.v, trust_v), hi_w])
        tight, free = self.tighten(it.sig)
        if self.sig_floor is not None:
            free &= it.sig[:, 1] > self.sig_floor
        dx, _ = qp.solve(it.r, J, it.E, dE, tight, self.alpha * self.dsig_v * free[:, None],
                         self.lo_lat, self.hi_lat, self.head_lim, lo_d, np.maximum(hi_d, lo_d), self._lead_rows(it))
        return dx

    def _lead_rows(self, it: Iterate) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """(M, lo, hi) on the turn step: each command's lead over the drive within +-turn_lead.max_radps,
        and never further beyond it than the iterate already is (so that no step is infeasible for it)."""
        tl = self.turn_lead
        if tl is None or self.problem.curvature_steered:
            return None
        g = tl.leads(it.w, self.problem.start.xi0[1])
        return tl.matrix(len(g)), np.minimum(-tl.max_radps - g, 0.0), np.maximum(tl.max_radps - g, 0.0)

    def moved(self, it: Iterate, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(v, w) after the step d from `step`: a curvature-steered robot keeps the step's curvature at
        its new speed, so a plan that slows down does not turn its old turn rate into a tighter curve."""
        K = len(it.v)
        v = np.clip(it.v + d[:K], self.problem.s.v_min_mps, self.v_max)
        if self.problem.curvature_steered:
            return v, v * (it.w / it.v + d[K:])
        return v, it.w + d[K:]


def _by_curvature(D: np.ndarray, v: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Derivatives by (v, w) in the last axis (2K) turned into derivatives by (v, c), w = v c: the
    curvature a curvature-steered robot turns at is linear in c, not in w (w / v at a crawl)."""
    K = len(v)
    out = D.copy()
    out[..., :K] += D[..., K:] * (w / v)
    out[..., K:] *= v
    return out


def solve_corridor(nlp: CorridorNLP, start: Iterate, qp: CorridorQP, trust_v: float = 0.5,
                   trust_w: float = 1.0) -> CorridorResult:
    """SQP from `start` (one evaluation already spent on it), bounded by sqp_iter iterations and
    max_evals residual evaluations, as LB/MM are."""
    s = nlp.problem.s
    cur, iters, evals, status = start, 0, 1, "budget"
    for it in range(s.sqp_iter):
        if evals >= s.max_evals:
            break
        iters = it + 1
        dx = nlp.step(cur, qp, trust_v, trust_w)
        if dx is None:
            status = "qp-failed"
            break
        accepted = None
        for beta in (1.0, 0.5, 0.25):                 # eq. 7.11's beta, by the merit function
            if evals >= s.max_evals:
                break
            cand = nlp.evaluate(*nlp.moved(cur, beta * dx))
            evals += 1
            if cand.merit < cur.merit - 1e-12:
                accepted = cand
                break
        if accepted is None:
            if np.max(np.abs(dx)) < 10 * s.tol:
                status = "converged"
            elif evals < s.max_evals:
                status = "stalled"
            break
        moved = max(np.max(np.abs(accepted.v - cur.v)), np.max(np.abs(accepted.w - cur.w)))
        cur = accepted
        if moved < s.tol:
            status = "converged"
            break
    return CorridorResult(cur, iters, evals, status)

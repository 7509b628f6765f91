"""The min-max problem of MM-LB-NMPC (eq. 6.3-6.6), solved as a sequence of small QPs in epigraph form.

    minimize_w  max_l c_l(w),   c_l = 1/2 |r_l(w)|^2,   l = 1..8 boundary sequences E + s_l * bound

The thesis iterates Gauss-Newton on whichever sequence is worst at the current iterate, with a damped
step (beta, eq. 6.9) and a convergence test (alpha). At the optimum of a min-max problem several
sequences are usually worst together; a step computed for one of them raises another, and that
iteration stalls at the kink well above the optimum. Here every iteration linearizes all
eight sequences and takes the step of

    minimize_{d, t}  t + 1/2 d' H d     s.t.  c_l + g_l' d <= t  (l = 1..8),   lo <= d <= hi

with H the Gauss-Newton Hessian of the worst sequence (the eight share every residual but their
offsets), then the thesis's damped step on the true worst-case cost. The QP has K + 1 variables; its
sparsity pattern is fixed, so one OSQP workspace is updated in place and warm-started.
"""
from __future__ import annotations

import numpy as np

from services.controller.gauss_newton import GNResult
from services.controller.horizon import HorizonProblem
from services.controller.osqp_workspace import FixedPatternQP

SIGNS = np.array([[sx, sy, sh] for sx in (1, -1) for sy in (1, -1) for sh in (1, -1)], dtype=float)  # eq. 6.5


class MinMaxQP:
    def __init__(self, K: int, n_seq: int = len(SIGNS)):
        self.K, self.m = K, n_seq
        n = K + 1
        p_mask = np.zeros((n, n), dtype=bool)
        p_mask[:K, :K] = True
        a_mask = np.zeros((n_seq + K, n), dtype=bool)
        a_mask[:n_seq] = True
        a_mask[n_seq + np.arange(K), np.arange(K)] = True
        self._qp = FixedPatternQP(p_mask, a_mask, eps_abs=1e-7, eps_rel=1e-7, max_iter=4000)
        self._A = np.zeros((n_seq + K, n))
        self._A[:n_seq, K] = -1.0
        self._A[n_seq:, :K] = np.eye(K)
        self._P = np.zeros((n, n))
        self._q = np.zeros(n)
        self._q[K] = 1.0

    def solve(self, c: np.ndarray, G: np.ndarray, H: np.ndarray, lo: np.ndarray, hi: np.ndarray):
        """Step d (K,) and the model's worst-case value t, or (None, None)."""
        K, m = self.K, self.m
        self._P[:K, :K] = H
        self._A[:m, :K] = G
        x = self._qp.solve(self._P, self._q, self._A, np.concatenate([np.full(m, -np.inf), lo]),
                           np.concatenate([-c, hi]))
        if x is None:
            return None, None
        return x[:K], float(x[K])


def boundary_costs(problem: HorizonProblem, bound: np.ndarray, w: np.ndarray, with_grad: bool):
    """Costs (8,) of the boundary sequences E + s_l * bound at w (eq. 6.5-6.6); with_grad also their
    gradients (8, K) and the Gauss-Newton Hessian of the worst. The eight share every residual but the
    errors' offsets, so one rollout of the mean serves them all."""
    K = problem.K
    L = problem.s.lookahead_m
    E, dE = problem.tracking(w, with_jac=with_grad)
    r_in = problem.input_residuals(w)
    El = E[None] + SIGNS[:, None, :] * bound[None]                   # (8, K, 3): all sequences at once
    Rq = (El * problem.sqrt_q).reshape(len(SIGNS), 3 * K)
    terms = problem.sqrt_qt * (El[:, -1, 1] + L * np.sin(El[:, -1, 2]))
    costs = 0.5 * (np.einsum("li,li->l", Rq, Rq) + float(r_in @ r_in) + terms ** 2)
    if not with_grad:
        return costs
    Jq = (dE * problem.sqrt_q[None, :, None]).reshape(3 * K, K)
    J_in = problem.input_jacobian()
    jt = problem.sqrt_qt * (dE[-1, 1][None] + L * np.cos(El[:, -1, 2])[:, None] * dE[-1, 2][None])   # (8, K)
    G = Rq @ Jq + (J_in.T @ r_in)[None] + jt * terms[:, None]
    worst = int(np.argmax(costs))
    H = Jq.T @ Jq + J_in.T @ J_in + np.outer(jt[worst], jt[worst])
    return costs, G, H


def solve_minmax(problem, bound: np.ndarray, w0: np.ndarray, lower: np.ndarray, upper: np.ndarray, qp: MinMaxQP,
                 max_iter: int, tol: float, max_evals: int) -> GNResult:
    """Epigraph SQP from w0 with the thesis's damped step (beta = 1, 1/2, 1/4) on the true worst case."""
    w = np.clip(np.asarray(w0, dtype=float), lower, upper)
    costs, G, H = boundary_costs(problem, bound, w, True)
    evals, it, status = 1, 0, "budget"
    best = float(costs.max())
    trust = 1.0
    while it < max_iter and evals < max_evals:
        it += 1
        lo = np.maximum(lower - w, -trust)
        hi = np.minimum(upper - w, trust)
        d, t = qp.solve(costs, G, H + 1e-8 * np.eye(len(w)), lo, hi)
        if d is None:
            status = "qp-failed"
            break
        if np.max(np.abs(d)) < tol:
            status = "converged"
            break
        accepted = False
        for beta in (1.0, 0.5, 0.25):
            if evals >= max_evals:
                break
            cand = w + beta * d
            # with the gradients at once: most candidates are accepted, and the next QP needs them there
            c_new, G_new, H_new = boundary_costs(problem, bound, cand, True)
            evals += 1
            if c_new.max() < best - 1e-12:
                w, best, accepted = cand, float(c_new.max()), True
                costs, G, H = c_new, G_new, H_new
                break
        if not accepted:
            status = "converged" if np.max(np.abs(d)) < 10 * tol else "stalled"
            trust *= 0.25
            if evals >= max_evals or trust < tol:
                break
            continue
    return GNResult(w, best, it, status == "converged", evals, status)

"""Gauss-Newton for nonlinear least squares with box bounds on the decision variables (eq. 5.5-5.10).

    minimize 1/2 ||r(u)||^2   subject to  lower <= u <= upper

Each iteration linearizes r around the current u (r + J du, eq. 5.5-5.8) and solves the linear
least-squares step (eq. 5.9), damped in the Levenberg-Marquardt way: while a full step decreases the
cost the damping shrinks and the iteration is plain Gauss-Newton; when it does not (a learned model
far from its data can make the problem strongly nonlinear) the step shortens and turns towards the
gradient, instead of oscillating. The step respects the bounds through a bounded linear least squares
(scipy's BVLS) only when the plain step would leave them.

For a real-time loop the work is bounded by a count of residual evaluations (deterministic, unlike a
wall-clock deadline, so lockstep runs stay reproducible); the best point found is returned either way
and the result says whether it converged. Non-finite residuals end the solve at the best finite point.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy.linalg import LinAlgError, cho_factor, cho_solve
from scipy.optimize import lsq_linear


@dataclass
class GNResult:
    u: np.ndarray
    cost: float          # 1/2 ||r||^2 at u
    iterations: int
    converged: bool      # the last step was below tol (else: out of budget, or stalled, see status)
    evaluations: int = 0
    status: str = "converged"   # converged | budget | stalled | non-finite


def _step(J: np.ndarray, r: np.ndarray, mu: float, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    H = J.T @ J
    if mu > 0.0:
        H[np.diag_indices_from(H)] += mu
    g = J.T @ r
    try:
        du = -cho_solve(cho_factor(H, check_finite=False), g, check_finite=False)
    except LinAlgError:
        du = -np.linalg.lstsq(J, r, rcond=None)[0]
    if np.all(du >= lo - 1e-12) and np.all(du <= hi + 1e-12):
        return du
    A = np.vstack([J, np.sqrt(mu) * np.eye(len(du))]) if mu > 0.0 else J
    b = np.concatenate([-r, np.zeros(len(du))]) if mu > 0.0 else -r
    return lsq_linear(A, b, bounds=(lo, hi), method="bvls").x


def _finite(r: np.ndarray, J: np.ndarray) -> bool:
    return bool(np.all(np.isfinite(r)) and np.all(np.isfinite(J)))


def gauss_newton(residual: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]], u0: np.ndarray,
                 lower: np.ndarray, upper: np.ndarray, *, max_iter: int = 20, tol: float = 1e-5,
                 mu0: float = 0.0, max_evals: int | None = None) -> GNResult:
    """`residual(u)` returns (r, J = dr/du). Starts undamped (mu0 = 0: pure Gauss-Newton, which for a
    linear model solves the problem exactly in one step); the damping only appears when needed.
    `max_evals` caps the residual evaluations (default 2 * max_iter + 1)."""
    budget = 2 * max_iter + 1 if max_evals is None else max_evals
    u = np.clip(np.asarray(u0, dtype=float), lower, upper)
    r, J = residual(u)
    evals = 1
    if not _finite(r, J):
        return GNResult(u, float("inf"), 0, False, evals, "non-finite")
    cost = 0.5 * float(r @ r)
    mu = mu0
    scale = max(float(np.max(np.sum(J * J, axis=0))), 1e-12) if J.size else 1.0
    for it in range(1, max_iter + 1):
        while True:
            if evals >= budget:
                return GNResult(u, cost, it, False, evals, "budget")
            du = _step(J, r, mu, lower - u, upper - u)
            trial = np.clip(u + du, lower, upper)
            moved = float(np.max(np.abs(trial - u))) if len(u) else 0.0
            if moved < tol:
                # converged (or damped to a standstill): the remaining step is below what matters
                return GNResult(u, cost, it, mu == 0.0 or mu <= 1e-3 * scale, evals,
                                "converged" if mu <= 1e-3 * scale else "stalled")
            r_t, J_t = residual(trial)
            evals += 1
            new_cost = 0.5 * float(r_t @ r_t) if _finite(r_t, J_t) else float("inf")
            if new_cost <= cost:
                mu = mu / 3.0 if mu > 1e-9 * scale else 0.0
                break
            # escalate fast: the budget allows only a few tries, and a damping that grows slowly from
            # 1e-4 * scale leaves the step nearly as long as the rejected one, so a solve that starts
            # in a badly linearized region would return its warm start unchanged step after step
            mu = max(10.0 * mu, 1e-3 * scale)
            if mu > 1e6 * scale:  # no step lowers the cost: this is a (local) minimum
                return GNResult(u, cost, it, True, evals, "converged")
        u, r, J, cost = trial, r_t, J_t, new_cost
    return GNResult(u, cost, max_iter, False, evals, "budget")

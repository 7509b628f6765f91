"""Gauss-Newton for nonlinear least squares with box bounds on the decision variables (eq. 5.5-5.10).

    minimize 1/2 ||r(u)||^2   subject to  lower <= u <= upper

Each iteration linearizes r around the current u (r + J du, eq. 5.5-5.8) and solves the linear
least-squares step (eq. 5.9), damped in the Levenberg-Marquardt way: while a full step decreases the
cost the damping shrinks and the iteration is plain Gauss-Newton; when it does not (a learned model
far from its data can make the problem strongly nonlinear) the step shortens and turns towards the
gradient, instead of oscillating. The step respects the bounds through a bounded linear least squares
(scipy's BVLS) only when the plain step would leave them.
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
    converged: bool


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


def gauss_newton(residual: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]], u0: np.ndarray,
                 lower: np.ndarray, upper: np.ndarray, *, max_iter: int = 20, tol: float = 1e-5,
                 mu0: float = 0.0) -> GNResult:
    """`residual(u)` returns (r, J = dr/du). Starts undamped (mu0 = 0: pure Gauss-Newton, which for a
    linear model solves the problem exactly in one step); the damping only appears when needed."""
    u = np.clip(np.asarray(u0, dtype=float), lower, upper)
    r, J = residual(u)
    cost = 0.5 * float(r @ r)
    mu = mu0
    scale = max(float(np.max(np.sum(J * J, axis=0))), 1e-12) if J.size else 1.0
    for it in range(1, max_iter + 1):
        while True:
            du = _step(J, r, mu, lower - u, upper - u)
            trial = np.clip(u + du, lower, upper)
            moved = float(np.max(np.abs(trial - u))) if len(u) else 0.0
            if moved < tol:
                # converged: the remaining step is below the resolution that matters; stop here
                return GNResult(u, cost, it, True)
            r_t, J_t = residual(trial)
            new_cost = 0.5 * float(r_t @ r_t)
            if new_cost <= cost:
                mu = mu / 3.0 if mu > 1e-9 * scale else 0.0
                break
            mu = max(4.0 * mu, 1e-4 * scale)
            if mu > 1e6 * scale:  # no step lowers the cost: this is a (local) minimum
                return GNResult(u, cost, it, True)
        u, r, J, cost = trial, r_t, J_t, new_cost
    return GNResult(u, cost, max_iter, False)

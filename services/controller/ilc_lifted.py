"""The ILC update from the lifted model of the trial just driven (thesis eq. 3.6-3.13), solved for the
feedforward change that best cancels its errors: norm-optimal ILC (Amann, Owens and Rogers 1996; the
"optimal (quadratic)" group of Bristow et al. 2006 that the thesis names in 3.1).

The thesis's P-type law (eq. 3.14-3.15) stabilizes the trial-domain iteration e+ = (gamma_u - B Gamma_e) e
(eq. 3.13) only when its lookahead matches how late the errors answer a feedforward change. Fixed at a
few vertices, it does not on a robot whose drive lags 0.2-0.5 s, behind a 0.1-0.2 s old estimate, at
1-2 m/s: there the feedforward grows trial after trial while the error pattern moves along the route.
Here B is built from a model of the closed loop the feedforward acts on, per vertex interval
(Delta t_i = d_i / v_i at the speed the trial passed there):

    e_L' = p2,   p2' = v delta,   delta' = (yhat / v + w_ff - delta) / tau_w,   z' = (2 / D)(y - z)

with p2 = v sin e_H (eq. 3.4), delta the drive's achieved turn rate less the route's, tau_w the identified
lag of the turn-rate drive (actuator.py), y = -gamma1 e_L - gamma2 p2 the feedback of eq. 3.5 and
yhat = 2 z - y its value D seconds late (first-order Pade: the estimate's age). Discretized exactly over
each interval (zero-order hold on w_ff,i), stacked into the lifted G (eq. 3.8) for e_L and e_H = p2 / v
at every vertex. The change minimizes

    sum_i q_L (e_L,i + G_L dw)_i^2 + q_H (e_H,i + G_H dw)_i^2 + rho |dw|^2 + rho_d |D1 (w_ff + dw)|^2

(D1: first differences along the route) and only `step` of it is taken: a trial's noise is not learned
as if it would repeat. With an exact model the repeating error falls by about (1 - step) per trial.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import expm

from services.controller.fl import FLGains

MIN_TAU_S = 0.02          # a drive without a lag is modelled as this fast one (the state stays proper)
MIN_SPEED_MPS = 0.05


@dataclass(frozen=True)
class ILCPlant:
    """What the lifted model needs to know of the loop the feedforward acts on."""
    fl: FLGains
    tau_w_s: float = 0.0        # the turn-rate drive's first-order lag (identified; dead time included)
    delay_s: float = 0.0        # the estimate's age when the feedback uses it


def _continuous(v: float, plant: ILCPlant) -> tuple[np.ndarray, np.ndarray]:
    """(A, B) of the state (e_L, p2, delta, z) at speed v, input w_ff."""
    g1, g2 = plant.fl.gamma1, plant.fl.gamma2
    tau = max(plant.tau_w_s, MIN_TAU_S)
    y = np.array([-g1, -g2, 0.0, 0.0])                 # y = -gamma1 e_L - gamma2 p2
    if plant.delay_s > 0:
        a = 2.0 / plant.delay_s
        yhat = -y + np.array([0.0, 0.0, 0.0, 2.0])     # 2 z - y
        z_row = a * (y - np.array([0.0, 0.0, 0.0, 1.0]))
    else:
        yhat, z_row = y, np.zeros(4)
    A = np.zeros((4, 4))
    A[0, 1] = 1.0
    A[1, 2] = v
    A[2] = yhat / (v * tau)
    A[2, 2] -= 1.0 / tau
    A[3] = z_row
    B = np.array([0.0, 0.0, 1.0 / tau, 0.0])
    return A, B


def _discrete(v: float, dt: float, plant: ILCPlant) -> tuple[np.ndarray, np.ndarray]:
    """Exact zero-order-hold discretization over dt (Van Loan: one exponential of the augmented matrix)."""
    A, B = _continuous(v, plant)
    M = np.zeros((5, 5))
    M[:4, :4], M[:4, 4] = A, B
    E = expm(M * dt)
    return E[:4, :4], E[:4, 4]


def lifted_model(distances_m: np.ndarray, speeds_mps: np.ndarray, plant: ILCPlant) -> tuple[np.ndarray, np.ndarray]:
    """(G_L, G_H), each (N, N): the change of e_L and e_H at vertex k per unit w_ff held from vertex i to
    i + 1 (zero for k <= i). `distances_m[i]`: from vertex i to i + 1 (N - 1 of them); `speeds_mps[i]`:
    the speed the robot passed vertex i at."""
    n = len(speeds_mps)
    v = np.maximum(np.asarray(speeds_mps, dtype=float), MIN_SPEED_MPS)
    GL, GH = np.zeros((n, n)), np.zeros((n, n))
    M = np.zeros((4, n))                       # the state's sensitivity to each w_ff,i
    for i in range(n - 1):
        Phi, Gam = _discrete(v[i], float(distances_m[i]) / v[i], plant)
        M = Phi @ M
        M[:, i] += Gam
        GL[i + 1] = M[0]
        GH[i + 1] = M[1] / v[i + 1]
    return GL, GH


@dataclass(frozen=True, kw_only=True)
class LiftedWeights:
    q_lat: float = 1.0          # 1/m^2
    q_head: float = 1.0         # 1/rad^2
    rho: float = 0.02           # on dw, relative to the mean diagonal of G^T Q G
    rho_diff: float = 0.05      # on the first differences of the feedforward, relative the same way
    step: float = 0.6           # share of the optimal change taken per trial


def norm_optimal_change(w_ff: np.ndarray, e_lat: np.ndarray, e_head: np.ndarray, seen: np.ndarray,
                        GL: np.ndarray, GH: np.ndarray, wt: LiftedWeights) -> np.ndarray:
    """The feedforward change (N,) for the next trial from this trial's mean errors per vertex; vertices
    not seen carry no error term and are not changed."""
    n = len(w_ff)
    q = seen.astype(float)
    H = GL.T @ (q[:, None] * wt.q_lat * GL) + GH.T @ (q[:, None] * wt.q_head * GH)
    scale = max(float(np.mean(np.diag(H))), 1e-12)
    D = np.diff(np.eye(n), axis=0)
    H = H + wt.rho * scale * np.eye(n) + wt.rho_diff * scale * (D.T @ D)
    rhs = -(GL.T @ (q * wt.q_lat * e_lat) + GH.T @ (q * wt.q_head * e_head)) - wt.rho_diff * scale * (D.T @ (D @ w_ff))
    free = _reachable(seen)
    dw = np.zeros(n)
    if np.any(free):
        idx = np.flatnonzero(free)
        dw[idx] = np.linalg.solve(H[np.ix_(idx, idx)], rhs[idx])
    return wt.step * dw


def _reachable(seen: np.ndarray) -> np.ndarray:
    """The vertices whose feedforward may change: up to the last one seen (a change beyond it has no
    error to answer to)."""
    out = np.zeros(len(seen), dtype=bool)
    if np.any(seen):
        last = int(np.flatnonzero(seen)[-1])
        out[:last] = True
    return out


def mean_speeds(speed_sum: np.ndarray, count: np.ndarray, fallback: float) -> np.ndarray:
    """Per vertex the mean commanded speed of the trial, filled in from the neighbours where unseen."""
    v = np.full(len(count), np.nan)
    ok = count > 0
    v[ok] = speed_sum[ok] / count[ok]
    if not np.any(ok):
        return np.full(len(count), fallback)
    idx = np.arange(len(v))
    return np.interp(idx, idx[ok], v[ok])

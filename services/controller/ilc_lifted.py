"""The ILC update from the lifted model of the trial just driven (thesis eq. 3.6-3.13), solved for the
feedforward change that best cancels its errors: norm-optimal ILC (Amann, Owens and Rogers 1996; the
"optimal (quadratic)" group of Bristow et al. 2006 that the thesis names in 3.1).

The thesis's P-type law (eq. 3.14-3.15) stabilizes the trial-domain iteration e+ = (gamma_u - B Gamma_e) e
(eq. 3.13) only when its lookahead matches how late the errors answer a feedforward change. Fixed at a
few vertices, it does not on a robot whose drive lags 0.2-0.5 s, behind a 0.1-0.2 s old estimate, at
1-2 m/s: there the feedforward grows trial after trial while the error pattern moves along the route.
Here B is built from a model of the closed loop the feedforward acts on, per vertex interval
(Delta t_i = d_i / v_i at the speed the trial passed there):

    e_L' = p2,   p2' = v delta,   delta' = (k (yhat / v + w_ff) - delta) / tau_w,   z' = (2 / D)(y - z)

with p2 = v sin e_H (eq. 3.4), delta the robot's turn rate less the route's, k the share of the drive's
turn rate the robot turns at (actuator.py turn_gain; FL asks for the route's rate over it), tau_w the identified
lag of the turn-rate drive (actuator.py), y = -gamma1 e_L - gamma2 p2 the feedback of eq. 3.5 and
yhat = 2 z - y its value D seconds late (first-order Pade: the estimate's age). With FL's lead
(fl.py, `ILCPlant.lead_s` = T) y is taken at the led errors, linearized: the estimate's part
-gamma1 e_L - (gamma1 T + gamma2) p2 is late by D, the drive's -(gamma1 T^2 / 2 + gamma2 T) v delta is
not. Discretized exactly over each interval (zero-order hold on w_ff,i), stacked into the lifted G
(eq. 3.8) for e_L and e_H = p2 / v at every vertex. The change minimizes

    sum_i q_L (e_L,i + G_L dw)_i^2 + q_H (e_H,i + G_H dw)_i^2 + rho |dw|^2 + rho_d |D1 (w_ff + dw)|^2

(D1: first differences along the route) and only `step` of it is taken: a trial's noise is not learned
as if it would repeat. With an exact model the repeating error falls by about (1 - step) per trial.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import expm, solveh_banded

from services.controller.fl import FLGains

MIN_TAU_S = 0.02          # a drive without a lag is modelled as this fast one (the state stays proper)
MIN_SPEED_MPS = 0.05


@dataclass(frozen=True)
class ILCPlant:
    """What the lifted model needs to know of the loop the feedforward acts on."""
    fl: FLGains
    tau_w_s: float = 0.0        # the turn-rate drive's first-order lag (identified; dead time included)
    delay_s: float = 0.0        # the estimate's age when the feedback uses it
    turn_gain: float = 1.0      # the robot's turn rate over the drive's (actuator.py): on feedback and feedforward
    lead_s: float = 0.0         # the feedback's lead (fl.py; the estimate's age and the drive's lag with FLGains.lead)


def _continuous(v: float, plant: ILCPlant) -> tuple[np.ndarray, np.ndarray]:
    """(A, B) of the state (e_L, p2, delta, z) at speed v, input w_ff."""
    g1, g2, T = plant.fl.gamma1, plant.fl.gamma2, plant.lead_s
    tau = max(plant.tau_w_s, MIN_TAU_S)
    # y = -gamma1 e_L* - gamma2 p2* at the led errors (fl.py, linearized): e_L* = e_L + T p2 + T^2 v delta / 2,
    # p2* = p2 + T v delta; the estimate's (e_L, p2) are D old, the drive's turn delta is the current one
    y = np.array([-g1, -(g1 * T + g2), 0.0, 0.0])
    y_now = np.array([0.0, 0.0, -(0.5 * g1 * T * T + g2 * T) * v, 0.0])
    if plant.delay_s > 0:
        a = 2.0 / plant.delay_s
        yhat = -y + np.array([0.0, 0.0, 0.0, 2.0]) + y_now    # 2 z - y
        z_row = a * (y - np.array([0.0, 0.0, 0.0, 1.0]))
    else:
        yhat, z_row = y + y_now, np.zeros(4)
    A = np.zeros((4, 4))
    A[0, 1] = 1.0
    A[1, 2] = v
    k = plant.turn_gain
    A[2] = k * yhat / (v * tau)
    A[2, 2] -= 1.0 / tau
    A[3] = z_row
    B = np.array([0.0, 0.0, k / tau, 0.0])
    return A, B


def _discrete(v: float, dt: float, plant: ILCPlant) -> tuple[np.ndarray, np.ndarray]:
    """Exact zero-order-hold discretization over dt (Van Loan: one exponential of the augmented matrix)."""
    A, B = _continuous(v, plant)
    M = np.zeros((5, 5))
    M[:4, :4], M[:4, 4] = A, B
    E = expm(M * dt)
    return E[:4, :4], E[:4, 4]


@dataclass(frozen=True)
class LiftedModel:
    """The lifted G_L and G_H in band form: lat[r, d] = G_L[r, r - 1 - d], the change of e_L at vertex r
    per unit w_ff held over interval r - 1 - d (d = 0..B - 1); the same for heading. The closed loop
    forgets a feedforward pulse within a few seconds, so G is a band of B intervals (the pulse's state
    below RESPONSE_TOL of its peak beyond it), whatever the route's length."""
    lat: np.ndarray           # (N, B)
    head: np.ndarray          # (N, B)

    @property
    def n(self) -> int:
        return self.lat.shape[0]

    @property
    def bandwidth(self) -> int:
        return self.lat.shape[1]


RESPONSE_TOL = 1e-6


def lifted_model(distances_m: np.ndarray, speeds_mps: np.ndarray, plant: ILCPlant) -> LiftedModel:
    """G_L and G_H of the route: `distances_m[i]` from vertex i to i + 1 (N - 1 of them), `speeds_mps[i]`
    the speed the robot passed vertex i at. Zero-order hold of w_ff,i over interval i (eq. 3.6-3.8)."""
    n = len(speeds_mps)
    v = np.maximum(np.asarray(speeds_mps, dtype=float), MIN_SPEED_MPS)
    rows: list[tuple[np.ndarray, np.ndarray]] = [(np.zeros(0), np.zeros(0))]   # vertex 0: nothing acts yet
    M = np.zeros((4, 0))            # the state's sensitivity to w_ff of the active intervals, newest last
    peak = np.zeros(0)
    for i in range(n - 1):
        Phi, Gam = _discrete(v[i], float(distances_m[i]) / v[i], plant)
        M = np.column_stack([Phi @ M, Gam])
        size = np.max(np.abs(M), axis=0)
        peak = np.maximum(np.append(peak, 0.0), size)
        rows.append((M[0, ::-1].copy(), M[1, ::-1] / v[i + 1]))        # d = 0 first
        keep = int(np.argmax(size >= RESPONSE_TOL * peak)) if np.any(size >= RESPONSE_TOL * peak) else len(size)
        M, peak = M[:, keep:], peak[keep:]                              # the forgotten oldest pulses go
    B = max(1, max(len(r[0]) for r in rows))
    lat, head = np.zeros((n, B)), np.zeros((n, B))
    for r, (gl, gh) in enumerate(rows):
        lat[r, :len(gl)], head[r, :len(gh)] = gl, gh
    return LiftedModel(lat, head)


@dataclass(frozen=True, kw_only=True)
class LiftedWeights:
    q_lat: float = 1.0          # 1/m^2
    q_head: float = 1.0         # 1/rad^2
    rho: float = 0.02           # on dw, relative to the mean diagonal of G^T Q G
    rho_diff: float = 0.05      # on the first differences of the feedforward, relative the same way
    step: float = 0.6           # share of the optimal change taken per trial


def _gram(Gb: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(B, N) upper diagonals of G^T diag(q) G for G in band form: out[off, j] = (G^T q G)[j, j + off]."""
    n, B = Gb.shape
    out = np.zeros((B, n))
    for off in range(B):
        for d2 in range(B - off):
            r0 = off + 1 + d2                      # G[r, j] = Gb[r, off + d2], G[r, j + off] = Gb[r, d2]
            if r0 >= n:
                break
            out[off, :n - r0] += q[r0:] * Gb[r0:, off + d2] * Gb[r0:, d2]
    return out


def _transpose_times(Gb: np.ndarray, y: np.ndarray) -> np.ndarray:
    """G^T y for G in band form."""
    n, B = Gb.shape
    out = np.zeros(n)
    for d in range(min(B, n - 1)):
        out[:n - 1 - d] += Gb[1 + d:, d] * y[1 + d:]
    return out


def norm_optimal_change(w_ff: np.ndarray, e_lat: np.ndarray, e_head: np.ndarray, seen: np.ndarray,
                        model: LiftedModel, wt: LiftedWeights) -> np.ndarray:
    """The feedforward change (N,) for the next trial from this trial's mean errors per vertex; vertices
    not seen carry no error term and are not changed. A banded solve: linear in the route's length."""
    n = len(w_ff)
    q = seen.astype(float)
    H = wt.q_lat * _gram(model.lat, q) + wt.q_head * _gram(model.head, q)
    if H.shape[0] < 2:
        H = np.vstack([H, np.zeros((1, n))])      # room for the first differences' off-diagonal
    rhs = -(wt.q_lat * _transpose_times(model.lat, q * e_lat) + wt.q_head * _transpose_times(model.head, q * e_head))
    free = int(np.sum(_reachable(seen)))
    if free == 0:
        return np.zeros(n)
    scale = max(float(np.mean(H[0, :free])), 1e-12)
    dtd_diag = np.full(n, 2.0)
    dtd_diag[[0, -1]] = 1.0                       # D^T D of the first differences: tridiagonal
    H[0] += wt.rho * scale + wt.rho_diff * scale * dtd_diag
    H[1, :n - 1] -= wt.rho_diff * scale
    dw_prev = np.diff(w_ff)
    rhs -= wt.rho_diff * scale * (np.concatenate([[0.0], dw_prev]) - np.concatenate([dw_prev, [0.0]]))
    u = H.shape[0] - 1
    ab = np.zeros((u + 1, free))                  # solveh_banded's upper form: ab[u - off, j + off]
    for off in range(min(u + 1, free)):           # a trial that saw fewer vertices than the band is wide
        ab[u - off, off:] = H[off, :free - off]
    dw = np.zeros(n)
    dw[:free] = solveh_banded(ab, rhs[:free])
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

"""The QP of one SQP iteration of C-/RC-LB-NMPC, kept in one OSQP workspace across iterations and steps.

Variables z = (dv_0..dv_{K-1}, dw_0..dw_{K-1}, s_lat (K), s_head (K)):

    min  1/2 |r + J d|^2 + rho (1's + 1/2 |s|^2)
    s.t. lat_j  + tight_j + (J_lat + dtight)_j d - s_lat,j  <= hi_j        (corridor, eq. 7.4)
         lat_j  - tight_j + (J_lat - dtight)_j d + s_lat,j  >= lo_j
         head_j + tight_j + J_head,j d - s_head,j <= head_lim_j
         head_j - tight_j + J_head,j d + s_head,j >= -head_lim_j
         lo_d <= d <= hi_d                                             (actuator limits, trust region)
         lo_lead <= M dw <= hi_lead                                    (the turn drive's acceleration: turn_accel.py)
         s >= 0

The sparsity pattern depends only on K: one OSQP workspace (osqp_workspace.py) is updated in place.
"""
from __future__ import annotations

import numpy as np

from services.controller.osqp_workspace import FixedPatternQP


class CorridorQP:
    def __init__(self, K: int, slack_weight: float):
        self.K = K
        self.rho = slack_weight
        n, m = 4 * K, 9 * K
        p_mask = np.zeros((n, n), dtype=bool)
        p_mask[:2 * K, :2 * K] = True
        p_mask[np.arange(2 * K, n), np.arange(2 * K, n)] = True
        a_mask = np.zeros((m, n), dtype=bool)
        a_mask[:4 * K, :2 * K] = True
        i = np.arange(K)
        for blk, off in ((0, 2 * K), (1, 2 * K), (2, 3 * K), (3, 3 * K)):
            a_mask[blk * K + i, off + i] = True
        a_mask[4 * K + np.arange(n), np.arange(n)] = True
        a_mask[8 * K:, K:2 * K] = np.tri(K, K, dtype=bool)
        self._qp = FixedPatternQP(p_mask, a_mask, eps_abs=1e-5, eps_rel=1e-5, max_iter=2000)
        self._P = np.zeros((n, n))
        self._P[2 * K:, 2 * K:] = np.eye(2 * K) * slack_weight
        self._A = np.zeros((m, n))
        self._A[4 * K:8 * K, :] = np.eye(n)
        for blk, off, sign in ((0, 2 * K, -1), (1, 2 * K, 1), (2, 3 * K, -1), (3, 3 * K, 1)):
            self._A[blk * K + i, off + i] = sign

    def solve(self, r, J, E, dE, tight, dtight_v, lo_lat, hi_lat, head_lim, lo_d, hi_d, lead=None):
        """The step d (2K) and the largest slack used, or (None, 0) when OSQP gives nothing usable. `lead`:
        (M, lo, hi) of the turn commands' lead over the drive (None: unbounded)."""
        K = self.K
        H = J.T @ J
        H[np.diag_indices(2 * K)] += 1e-6
        self._P[:2 * K, :2 * K] = H
        q = np.concatenate([J.T @ r, np.full(2 * K, self.rho)])
        Jlat, Jhead = dE[:, 1, :], dE[:, 2, :]
        A = self._A
        A[:K, :2 * K] = Jlat
        A[:K, :K] += dtight_v
        A[K:2 * K, :2 * K] = Jlat
        A[K:2 * K, :K] -= dtight_v
        A[2 * K:3 * K, :2 * K] = Jhead
        A[3 * K:4 * K, :2 * K] = Jhead
        inf = np.full(K, np.inf)
        if lead is None:
            A[8 * K:, K:2 * K] = 0.0
            lo_lead, hi_lead = -inf, inf
        else:
            A[8 * K:, K:2 * K], lo_lead, hi_lead = lead
        lo = np.concatenate([-inf, lo_lat - E[:, 1] + tight[:, 1], -inf, -head_lim - E[:, 2] + tight[:, 2],
                             lo_d, np.zeros(2 * K), lo_lead])
        hi = np.concatenate([hi_lat - E[:, 1] - tight[:, 1], inf, head_lim - E[:, 2] - tight[:, 2], inf,
                             hi_d, np.full(2 * K, np.inf), hi_lead])
        x = self._qp.solve(self._P, q, A, lo, hi)
        if x is None:
            return None, 0.0
        return x[:2 * K], float(max(np.max(x[2 * K:], initial=0.0), 0.0))

"""One OSQP workspace for a QP whose sparsity pattern never changes (the SQP steps of MM- and
C-/RC-LB-NMPC): the dense matrices are read at fixed CSC patterns and passed with `update`, so there is
no set-up and no scipy.sparse assembly per solve (at this size they cost more than the solve), and OSQP
warm-starts from the previous solution and multipliers."""
from __future__ import annotations

import numpy as np
import osqp
import scipy.sparse as sp

# OSQP status values whose point is a usable direction (solved, solved inaccurate, out of iterations);
# the caller's merit test decides whether it helps
USABLE = {int(osqp.SolverStatus[k].value) for k in ("OSQP_SOLVED", "OSQP_SOLVED_INACCURATE", "OSQP_MAX_ITER_REACHED")}


def csc_pattern(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(row, col) of each stored entry of a dense boolean mask in CSC order, and the CSC column pointer."""
    cols, rows = np.nonzero(mask.T)           # column-major: sorted by column, then row
    indptr = np.concatenate([[0], np.cumsum(np.bincount(cols, minlength=mask.shape[1]))])
    return rows, cols, indptr


class FixedPatternQP:
    """min 1/2 z'Pz + q'z  s.t.  l <= Az <= u, with P (upper triangle) and A inside fixed masks."""

    def __init__(self, p_mask: np.ndarray, a_mask: np.ndarray, **settings):
        self._p, self._a = csc_pattern(np.triu(p_mask)), csc_pattern(a_mask)
        self.n, self.m = p_mask.shape[0], a_mask.shape[0]
        self.settings = dict(verbose=False, polishing=True, **settings)
        self._solver: osqp.OSQP | None = None
        self.setups = 0

    def solve(self, P: np.ndarray, q: np.ndarray, A: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray | None:
        """The minimizer, or None when OSQP gives nothing usable (the next solve then starts afresh: a
        failed workspace warm-starts badly)."""
        prow, pcol, pptr = self._p
        arow, acol, aptr = self._a
        Px, Ax = P[prow, pcol], A[arow, acol]
        if self._solver is None:
            self._solver = osqp.OSQP()
            self._solver.setup(sp.csc_matrix((Px, prow, pptr), shape=(self.n, self.n)), q,
                               sp.csc_matrix((Ax, arow, aptr), shape=(self.m, self.n)), lo, hi, **self.settings)
            self.setups += 1
        else:
            self._solver.update(Px=Px, Ax=Ax, q=q, l=lo, u=hi)
        res = self._solver.solve(raise_error=False)
        x = res.x
        if x is None or res.info.status_val not in USABLE or not np.all(np.isfinite(x)):
            self._solver = None
            return None
        return x

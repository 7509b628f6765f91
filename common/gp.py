"""Gaussian-process disturbance model (thesis 5.2.2-5.2.3): the math, nothing else.

One independent exact GP per output dimension of the disturbance g (eq. 5.21), all sharing the same
inputs a (eq. 5.15), each with a zero prior mean and the squared-exponential kernel with automatic
relevance determination (eq. 5.20)

    k(a_i, a_j) = sigma_f^2 exp(-1/2 (a_i - a_j)^T M^-2 (a_i - a_j)) + sigma_n^2 delta_ij,
    M = diag(lengthscales).

`GaussianProcess` is queried by the controller inside its real-time loop: everything that depends
only on the training data (Cholesky factor L of K, alpha = K^-1 y, scaled and centred inputs) is
computed once at construction, and `predict` / `predict_with_grad` are batched over query points with
no Python loop over data or query points (only over the d <= 3 output dimensions).

`fit_hyperparameters` is the offline step of 5.2.3: per output dimension it maximizes the log marginal
likelihood (Rasmussen & Williams 2006, eq. 2.30, analytic gradient eq. 5.9) with L-BFGS-B over the log
hyperparameters, from several initial values (the first data-driven or given, the others random), and
keeps the best. Above `max_points` rows it fits on a uniformly random subsample of that many rows
(without replacement), which is representative of the whole set in expectation and keeps the O(n^3)
cost bounded; the hyperparameters are then used with whatever data the caller builds its GPs from.

Pure numpy/scipy: no global random state (callers pass a `np.random.Generator`), no I/O.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
from scipy.linalg import lapack, solve_triangular
from scipy.optimize import minimize

__all__ = ["SEHyper", "se_ard", "log_marginal_likelihood", "GaussianProcess", "FitResult", "subsample_rows",
           "fit_hyperparameters", "hyper_bounds", "heuristic_hyper"]

_LOG_2PI = math.log(2.0 * math.pi)
_JITTER_START = 1e-10   # relative to the mean diagonal of K; only used when a Cholesky fails
_JITTER_MAX = 1e-3
_FLOOR = 1e-12          # smallest positive hyperparameter accepted anywhere


# --- hyperparameters --------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class SEHyper:
    """Hyperparameters of one output dimension: SE-ARD kernel of eq. 5.20.

    lengthscales: (p,) diagonal of M; signal_std: sigma_f; noise_std: sigma_n (all > 0).
    """
    lengthscales: np.ndarray
    signal_std: float
    noise_std: float

    def __post_init__(self):
        ell = np.array(self.lengthscales, dtype=float).reshape(-1)
        if ell.size == 0 or not np.all(np.isfinite(ell)) or np.any(ell <= 0):
            raise ValueError("lengthscales must be a non-empty vector of finite values > 0")
        ell.setflags(write=False)
        object.__setattr__(self, "lengthscales", ell)
        for name in ("signal_std", "noise_std"):
            v = float(getattr(self, name))
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be finite and > 0 (got {v})")
            object.__setattr__(self, name, v)

    @property
    def p(self) -> int:
        return int(self.lengthscales.size)

    def to_log(self) -> np.ndarray:
        """[log ell_1..p, log sigma_f, log sigma_n]: the parameters the optimizer works on."""
        return np.concatenate([np.log(self.lengthscales), [math.log(self.signal_std), math.log(self.noise_std)]])

    @classmethod
    def from_log(cls, theta) -> "SEHyper":
        theta = np.asarray(theta, dtype=float).reshape(-1)
        if theta.size < 3:
            raise ValueError("theta needs p >= 1 log lengthscales plus log sigma_f and log sigma_n")
        return cls(np.exp(theta[:-2]), float(np.exp(theta[-2])), float(np.exp(theta[-1])))

    def to_dict(self) -> dict:
        return {"lengthscales": [float(v) for v in self.lengthscales], "signal_std": self.signal_std,
                "noise_std": self.noise_std}

    @classmethod
    def from_dict(cls, d: dict) -> "SEHyper":
        return cls(np.asarray(d["lengthscales"], dtype=float), float(d["signal_std"]), float(d["noise_std"]))

    def __eq__(self, other) -> bool:
        if not isinstance(other, SEHyper):
            return NotImplemented
        return (self.signal_std == other.signal_std and self.noise_std == other.noise_std
                and np.array_equal(self.lengthscales, other.lengthscales))

    __hash__ = None  # mutable-looking contents: not hashable

    def __repr__(self) -> str:
        ell = ", ".join(f"{v:.4g}" for v in self.lengthscales)
        return f"SEHyper(lengthscales=[{ell}], signal_std={self.signal_std:.4g}, noise_std={self.noise_std:.4g})"


# --- kernel -----------------------------------------------------------------------------------
def _sqdist(A: np.ndarray, B: np.ndarray, A2: np.ndarray | None = None, B2: np.ndarray | None = None) -> np.ndarray:
    """Squared Euclidean distances between rows of A (n, p) and B (m, p), clipped at 0."""
    if A2 is None:
        A2 = np.einsum("ij,ij->i", A, A)
    if B2 is None:
        B2 = np.einsum("ij,ij->i", B, B)
    D = A @ B.T
    D *= -2.0
    D += A2[:, None]
    D += B2[None, :]
    np.maximum(D, 0.0, out=D)
    return D


def se_ard(X1, X2, lengthscales, signal_std) -> np.ndarray:
    """(N1, N2) SE-ARD kernel matrix sigma_f^2 exp(-1/2 |M^-1 (x1 - x2)|^2), without the noise term."""
    X1 = np.atleast_2d(np.asarray(X1, dtype=float))
    X2 = np.atleast_2d(np.asarray(X2, dtype=float))
    inv = 1.0 / np.asarray(lengthscales, dtype=float)
    # centring on a common point does not change distances but avoids cancellation far from 0
    c = X1.mean(axis=0) if len(X1) else 0.0
    D = _sqdist((X1 - c) * inv, (X2 - c) * inv)
    D *= -0.5
    np.exp(D, out=D)
    D *= float(signal_std) ** 2
    return D


def _cholesky(K: np.ndarray) -> tuple[np.ndarray, float] | None:
    """Lower Cholesky factor of K (K itself is left as it was), adding diagonal jitter, growing from
    1e-10 to 1e-3 times the mean diagonal, only if the plain factorization fails. Returns
    (L, jitter_added) or None if even the largest jitter does not help."""
    c, info = lapack.dpotrf(K, lower=1, clean=1, overwrite_a=0)
    if info == 0:
        return c, 0.0
    if info < 0 or not np.all(np.isfinite(K)):
        return None
    scale = float(np.mean(np.diag(K))) if len(K) else 1.0
    if not (math.isfinite(scale) and scale > 0):
        scale = 1.0
    jitter = _JITTER_START * scale
    diag = np.diag_indices_from(K)
    base = K[diag].copy()
    while jitter <= _JITTER_MAX * scale:
        K[diag] = base + jitter
        c, info = lapack.dpotrf(K, lower=1, clean=1, overwrite_a=0)
        if info == 0:
            K[diag] = base
            return c, jitter
        jitter *= 10.0
    K[diag] = base
    return None


# --- log marginal likelihood ------------------------------------------------------------------
def _lml(X: np.ndarray, y: np.ndarray, theta: np.ndarray, with_grad: bool):
    """LML and its gradient w.r.t. theta = [log ell, log sf, log sn]; X already centred.

    Returns (-inf, zeros) when K cannot be factorized (never NaN)."""
    n, p = X.shape
    grad_fail = np.zeros(p + 2)
    if not np.all(np.isfinite(theta)):
        return (-math.inf, grad_fail) if with_grad else -math.inf
    if n == 0:
        return (0.0, grad_fail) if with_grad else 0.0
    inv_ell = np.exp(-theta[:p])
    sf2 = math.exp(2.0 * theta[p])
    sn2 = math.exp(2.0 * theta[p + 1])
    A = X * inv_ell
    Kf = _sqdist(A, A)
    np.fill_diagonal(Kf, 0.0)                    # exact zeros despite rounding in |a|^2 + |b|^2 - 2ab
    Kf *= -0.5
    np.exp(Kf, out=Kf)
    Kf *= sf2
    K = Kf.copy()
    K[np.diag_indices(n)] += sn2
    fac = _cholesky(K)
    if fac is None:
        return (-math.inf, grad_fail) if with_grad else -math.inf
    L, _ = fac
    alpha, info = lapack.dpotrs(L, y, lower=1)
    if info != 0 or not np.all(np.isfinite(alpha)):
        return (-math.inf, grad_fail) if with_grad else -math.inf
    logdet_half = float(np.sum(np.log(np.diag(L))))
    lml = -0.5 * float(y @ alpha) - logdet_half - 0.5 * n * _LOG_2PI
    if not math.isfinite(lml):
        return (-math.inf, grad_fail) if with_grad else -math.inf
    if not with_grad:
        return lml
    # W = alpha alpha^T - K^-1 ; dLML/dtheta_i = 1/2 tr(W dK/dtheta_i)   (R&W eq. 5.9)
    Kinv, info = lapack.dpotri(L, lower=1)
    if info != 0:
        return -math.inf, grad_fail
    Kinv = np.tril(Kinv)
    Kinv += np.tril(Kinv, -1).T
    W = np.outer(alpha, alpha)
    W -= Kinv
    Q = W * Kf                                   # elementwise; dK/dlog sf = 2 Kf
    q1 = Q.sum(axis=1)
    QA = Q @ A
    g = np.empty(p + 2)
    # dK/dlog ell_j = Kf * (a_ij - a_kj)^2 ; 1/2 sum Q (a_i - a_k)^2 = sum_i a_i^2 (Q1)_i - a^T Q a
    g[:p] = (A * A).T @ q1 - np.einsum("ij,ij->j", A, QA)
    g[p] = float(q1.sum())
    g[p + 1] = sn2 * float(np.trace(W))           # dK/dlog sn = 2 sn^2 I
    if not np.all(np.isfinite(g)):
        return -math.inf, grad_fail
    return lml, g


def _clean_xy(X, Y) -> tuple[np.ndarray, np.ndarray]:
    X = np.asarray(X, dtype=float)
    Y = np.asarray(Y, dtype=float)
    if X.ndim == 1:
        X = X[:, None]
    if Y.ndim == 1:
        Y = Y[:, None]
    if X.ndim != 2 or Y.ndim != 2 or len(X) != len(Y):
        raise ValueError(f"X must be (N, p) and Y (N, d) with the same N; got {X.shape} and {Y.shape}")
    return X, Y


def log_marginal_likelihood(X, y, hyper: SEHyper, with_grad: bool = False):
    """log p(y | X, hyper) of one output dimension (R&W eq. 2.30).

    With `with_grad`, also the analytic gradient w.r.t. `hyper.to_log()` (R&W eq. 5.9). Returns -inf
    (and a zero gradient) if K cannot be factorized even with jitter; never NaN."""
    X = np.asarray(X, dtype=float)
    if X.ndim == 1:
        X = X[:, None]
    y = np.asarray(y, dtype=float).reshape(-1)
    if len(X) != len(y):
        raise ValueError(f"X has {len(X)} rows but y has {len(y)}")
    if X.shape[1] != hyper.p:
        raise ValueError(f"X has {X.shape[1]} columns but the hyperparameters have {hyper.p} lengthscales")
    Xc = X - X.mean(axis=0) if len(X) else X
    return _lml(Xc, y, hyper.to_log(), with_grad)


# --- regression -------------------------------------------------------------------------------
def _trsolve(L: np.ndarray, B: np.ndarray, transpose: bool) -> np.ndarray:
    """L^-1 B (or L^-T B) for a lower-triangular, Fortran-ordered L; B (N, M)."""
    x, info = lapack.dtrtrs(L, B, lower=1, trans=1 if transpose else 0)
    if info != 0:  # cannot happen for a successful Cholesky factor; keep the generic path as a fallback
        x = solve_triangular(L, B, lower=True, trans="T" if transpose else "N", check_finite=False)
    return x


class _Dim:
    """Everything one output dimension needs at query time, computed once from the data."""
    __slots__ = ("inv_ell", "inv_ell2", "sf2", "B", "B2", "L", "alpha", "alpha_aug", "jitter")

    def __init__(self, Xc: np.ndarray, y: np.ndarray, h: SEHyper):
        self.inv_ell = 1.0 / h.lengthscales
        self.inv_ell2 = self.inv_ell ** 2
        self.sf2 = h.signal_std ** 2
        n = len(Xc)
        self.B = np.ascontiguousarray(Xc * self.inv_ell)
        self.B2 = np.einsum("ij,ij->i", self.B, self.B)
        self.jitter = 0.0
        if n == 0:
            self.L = np.zeros((0, 0), order="F")
            self.alpha = np.zeros(0)
            self.alpha_aug = np.zeros((0, Xc.shape[1] + 1))
            return
        K = _sqdist(self.B, self.B, self.B2, self.B2)
        np.fill_diagonal(K, 0.0)
        K *= -0.5
        np.exp(K, out=K)
        K *= self.sf2
        K[np.diag_indices(n)] += h.noise_std ** 2
        fac = _cholesky(K)
        if fac is None:  # hopeless conditioning: fall back to a strongly regularized factor
            K[np.diag_indices(n)] += _JITTER_MAX * float(np.mean(np.diag(K)))
            fac = _cholesky(K)
            if fac is None:
                raise np.linalg.LinAlgError("kernel matrix is not positive definite (non-finite data?)")
        self.L, self.jitter = fac
        self.L = np.asfortranarray(self.L)   # LAPACK's layout: no copy per triangular solve
        self.alpha, _ = lapack.dpotrs(self.L, y, lower=1)
        # [alpha, alpha * x]: one product gives the mean and the sum its gradient needs
        self.alpha_aug = np.column_stack([self.alpha, self.alpha[:, None] * Xc])


def _capped_hyper(h: SEHyper, dims: tuple[int, ...], caps: tuple[float, ...]) -> SEHyper:
    ell = np.array(h.lengthscales, dtype=float)
    ell[list(dims)] = np.minimum(ell[list(dims)], caps)
    return SEHyper(ell, h.signal_std, h.noise_std)


class GaussianProcess:
    """Exact GP regression, one independent GP per output dimension sharing the inputs (eq. 5.21).
    Zero prior mean: with no data the mean is 0 and the variance the prior sigma_f^2.

    X: (N, p) inputs, Y: (N, d) outputs (N may be 0), hypers: one `SEHyper` per output dimension.
    Rows with a non-finite entry are dropped.
    """

    def __init__(self, X: np.ndarray, Y: np.ndarray, hypers: list[SEHyper]):
        X, Y = _clean_xy(X, Y)
        hypers = list(hypers)
        if Y.shape[1] != len(hypers):
            raise ValueError(f"Y has {Y.shape[1]} output dimensions but {len(hypers)} hyperparameter sets were given")
        p = hypers[0].p if hypers else X.shape[1]
        if len(X) and X.shape[1] != p or any(h.p != p for h in hypers):
            raise ValueError(f"inputs have {X.shape[1]} dimensions; every SEHyper needs that many lengthscales")
        keep = np.all(np.isfinite(X), axis=1) & np.all(np.isfinite(Y), axis=1)
        if not np.all(keep):
            X, Y = X[keep], Y[keep]
        self.p = p
        self.d = len(hypers)
        self.n = len(X)
        self.hypers = hypers
        self._X, self._Y = X, Y
        self._capped: dict[tuple, GaussianProcess] = {}
        self.center = X.mean(axis=0) if self.n else np.zeros(p)
        Xc = np.ascontiguousarray(X - self.center)
        self._Xc1 = np.column_stack([np.ones(self.n), Xc])   # [1, x]: sum and first moment in one product
        self._dims = [_Dim(Xc, np.ascontiguousarray(Y[:, j]), h) for j, h in enumerate(hypers)]
        self._stack = None

    def capped(self, dims: tuple[int, ...], caps: tuple[float, ...]) -> GaussianProcess:
        """The same data and signal and noise levels, with no lengthscale of input dims[i] longer than
        caps[i] (built once per GP; itself where none is longer)."""
        key = (tuple(dims), tuple(caps))
        if key not in self._capped:
            hypers = [_capped_hyper(h, dims, caps) for h in self.hypers]
            same = all(np.array_equal(a.lengthscales, h.lengthscales) for a, h in zip(hypers, self.hypers))
            self._capped[key] = self if same else GaussianProcess(self._X, self._Y, hypers)
        return self._capped[key]

    def mean_terms(self) -> tuple[np.ndarray, np.ndarray, list[tuple[np.ndarray, float, np.ndarray]]]:
        """(center, centred inputs (N, p), per output (1/lengthscales, sigma_f^2, alpha)): the posterior
        mean is sf2 * sum_n alpha_n exp(-|(a - center - x_n) / ell|^2 / 2), for re-expressing it in
        another modelling language (the CasADi benchmark does)."""
        Xc = self._Xc1[:, 1:]
        return self.center.copy(), Xc.copy(), [(c.inv_ell.copy(), float(c.sf2), c.alpha.copy()) for c in self._dims]

    def mean_and_grad(self, x) -> tuple[np.ndarray, np.ndarray]:
        """Posterior mean (d,) and its gradient (d, p) at ONE query point, all output dimensions in a
        handful of stacked numpy operations: the NMPC rolls its horizon out point by point, so per-call
        overhead, not flops, is what counts there."""
        q = np.asarray(x, dtype=float) - self.center
        if self.n == 0:
            return np.zeros(self.d), np.zeros((self.d, self.p))
        if self._stack is None:
            dims = self._dims
            # log k_n = log sf2 - |b_n|^2 / 2 + b_n . a - |a|^2 / 2: the query-free terms folded in once
            self._stack = (np.stack([c.B for c in dims]),
                           np.stack([np.log(c.sf2) - 0.5 * c.B2 for c in dims]),
                           np.stack([c.inv_ell for c in dims]), np.stack([c.inv_ell2 for c in dims]),
                           np.stack([c.alpha_aug for c in dims]))
        B, logc, inv_ell, inv_ell2, alpha_aug = self._stack
        A = q * inv_ell                                                     # (d, p)
        k = np.matmul(B, A[:, :, None])[:, :, 0]
        k += logc
        k -= 0.5 * np.einsum("ij,ij->i", A, A)[:, None]
        np.exp(k, out=k)                                                    # (d, N)
        r = np.matmul(k[:, None, :], alpha_aug)[:, 0, :]                    # [k alpha, k (alpha x)]
        mean = r[:, 0]
        return mean, (r[:, 1:] - q * r[:, :1]) * inv_ell2

    def mean(self, Xq) -> np.ndarray:
        """Posterior mean (M, d) only (no variance: no triangular solves)."""
        Q = self._prep(Xq)
        out = np.zeros((len(Q), self.d))
        if self.n == 0:
            return out
        for j, c in enumerate(self._dims):
            Kq = _sqdist(Q * c.inv_ell, c.B, None, c.B2)
            Kq *= -0.5
            np.exp(Kq, out=Kq)
            out[:, j] = c.sf2 * (Kq @ c.alpha)
        return out

    def _prep(self, Xq) -> np.ndarray:
        Xq = np.asarray(Xq, dtype=float)
        if Xq.ndim == 1:
            Xq = Xq[None, :]
        if Xq.ndim != 2 or Xq.shape[1] != self.p:
            raise ValueError(f"query points must be (M, {self.p}); got {Xq.shape}")
        return Xq - self.center

    def predict(self, Xq, coverage: bool = False):
        """Posterior mean (M, d) and variance (M, d) of the latent g (without sigma_n^2). With
        `coverage`, also (M, d) the kernel correlation to the nearest training input, max_n k(a, a_n) /
        sigma_f^2 in each output's own metric: 1 on a training input, 0 far from all of them."""
        Q = self._prep(Xq)
        m = len(Q)
        mean = np.zeros((m, self.d))
        var = np.empty((m, self.d))
        near = np.zeros((m, self.d))
        for j, c in enumerate(self._dims):
            if self.n == 0:
                var[:, j] = c.sf2
                continue
            A = Q * c.inv_ell
            Kq = _sqdist(A, c.B, None, c.B2)
            Kq *= -0.5
            np.exp(Kq, out=Kq)
            if coverage:
                near[:, j] = Kq.max(axis=1)
            Kq *= c.sf2
            mean[:, j] = Kq @ c.alpha
            V = _trsolve(c.L, Kq.T, False)                          # L^-1 k, (N, M)
            var[:, j] = c.sf2 - np.einsum("ij,ij->j", V, V)
        np.maximum(var, 0.0, out=var)
        return (mean, var, near) if coverage else (mean, var)

    def predict_with_grad(self, Xq) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Mean (M, d), variance (M, d), and their gradients w.r.t. the query point, (M, d, p) each."""
        Q = self._prep(Xq)
        m, p = Q.shape
        mean = np.zeros((m, self.d))
        var = np.empty((m, self.d))
        dmean = np.zeros((m, self.d, p))
        dvar = np.zeros((m, self.d, p))
        if self.n == 0:
            for j, c in enumerate(self._dims):
                var[:, j] = c.sf2
            return mean, var, dmean, dvar
        Xc1 = self._Xc1
        for j, c in enumerate(self._dims):
            A = Q * c.inv_ell
            Kq = _sqdist(A, c.B, None, c.B2)
            Kq *= -0.5
            np.exp(Kq, out=Kq)
            Kq *= c.sf2                                                    # k(a_q, a_n), (M, N)
            r = Kq @ c.alpha_aug                                           # [k alpha, k (alpha x)]
            mu = r[:, 0]
            mean[:, j] = mu
            # dk_n/da_q = -k_n (a_q - a_n) / ell^2 ; sum_n alpha_n dk_n = -(a_q mu - k (alpha x)) / ell^2
            dmean[:, j, :] = (r[:, 1:] - Q * mu[:, None]) * c.inv_ell2
            V = _trsolve(c.L, Kq.T, False)                                 # L^-1 k, (N, M)
            beta = _trsolve(c.L, V, True)                                  # K^-1 k
            P = beta.T * Kq                                                # (M, N)
            r = P @ Xc1                                                    # [k K^-1 k, sum_n P_n x_n]
            v = c.sf2 - np.einsum("ij,ij->j", V, V)
            # d var / d a_q = -2 k^T K^-1 dk/da_q = 2/ell^2 sum_n P_n (a_q - a_n)
            g = (Q * r[:, :1] - r[:, 1:]) * (2.0 * c.inv_ell2)
            clipped = v < 0.0
            if np.any(clipped):
                v[clipped] = 0.0
                g[clipped] = 0.0
            var[:, j] = v
            dvar[:, j, :] = g
        return mean, var, dmean, dvar


# --- hyperparameter fitting -------------------------------------------------------------------
@dataclass
class FitResult:
    hypers: list[SEHyper]
    lml: list[float]       # per output dimension, on the data used for fitting
    n_used: int
    seconds: float
    restarts: int          # random restarts per output dimension (1 + restarts optimizer runs each)


def _scales(X: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, float]:
    """Per-input spread and output magnitude that the bounds and initial values scale with."""
    if len(X) > 1:
        sx = X.std(axis=0)
    else:
        sx = np.ones(X.shape[1])
    sx = np.where(np.isfinite(sx) & (sx > 1e-12), sx, 1.0)
    ry = float(np.sqrt(np.mean(y * y))) if len(y) else 1.0
    if not (math.isfinite(ry) and ry > 1e-12):
        ry = 1.0
    return sx, ry


def hyper_bounds(X, y) -> np.ndarray:
    """(p + 2, 2) bounds on [log ell, log sf, log sn] used by `fit_hyperparameters`, relative to the
    data: ell_j in [1e-3, 1e5] std(x_j); sigma_f in [1e-4, 1e3] rms(y); sigma_n in [1e-6, 1e2] rms(y)."""
    X, y = np.asarray(X, dtype=float), np.asarray(y, dtype=float).reshape(-1)
    sx, ry = _scales(X, y)
    lo = np.concatenate([np.log(1e-3 * sx), [math.log(1e-4 * ry), math.log(max(1e-6 * ry, _FLOOR))]])
    hi = np.concatenate([np.log(1e5 * sx), [math.log(1e3 * ry), math.log(1e2 * ry)]])
    return np.column_stack([lo, hi])


def heuristic_hyper(X, y) -> SEHyper:
    """Data-driven starting point: lengthscales sqrt(p) std(x_j) (a smooth function of all inputs),
    sigma_f = rms(y), sigma_n = rms(y) / 3."""
    X, y = np.asarray(X, dtype=float), np.asarray(y, dtype=float).reshape(-1)
    sx, ry = _scales(X, y)
    return SEHyper(math.sqrt(X.shape[1]) * sx, ry, ry / 3.0)


def _random_start(rng: np.random.Generator, X, y) -> np.ndarray:
    sx, ry = _scales(X, y)
    p = X.shape[1]
    log_ell = np.log(math.sqrt(p) * sx) + rng.uniform(math.log(0.2), math.log(10.0), p)
    log_sf = math.log(ry) + rng.uniform(math.log(0.1), math.log(3.0))
    log_sn = math.log(ry) + rng.uniform(math.log(0.003), math.log(1.0))
    return np.concatenate([log_ell, [log_sf, log_sn]])


def _lml_blocks(blocks: list[tuple[np.ndarray, np.ndarray]], theta: np.ndarray, with_grad: bool):
    """Sum of independent LMLs: the data as the controller uses it, one local window at a time."""
    if len(blocks) == 1:
        return _lml(blocks[0][0], blocks[0][1], theta, with_grad)
    total, grad = 0.0, np.zeros(len(theta))
    for Xb, yb in blocks:
        out = _lml(Xb, yb, theta, with_grad)
        f, g = out if with_grad else (out, None)
        if not math.isfinite(f):
            return (-math.inf, np.zeros(len(theta))) if with_grad else -math.inf
        total += f
        if with_grad:
            grad += g
    return (total, grad) if with_grad else total


def _optimize(blocks: list[tuple[np.ndarray, np.ndarray]], theta0: np.ndarray,
              bounds: np.ndarray) -> tuple[np.ndarray, float]:
    """One L-BFGS-B run on -LML from theta0; returns the (clipped) optimum and its LML (or -inf)."""
    big = 1e30

    def objective(theta):
        f, g = _lml_blocks(blocks, theta, True)
        if not math.isfinite(f):
            return big, np.zeros_like(theta)
        return -f, -g

    theta0 = np.clip(theta0, bounds[:, 0], bounds[:, 1])
    try:
        res = minimize(objective, theta0, jac=True, method="L-BFGS-B", bounds=bounds, options={"maxiter": 2000})
        theta = np.clip(np.asarray(res.x, dtype=float), bounds[:, 0], bounds[:, 1])
    except (ValueError, ArithmeticError, np.linalg.LinAlgError):
        theta = theta0
    if not np.all(np.isfinite(theta)):
        theta = theta0
    f = _lml_blocks(blocks, theta, False)
    f0 = _lml_blocks(blocks, theta0, False)
    if f0 > f:  # the optimizer never makes things worse than its start
        return theta0, f0
    return theta, f


def subsample_rows(n: int, labels: np.ndarray | None, max_points: int, rng: np.random.Generator) -> np.ndarray:
    """Indices of at most `max_points` of n rows drawn with `rng`: uniformly, or with `labels` whole groups
    in random order until max_points rows (at least one group)."""
    if labels is None:
        return np.sort(rng.choice(n, size=int(max_points), replace=False))
    order = rng.permutation(np.unique(labels))
    sizes = np.array([np.count_nonzero(labels == g) for g in order])
    chosen = order[: max(1, int(np.searchsorted(np.cumsum(sizes), max_points, side="right")))]
    return np.flatnonzero(np.isin(labels, chosen))


def fit_hyperparameters(X, Y, *, restarts: int = 5, rng: np.random.Generator, max_points: int = 1000,
                        init: list[SEHyper] | None = None, groups: np.ndarray | None = None,
                        min_lengthscales: np.ndarray | None = None,
                        max_lengthscales: np.ndarray | None = None) -> FitResult:
    """Maximize the log marginal likelihood of each output dimension separately (thesis 5.2.3).

    Per output dimension: 1 + `restarts` L-BFGS-B runs on the log hyperparameters within
    `hyper_bounds`, the first from `init[j]` if given, else from `heuristic_hyper`, the others from
    random values around the data's scales; the best LML wins (the same counting as scikit-learn's
    `n_restarts_optimizer`). With N > `max_points`, all dimensions are fitted on one uniformly random
    subsample of `max_points` rows drawn with `rng`. Rows with a non-finite entry are dropped. Never
    raises on ill-conditioned data: a candidate whose kernel cannot be factorized scores -inf.

    `min_lengthscales` (p,), or (d, p) with one row per output dimension, raises the lower bounds of the
    lengthscales to a physical floor: how fast the disturbance can possibly change with each input.
    Closed-loop data are narrow (a robot that tracks well stays within centimetres of its route), and the
    likelihood alone then happily fits lengthscales far below any physical scale, which a controller that
    queries the model off its data exploits.

    `max_lengthscales`, shaped the same (inf: no ceiling), lowers the upper bounds: with the floor, it
    holds a lengthscale the data cannot tell at a chosen value.

    `groups` (one label per row) fits the model as it will be used when predictions come from local
    windows of the data (thesis 5.3.2): the objective is the sum of the LMLs of the groups, each an
    independent GP, and the subsample keeps whole groups. A pooled fit would also have to explain
    differences *between* places with the other inputs, which in closed-loop data are correlated
    with the place (the controller steers hardest where the disturbance is largest).
    """
    t0 = time.perf_counter()
    X, Y = _clean_xy(X, Y)
    keep = np.all(np.isfinite(X), axis=1) & np.all(np.isfinite(Y), axis=1)
    if not np.all(keep):
        X, Y = X[keep], Y[keep]
    n, p = X.shape
    d = Y.shape[1]
    restarts = max(0, int(restarts))
    if init is not None and len(init) != d:
        raise ValueError(f"init has {len(init)} hyperparameter sets for {d} output dimensions")
    labels = None if groups is None else np.asarray(groups)[keep]
    if max_points > 0 and n > max_points:
        idx = subsample_rows(n, labels, max_points, rng)
        X, Y = X[idx], Y[idx]
        labels = None if labels is None else labels[idx]
        n = len(X)
    Xc = X - X.mean(axis=0) if n else X
    members = [np.arange(n)] if labels is None else [np.flatnonzero(labels == g) for g in np.unique(labels)]
    hypers: list[SEHyper] = []
    lmls: list[float] = []
    for j in range(d):
        y = np.ascontiguousarray(Y[:, j])
        bounds = hyper_bounds(Xc, y)
        if min_lengthscales is not None:
            floors = np.asarray(min_lengthscales, dtype=float)
            floor = np.log(np.maximum(floors[j] if floors.ndim == 2 else floors, 1e-12))
            bounds[:p, 0] = np.maximum(bounds[:p, 0], floor)
            bounds[:p, 1] = np.maximum(bounds[:p, 1], bounds[:p, 0])
        if max_lengthscales is not None:
            ceilings = np.asarray(max_lengthscales, dtype=float)
            ceiling = np.log(np.maximum(ceilings[j] if ceilings.ndim == 2 else ceilings, 1e-12))
            bounds[:p, 1] = np.minimum(bounds[:p, 1], ceiling)
            bounds[:p, 0] = np.minimum(bounds[:p, 0], bounds[:p, 1])
        first = init[j] if init is not None else heuristic_hyper(Xc, y)
        if first.p != p:
            raise ValueError(f"init[{j}] has {first.p} lengthscales for {p} inputs")
        starts = [first.to_log()] + [_random_start(rng, Xc, y) for _ in range(restarts)]
        best_theta, best_f = np.clip(starts[0], bounds[:, 0], bounds[:, 1]), -math.inf
        if n == 0:
            hypers.append(first)
            lmls.append(0.0)
            continue
        blocks = [(Xc[m] - Xc[m].mean(axis=0), y[m]) for m in members]
        for theta0 in starts:
            theta, f = _optimize(blocks, theta0, bounds)
            if f > best_f:
                best_theta, best_f = theta, f
        hypers.append(SEHyper.from_log(best_theta))
        lmls.append(float(best_f))
    return FitResult(hypers=hypers, lml=lmls, n_used=n, seconds=time.perf_counter() - t0, restarts=restarts)

"""Uncertainty along the horizon (thesis 6.2.2, 7.3.2): the sigma-point transform of eq. 6.10-6.14.

The state x_j ~ N(xbar_j, Sigma_j) and the disturbance g(a_j) ~ N(mu(a_j), Sigma_gp(a_j)) are stacked
into z_j = (xbar_j, mu_j) with P_j = diag(Sigma_j, Sigma_gp); its 4n+1 = 13 sigma points go through the
unicycle step x' = f(x, u) + R(theta) m (the disturbance is in the body frame, as experiences are built),
and are recombined with the weights of eq. 6.14 (tuning gamma). The mean sequence is the deterministic
one of eq. 7.6b (the rollout in nmpc.py, whose Jacobians the solvers use); the sigma points give the
covariance around it.

The a-priori uncertainty of the unicycle model per control period is `PriorStd` (growing with speed
and turn rate); it is the variance before any experience (trial 1, or a speed never driven there). With
a GP, the variance is that prior scaled by the share of the GP's prior variance its (latent) posterior
keeps, or, near the experiences (in the GP's own metric), the posterior variance itself where it is
smaller; plus a small `process_std` floor for what never repeats. That metric's lengthscales are capped
along the route, in commanded speed and in commanded turn rate (`VOUCH_DIMS`; the caps are the setting
`NMPCSettings.vouch_lengthscales`, by default `VOUCH_SCALES`): fitted,
they grow long in every input the data hardly vary (one trial at one speed says nothing of how the
disturbance changes with speed), and then a handful of experiences on a straight at 0.9 m/s vouch for
a corner at 1.8 m/s. The mean keeps the fitted lengthscales. The measurement noise sigma_n, mostly
localization jitter between consecutive estimates, is not a disturbance of the motion and is left out.
Below the slowest speed of a window the learned mean is faded (rest_fade.py), and the part faded away is
added to the variance: slower than the data, a plan is not known to be narrower.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from services.controller.rest_fade import RestFaded


@dataclass(frozen=True, kw_only=True)
class PriorStd:
    """Per control period, in the body frame: std = base + per_mps * |v| + per_radps * |w| (m, m, rad)."""
    base: tuple[float, float, float] = (0.001, 0.002, 0.003)
    per_mps: tuple[float, float, float] = (0.004, 0.008, 0.008)
    per_radps: tuple[float, float, float] = (0.002, 0.004, 0.015)

    def __post_init__(self):
        if len(self.base) != 3 or len(self.per_mps) != 3 or len(self.per_radps) != 3 or min(
                *self.base, *self.per_mps, *self.per_radps) < 0:
            raise ValueError("prior std: three non-negative values each for base, per_mps and per_radps")

    def std(self, U: np.ndarray) -> np.ndarray:
        """(n, 3) std per period for commands U (n, 2): v, w."""
        return (np.asarray(self.base) + np.outer(np.abs(U[:, 0]), self.per_mps)
                + np.outer(np.abs(U[:, 1]), self.per_radps))


# the inputs of a (experience.A_NAMES) an experience vouches for only nearby, and how near at most by
# default (the variance's lengthscales): along the route, in commanded speed (the store's speed bin) and
# turn rate
VOUCH_DIMS = (0, 5, 6)
VOUCH_SCALES = (1.0, 0.25, 0.25)      # m, m/s, rad/s


def variance_gp(gp, caps: tuple[float, float, float] = VOUCH_SCALES):
    """The GP whose variance the laws use: `gp`'s data under lengthscales capped at `caps` (along the
    route, commanded speed, commanded turn rate; built once per GP and caps)."""
    return gp.capped(VOUCH_DIMS, tuple(caps))


class DisturbanceVariance:
    """Var[g(a)] per output for a batch of inputs: the GP's (latent) variance, or the prior."""

    def __init__(self, gp, prior: PriorStd, process_std: tuple[float, float, float],
                 caps: tuple[float, float, float] = VOUCH_SCALES):
        self.gp = gp
        self.var_gp = None if gp is None else variance_gp(gp, caps)
        self.prior = prior
        self.floor = np.square(np.asarray(process_std, dtype=float))

    def __call__(self, A: np.ndarray) -> np.ndarray:
        return self.with_mean(A)[1]

    def with_mean(self, A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(the GP's posterior mean, zero without a GP; the variance) from one GP prediction."""
        std = self.prior.std(A[:, 5:7])
        if self.gp is None:
            return np.zeros((len(A), 3)), std ** 2 + self.floor
        # the share of its prior sigma_f^2 the GP's posterior keeps (~0 next to repeated experiences, 1
        # far from them), applied to the a-priori variance at these commands: sigma_f^2 alone is one number
        # for all inputs and would claim the same uncertainty creeping as at full speed. Near the data the
        # posterior variance itself counts where smaller: a disturbance the data show to be small (side
        # slip on a flat floor) gets sigma_f below its noise, whose share stays ~1 however much is known.
        sf2 = np.array([h.signal_std ** 2 for h in self.gp.hypers])
        if self.var_gp is self.gp:
            mean, latent, near = self.gp.predict(A, coverage=True)
        else:
            mean, (_, latent, near) = self.gp.mean(A), self.var_gp.predict(A, coverage=True)
        prior = std ** 2
        share = np.minimum(latent / sf2, 1.0)
        var = np.minimum(share * prior, latent + (1.0 - near) * prior) + self.floor
        if isinstance(self.gp, RestFaded):
            var += np.square(self.gp.gap(A, mean))
        return mean, var


def sigma_point_step(x: np.ndarray, Sigma: np.ndarray, mu: np.ndarray, var_g: np.ndarray, v: float, w: float,
                     dt: float, gamma: float) -> np.ndarray:
    """Eq. 6.10-6.14 for one period: the covariance of x_{j+1} given x_j ~ N(x, Sigma) and the
    disturbance ~ N(mu, diag(var_g)). Returns Sigma_{j+1} (3x3).

    The 13 sigma points of z = (x, m) (n = 6, spread sqrt(n + gamma) along the columns of the block-
    diagonal square root) in closed form: the step is linear in m at fixed heading, so the six points
    that move only m lie symmetric about f(z_0) and together contribute exactly R diag(var_g) R' (their
    weight 1/(2(n + gamma)) times 2(n + gamma)) plus their offset from the mean; only the six points
    that move x go through cos/sin. Scalar arithmetic: numpy's per-call overhead was most of the cost
    at this size, and the law calls this K times per step."""
    n2 = 6
    scale = math.sqrt(n2 + gamma)
    w0 = gamma / (n2 + gamma)
    wi = 0.5 / (n2 + gamma)
    L = _chol3_rows(Sigma)
    x0, y0, t0 = float(x[0]), float(x[1]), float(x[2])
    m1, m2, m3 = float(mu[0]), float(mu[1]), float(mu[2])
    fwd = v * dt + m1            # along-track motion at the mean disturbance
    turn = w * dt + m3

    def f(px, py, pt):
        c, s = math.cos(pt), math.sin(pt)
        return px + fwd * c - m2 * s, py + fwd * s + m2 * c, pt + turn

    F0 = f(x0, y0, t0)
    pts = []
    for i in range(3):
        dx, dy, dth = scale * L[0][i], scale * L[1][i], scale * L[2][i]
        pts.append(f(x0 + dx, y0 + dy, t0 + dth))
        pts.append(f(x0 - dx, y0 - dy, t0 - dth))
    # mean: the six m-points average to F0
    mx = (w0 + 6 * wi) * F0[0] + wi * sum(p[0] for p in pts)
    my = (w0 + 6 * wi) * F0[1] + wi * sum(p[1] for p in pts)
    mt = (w0 + 6 * wi) * F0[2] + wi * sum(p[2] for p in pts)
    e = (F0[0] - mx, F0[1] - my, F0[2] - mt)
    ce = w0 + 6 * wi
    cxx, cxy, cxt = ce * e[0] * e[0], ce * e[0] * e[1], ce * e[0] * e[2]
    cyy, cyt, ctt = ce * e[1] * e[1], ce * e[1] * e[2], ce * e[2] * e[2]
    for p in pts:
        a, b, t = p[0] - mx, p[1] - my, p[2] - mt
        cxx += wi * a * a
        cxy += wi * a * b
        cxt += wi * a * t
        cyy += wi * b * b
        cyt += wi * b * t
        ctt += wi * t * t
    # + R(t0) diag(var_g) R(t0)' from the m-points
    c, s = math.cos(t0), math.sin(t0)
    v1, v2, v3 = (max(float(q), 0.0) for q in var_g)
    cxx += c * c * v1 + s * s * v2
    cxy += c * s * (v1 - v2)
    cyy += s * s * v1 + c * c * v2
    ctt += v3
    return np.array([[cxx, cxy, cxt], [cxy, cyy, cyt], [cxt, cyt, ctt]])


def _chol3_rows(Sigma: np.ndarray) -> list[list[float]]:
    """Lower Cholesky factor of a 3x3 covariance as nested lists, written out (np.linalg's call overhead
    is most of its cost at this size); one that is singular (a perfectly known heading, say) goes
    through its eigendecomposition (a square root, not triangular: any one serves the sigma points)."""
    a = Sigma.tolist()
    l11 = a[0][0] + 1e-12
    if l11 > 0:
        l11 = math.sqrt(l11)
        l21, l31 = a[1][0] / l11, a[2][0] / l11
        d2 = a[1][1] + 1e-12 - l21 * l21
        if d2 > 0:
            l22 = math.sqrt(d2)
            l32 = (a[2][1] - l31 * l21) / l22
            d3 = a[2][2] + 1e-12 - l31 * l31 - l32 * l32
            if d3 > 0:
                return [[l11, 0.0, 0.0], [l21, l22, 0.0], [l31, l32, math.sqrt(d3)]]
    vals, vecs = np.linalg.eigh(0.5 * (Sigma + Sigma.T))
    return (vecs * np.sqrt(np.maximum(vals, 0.0))).tolist()


def propagate(X: np.ndarray, A: np.ndarray, G: np.ndarray, var_g: np.ndarray, v: np.ndarray, w: np.ndarray,
              Sigma0: np.ndarray, dt: float, gamma: float) -> np.ndarray:
    """Covariances (K+1, 3, 3) along a predicted mean sequence X (K+1, 3) with disturbance means G (K, 3)
    and variances var_g (K, 3)."""
    K = len(v)
    out = np.empty((K + 1, 3, 3))
    out[0] = Sigma0
    for j in range(K):
        out[j + 1] = sigma_point_step(X[j], out[j], G[j], var_g[j], float(v[j]), float(w[j]), dt, gamma)
    return out


def route_sigmas(Sigmas: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Standard deviations (K, 3) of the along, lateral and heading errors of x_1..x_K, measured along
    the route's `direction` (K,) at each desired pose."""
    c, s = np.cos(direction), np.sin(direction)
    Sxx, Sxy, Syy = Sigmas[1:, 0, 0], Sigmas[1:, 0, 1], Sigmas[1:, 1, 1]
    along = c * c * Sxx + 2 * c * s * Sxy + s * s * Syy
    lat = s * s * Sxx - 2 * c * s * Sxy + c * c * Syy
    return np.sqrt(np.maximum(np.column_stack([along, lat, Sigmas[1:, 2, 2]]), 0.0))


def lateral_sigma_speed_jacobian(X: np.ndarray, Sigmas: np.ndarray, v: np.ndarray, direction: np.ndarray,
                                 sig_lat: np.ndarray, dt: float, dvar_dv: np.ndarray | None = None,
                                 dvar_dvprev: np.ndarray | None = None, lag: np.ndarray | None = None) -> np.ndarray:
    """d sigma_lat,j / d v_i (K, K), to first order (the linearized propagation Sigma' = A Sigma A' + Q with
    A = df/dx and Q = R(theta) diag(var_g) R(theta)'). Two effects: faster driving turns heading
    uncertainty into lateral uncertainty sooner (through A), and the disturbance itself is more uncertain
    at speeds with little experience or under a prior growing with speed (`dvar_dv` (K, 3): d var_g,j /
    d v_j; `dvar_dvprev`: d var_g,j / d v_{j-1}, the previous command being a GP input too). The
    constrained law needs this to know that slowing down shrinks the tightened corridor margin. `v` are
    the speeds the robot moves at; with a drive lag (`lag`: L of actuator.py, vbar = L v + c) the motion
    term of step j comes from every earlier command i with weight L[j, i] (the variance's from the
    commands themselves, which are the GP's inputs)."""
    K = len(v)
    out = np.zeros((K, K))
    n = np.column_stack([-np.sin(direction), np.cos(direction), np.zeros(K)])   # lateral direction
    th = X[:-1, 2]
    As = np.zeros((K, 3, 3))
    As[:, 0, 0] = As[:, 1, 1] = As[:, 2, 2] = 1.0
    As[:, 0, 2] = -v * dt * np.sin(th)
    As[:, 1, 2] = v * dt * np.cos(th)

    def dQ(j: int, dvar: np.ndarray) -> np.ndarray:
        c, s = math.cos(th[j]), math.sin(th[j])
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        return (R * dvar) @ R.T

    # dS[i] = d Sigma_{j+1} / d v_i for all i <= j, carried forward together: one batched product per j
    dS = np.zeros((K, 3, 3))
    for j in range(K):
        if j > 0:
            dS[:j] = As[j] @ dS[:j] @ As[j].T
            if dvar_dvprev is not None:
                dS[j - 1] += dQ(j, dvar_dvprev[j])
        dA = np.zeros((3, 3))
        dA[0, 2], dA[1, 2] = -dt * math.sin(th[j]), dt * math.cos(th[j])
        d = dA @ Sigmas[j] @ As[j].T
        if lag is None:
            dS[j] = d + d.T
        else:
            dS[:j + 1] += lag[j, :j + 1, None, None] * (d + d.T)
        if dvar_dv is not None:
            dS[j] += dQ(j, dvar_dv[j])
        if sig_lat[j] > 1e-9:
            out[j, :j + 1] = np.einsum("a,iab,b->i", n[j], dS[:j + 1], n[j]) / (2.0 * sig_lat[j])
    return out


def variance_speed_derivatives(var, A: np.ndarray, h: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """d var_g / d v_j and d var_g / d v_{j-1} (each (K, 3)) of a variance model `var(A)` along the
    horizon's inputs A (K, 9; column 5 is v_j, column 7 is v_{j-1}), by one batched forward difference."""
    K = len(A)
    B = np.vstack([A, A, A])
    B[K:2 * K, 5] += h
    B[2 * K:, 7] += h
    V = var(B)
    return (V[K:2 * K] - V[:K]) / h, (V[2 * K:] - V[:K]) / h

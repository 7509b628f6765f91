"""Sliding-window bundle adjustment of the teach pass's keyframe chain, with the stereo rig's
disparity offset estimated along (issue 21).

Frame-to-keyframe registration (pose.py) treats the reference keyframe's triangulated points as exact.
A point triangulated from one stereo pair is uncertain mostly in depth, and far more so at range
(sigma_z = z^2 sigma_d / (f b)), so every link of the chain inherits its reference frame's depth errors.
Here the last `size` keyframes and the landmarks tracked across them are estimated together: every
observation (u, v, d) of a landmark in every keyframe that saw it (equivalently its reprojection in
both images: u_right = u - d), weighted by the keypoint's own variances, robustly (Huber to converge
from the registrations, then Cauchy, which lets tracks across a repetitive scaffold or on a slowly
moving car lose their pull).

Disparity offset: a rectified rig whose calibration is slightly off (a relative yaw of the two cameras,
a principal point) measures every disparity off by a constant delta, d = f b / z - doffs - delta, and
depth from a small disparity is then too far by delta / d: a chain of frame-to-frame registrations
over-estimates motion by that much (a few per cent where most features are 10 px of disparity). delta
is observable from a window: the disparities of one landmark across keyframes and its image motion
must agree with one depth, and landmarks at different depths separate delta from the motion. So delta
is one more parameter, shared by all observations, with a Gaussian prior.

Landmarks are anchored inverse depth: in the frame of the oldest keyframe that saw it (its anchor a)
the landmark is p_a = (alpha, beta, 1) / rho, so a landmark at 80 m (rho = 0.0125) is as well
conditioned as one at 5 m, and the projection of p_j = R_ja p_a + t_ja is computed from
q = rho p_j = R_ja (alpha, beta, 1) + rho t_ja without dividing by rho:
    u = f_u q_x / q_z + c_u,  v = f_v q_y / q_z + c_v,  d = f_u b rho / q_z - doffs - delta.
Poses: T_j_w = exp(xi_j) T_j_w^0 (left perturbation in camera j, translation first, as in pose.py),
world = the window's oldest keyframe, held fixed (stereo fixes the scale; one pose fixes the gauge).
Levenberg-Marquardt with analytic Jacobians; each landmark's 3x3 block is eliminated (Schur
complement), leaving a 6 (n - 1) (+1) system. (scipy.optimize.least_squares with the sparse Jacobian,
trust region and LSMR, had lowered the cost of a 5-keyframe window from 16,430 to 4,114 after 8
evaluations against 3,698 at its minimum, reached after ~50: LSMR does not exploit the block structure;
the eliminated system converges in 2-3 iterations.) Pure: inputs in, poses out.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from common.se3 import exp as se3_exp
from common.se3 import inverse as inv_T
from services.localizer.vision.camera import StereoCamera
from services.localizer.vision.features import StereoKeypoints
from services.localizer.vision.settings import VisionSettings


@dataclass
class _Frame:
    kp: StereoKeypoints
    T_prev_this: np.ndarray     # the chain edge into the previous window frame (identity for the first)
    landmark: np.ndarray        # (N,) landmark id of each keypoint, -1 for none


@dataclass(frozen=True)
class _Problem:
    frame: np.ndarray           # (M,) window index of each observation
    anchor: np.ndarray          # (M,) window index of the observation's landmark's anchor
    lm: np.ndarray              # (M,) landmark column of each observation
    y: np.ndarray               # (M, 3) measured (u, v, d)
    inv_sigma: np.ndarray       # (M, 3) 1 / std of u, v, d
    n_free: int                 # frames 1..n_free are free, frame 0 fixed
    n_lm: int


@dataclass(frozen=True)
class Adjusted:
    """The window's refined chain edges T_prev_this of frames 1..n-1 and its disparity offset (px)
    with its standard deviation (None when it was held)."""
    edges: list[np.ndarray]
    offset_px: float
    offset_std_px: float | None


class KeyframeWindow:
    """The last `size` keyframes of the teach chain and the landmarks tracked across them.

    `push` adds a keyframe with its chain edge and its inlier matches against the previous keyframe
    (live index, previous index), as `estimate_pose` returns them; `adjust` re-estimates the window and
    returns the refined chain edges T_prev_this of frames 1..n-1 (frame 0 is held fixed). Every
    adjustment starts from the registrations' edges, not from the previous window's result: fed
    forward, one solve that settles in a wrong minimum (KITTI's scaffolding, 8 cm off in 5 m) starts
    the next one worse, and the chain ran away within five keyframes."""

    def __init__(self, camera: StereoCamera, settings: VisionSettings):
        if settings.ba_window < 2:
            raise ValueError(f"a bundle-adjustment window needs at least 2 keyframes, got {settings.ba_window}")
        self.camera, self.size, self.huber_k = camera, settings.ba_window, settings.huber_k
        self.max_iters, self.max_landmarks = settings.ba_iters, settings.ba_max_landmarks
        self.frames: list[_Frame] = []
        self._next_id = 0

    def __len__(self) -> int:
        return len(self.frames)

    def push(self, kp: StereoKeypoints, T_prev_this: np.ndarray, pairs: np.ndarray | None) -> None:
        """`pairs` None: no matches to the previous keyframe (a chain link made another way): the
        window restarts at this keyframe."""
        if pairs is None or not self.frames:
            self.frames = []
            T_prev_this = np.eye(4)
        landmark = np.full(len(kp), -1, dtype=np.int64)
        if self.frames and len(pairs):
            prev = self.frames[-1].landmark
            pairs = pairs[pairs[:, 1] < len(prev)]       # submap points added after the keyframe: no track
            this_i, prev_i = pairs[:, 0], pairs[:, 1]
            new = prev[prev_i] < 0
            ids = np.arange(self._next_id, self._next_id + int(new.sum()))
            self._next_id += len(ids)
            prev[prev_i[new]] = ids
            landmark[this_i] = prev[prev_i]
        self.frames.append(_Frame(kp, np.asarray(T_prev_this, dtype=float).copy(), landmark))
        if len(self.frames) > self.size:
            self.frames.pop(0)
            self.frames[0].T_prev_this = np.eye(4)

    def adjust(self, offset_px: float = 0.0, offset_prior_std_px: float | None = None) -> Adjusted | None:
        """Re-estimate the window; `offset_px` the disparity offset to start from, estimated with that
        prior mean and standard deviation (None: held fixed). None when there is nothing to adjust."""
        if len(self.frames) < 2:
            return None
        prob = self._problem()
        if prob is None:
            return None
        x = _State(self._poses(), self._initial_landmarks(prob, offset_px), offset_px)
        x.L = _refine_landmarks(self.camera, prob, x, self.huber_k, 2)
        prior = None if offset_prior_std_px is None else (offset_px, offset_prior_std_px)
        x, _ = _levenberg_marquardt(self.camera, prob, x, self.huber_k, self.max_iters, "huber", prior)
        x, std = _levenberg_marquardt(self.camera, prob, x, self.huber_k, 1, "cauchy", prior)
        T = x.T
        return Adjusted([T[j - 1] @ inv_T(T[j]) for j in range(1, len(T))], x.offset, std)

    # ------------------------------------------------------------- set-up
    def _poses(self) -> np.ndarray:
        """T_j_w of every window frame from the chain edges (w = frame 0)."""
        T_w_j = np.eye(4)
        out = [np.eye(4)]
        for f in self.frames[1:]:
            T_w_j = T_w_j @ f.T_prev_this
            out.append(inv_T(T_w_j))
        return np.array(out)

    def _problem(self) -> _Problem | None:
        frame, ids, y, var = [], [], [], []
        for j, f in enumerate(self.frames):
            seen = np.flatnonzero(f.landmark >= 0)
            frame.append(np.full(len(seen), j))
            ids.append(f.landmark[seen])
            y.append(f.kp.uvd[seen])
            var.append(f.kp.cov_uvd[seen])
        frame, ids = np.concatenate(frame), np.concatenate(ids)
        if len(ids) == 0:
            return None
        _, lm, count = np.unique(ids, return_inverse=True, return_counts=True)
        keep = count[lm] >= 2                          # a landmark seen once says nothing about the poses
        if not keep.any():
            return None
        if self.max_landmarks and np.count_nonzero(count >= 2) > self.max_landmarks:
            # the longest tracks carry the most about the poses and the offset
            order = np.lexsort((np.arange(len(count)), -count))[:self.max_landmarks]
            chosen = np.zeros(len(count), bool)
            chosen[order] = True
            keep &= chosen[lm]
        frame, y, var = frame[keep], np.concatenate(y)[keep], np.concatenate(var)[keep]
        kept, lm = np.unique(lm[keep], return_inverse=True)
        anchor = np.full(len(kept), len(self.frames))
        np.minimum.at(anchor, lm, frame)
        return _Problem(frame, anchor[lm], lm, y, 1.0 / np.sqrt(var), len(self.frames) - 1, len(kept))

    def _initial_landmarks(self, prob: _Problem, offset_px: float) -> np.ndarray:
        """(alpha, beta, rho) of each landmark from its anchor observation."""
        cam = self.camera
        at_anchor = prob.frame == prob.anchor
        first = np.zeros(prob.n_lm, dtype=np.int64)
        first[prob.lm[at_anchor][::-1]] = np.flatnonzero(at_anchor)[::-1]
        u, v, d = prob.y[first].T
        lm = np.column_stack([(u - cam.cu) / cam.fu, (v - cam.cv) / cam.fv,
                              (d + cam.doffs_px + offset_px) / (cam.fu * cam.baseline_m)])
        return lm


def _hat(v: np.ndarray) -> np.ndarray:
    """(M, 3, 3) skew matrices of (M, 3) vectors."""
    H = np.zeros((len(v), 3, 3))
    H[:, 0, 1], H[:, 0, 2] = -v[:, 2], v[:, 1]
    H[:, 1, 0], H[:, 1, 2] = v[:, 2], -v[:, 0]
    H[:, 2, 0], H[:, 2, 1] = -v[:, 1], v[:, 0]
    return H


# ----------------------------------------------------------------- the model and its Jacobian
@dataclass
class _State:
    T: np.ndarray               # (n, 4, 4) T_j_w
    L: np.ndarray               # (n_lm, 3) alpha, beta, rho
    offset: float               # disparity offset delta (px)


def _model(cam: StereoCamera, prob: _Problem, x: _State, jacobians: bool, poses: bool = True):
    """Whitened residuals (M, 3) of every observation and, if asked, their Jacobians by the landmark
    (M, 3, 3), by the observing frame's pose and by the anchor's pose (M, 3, 6 each; None unless
    `poses`); by the offset the Jacobian is -1 / sigma_d on the d rows."""
    T, L = x.T, x.L
    n = len(T)
    T_pairs = (T[:, None] @ inv_T_stack(T)[None]).reshape(n * n, 4, 4)   # [j, a]: anchor a -> frame j
    T_ja = T_pairs[prob.frame * n + prob.anchor]
    R, t = T_ja[:, :3, :3], T_ja[:, :3, 3]
    Lm = L[prob.lm]
    rho = Lm[:, 2]
    ray = np.column_stack([Lm[:, 0], Lm[:, 1], np.ones(len(Lm))])
    q = np.einsum("mij,mj->mi", R, ray) + rho[:, None] * t              # rho p_j
    iz = 1.0 / q[:, 2]
    fb = cam.fu * cam.baseline_m
    h = np.column_stack([cam.fu * q[:, 0] * iz + cam.cu, cam.fv * q[:, 1] * iz + cam.cv,
                         fb * rho * iz - cam.doffs_px - x.offset])
    r = (h - prob.y) * prob.inv_sigma
    if not jacobians:
        return r, None
    M = len(q)
    Jq = np.zeros((M, 3, 3))                        # dh/dq at fixed rho
    Jq[:, 0, 0] = cam.fu * iz
    Jq[:, 0, 2] = -cam.fu * q[:, 0] * iz ** 2
    Jq[:, 1, 1] = cam.fv * iz
    Jq[:, 1, 2] = -cam.fv * q[:, 1] * iz ** 2
    Jq[:, 2, 2] = -fb * rho * iz ** 2
    w = prob.inv_sigma[:, :, None]
    J_l = Jq @ np.concatenate([R[:, :, :2], t[:, :, None]], axis=2)     # by alpha, beta, rho
    J_l[:, 2, 2] += fb * iz                                              # d's own factor rho
    if not poses:
        return r, (J_l * w, None, None)
    dq_j = np.zeros((M, 3, 6))                      # frame j's pose: dq/dxi_j = [rho I, -q^]
    dq_j[:, [0, 1, 2], [0, 1, 2]] = rho[:, None]
    dq_j[:, :, 3:] = -_hat(q)
    da = np.zeros((M, 3, 6))                        # the anchor's: dq/dxi_a = -R_ja [rho I, -ray^]
    da[:, [0, 1, 2], [0, 1, 2]] = rho[:, None]
    da[:, :, 3:] = -_hat(ray)
    return r, (J_l * w, (Jq @ dq_j) * w, (-(Jq @ R) @ da) * w)


def inv_T_stack(T: np.ndarray) -> np.ndarray:
    """Inverses of a stack of rigid transforms (M, 4, 4)."""
    out = np.zeros_like(T)
    Rt = np.transpose(T[:, :3, :3], (0, 2, 1))
    out[:, :3, :3] = Rt
    out[:, :3, 3] = -np.einsum("mij,mj->mi", Rt, T[:, :3, 3])
    out[:, 3, 3] = 1.0
    return out


def _robust(r: np.ndarray, k: float, loss: str) -> tuple[np.ndarray, float]:
    """Weights of the observations (on their 3-dof whitened norm) and the robust cost: "huber" (convex,
    to converge from the registrations' poses) or "cauchy" (redescending: a track on a slowly moving
    car, or across a repetitive scaffold, agrees with each frame-to-frame registration but not with the
    window, and must lose its pull instead of bending the chain)."""
    n2 = np.sum(r * r, axis=1) / (k * k)
    if loss == "cauchy":
        return 1.0 / (1.0 + n2), float(0.5 * k * k * np.log1p(n2).sum())
    n = np.sqrt(n2)
    return np.where(n <= 1.0, 1.0, 1.0 / np.maximum(n, 1e-12)), \
        float((k * k * np.where(n <= 1.0, 0.5 * n2, n - 0.5)).sum())


def _per_landmark(prob: _Problem) -> sp.csr_matrix:
    """(n_lm, M) 0/1 matrix: sums per-observation terms by landmark."""
    M = len(prob.lm)
    return sp.csr_matrix((np.ones(M), (prob.lm, np.arange(M))), shape=(prob.n_lm, M))


def _refine_landmarks(cam: StereoCamera, prob: _Problem, x: _State, k: float, iters: int) -> np.ndarray:
    """Gauss-Newton on the landmarks alone, the poses held: from one observation's triangulation to
    all of the window's (3x3 per landmark), so that the joint problem starts near its minimum."""
    per_lm = _per_landmark(prob)
    L = x.L
    for _ in range(iters):
        r, (J_l, _, _) = _model(cam, prob, _State(x.T, L, x.offset), True, poses=False)
        w, _ = _robust(r, k, "huber")
        wJl = w[:, None, None] * J_l
        H = (per_lm @ (np.transpose(J_l, (0, 2, 1)) @ wJl).reshape(-1, 9)).reshape(-1, 3, 3)
        g = per_lm @ np.einsum("mia,mi->ma", wJl, r)
        L = L - np.linalg.solve(H + 1e-9 * np.eye(3), g[:, :, None])[:, :, 0]
    return L


def _global_jacobian(prob: _Problem, J_j: np.ndarray, J_a: np.ndarray, with_offset: bool) -> np.ndarray:
    """(M, 3, 6 (n - 1) [+ 1]) Jacobian of every observation by the free poses [and the offset]."""
    M, P = len(prob.lm), 6 * prob.n_free
    Jp = np.zeros((M, 3, P + 6 + with_offset))
    m = np.flatnonzero(prob.frame != prob.anchor)   # in its anchor frame a landmark depends on no pose
    for who, Jw in ((prob.frame, J_j), (prob.anchor, J_a)):
        Jp[m[:, None, None], np.arange(3)[None, :, None], (6 * who[m, None] + np.arange(6))[:, None, :]] = Jw[m]
    if with_offset:
        Jp[:, 2, -1] = -prob.inv_sigma[:, 2]
    return Jp[:, :, 6:]


def _step(x: _State, dp: np.ndarray, dl: np.ndarray, with_offset: bool) -> _State:
    T = x.T.copy()
    for j in range(1, len(T)):
        T[j] = se3_exp(dp[6 * (j - 1):6 * j]) @ x.T[j]
    return _State(T, x.L + dl, x.offset + (dp[-1] if with_offset else 0.0))


def _levenberg_marquardt(cam: StereoCamera, prob: _Problem, x: _State, k: float, iters: int, loss: str,
                         prior: tuple[float, float] | None) -> tuple[_State, float | None]:
    """Robust Gauss-Newton with Levenberg-Marquardt damping; the landmarks are eliminated per landmark
    (3x3 blocks, Schur complement). `prior` (mean, std) of the offset, None: held. Returns the state
    and the offset's standard deviation (from the undamped reduced system)."""
    with_offset = prior is not None
    P = 6 * prob.n_free + with_offset
    per_lm = _per_landmark(prob)

    def cost_of(state: _State) -> tuple[np.ndarray | None, float]:
        r, _ = _model(cam, prob, state, False)
        if not np.all(np.isfinite(r)):
            return None, np.inf
        _, c = _robust(r, k, loss)
        return r, c + (0.5 * ((state.offset - prior[0]) / prior[1]) ** 2 if with_offset else 0.0)

    lam, std = 1e-3, None
    _, cost = cost_of(x)
    for _ in range(iters):
        r, (J_l, J_j, J_a) = _model(cam, prob, x, True)
        w, _ = _robust(r, k, loss)
        Jp = _global_jacobian(prob, J_j, J_a, with_offset)
        M = len(r)
        wr = w[:, None] * r
        A = (Jp * np.sqrt(w)[:, None, None]).reshape(3 * M, P)
        H_pp = A.T @ A
        g_p = Jp.reshape(3 * M, P).T @ wr.ravel()
        if with_offset:
            H_pp[-1, -1] += prior[1] ** -2
            g_p[-1] += (x.offset - prior[0]) / prior[1] ** 2
        wJl = w[:, None, None] * J_l
        H_ll = (per_lm @ (np.transpose(J_l, (0, 2, 1)) @ wJl).reshape(M, 9)).reshape(-1, 3, 3)
        g_l = per_lm @ np.einsum("mia,mi->ma", J_l, wr)
        H_pl = (per_lm @ (np.transpose(Jp, (0, 2, 1)) @ wJl).reshape(M, 3 * P)).reshape(-1, P, 3)
        while True:
            Hl = H_ll + lam * (H_ll * np.eye(3)) + 1e-12 * np.eye(3)
            Y = H_pl @ np.linalg.inv(Hl)                                    # (n_lm, P, 3)
            S = H_pp - Y.transpose(1, 0, 2).reshape(P, -1) @ H_pl.transpose(1, 0, 2).reshape(P, -1).T
            S += lam * np.diag(np.diag(H_pp))
            b = g_p - np.einsum("lai,li->a", Y, g_l)
            try:
                dp = np.linalg.solve(S, -b)
            except np.linalg.LinAlgError:
                return x, std
            dl = -np.linalg.solve(Hl, (g_l + np.einsum("lai,a->li", H_pl, dp))[:, :, None])[:, :, 0]
            x_new = _step(x, dp, dl, with_offset)
            _, cost_new = cost_of(x_new)
            if cost_new < cost:
                lam = max(lam / 3.0, 1e-7)
                break
            lam *= 5.0
            if lam > 1e4:
                return x, std
        if with_offset:
            S0 = S - lam * np.diag(np.diag(H_pp))
            std = float(np.sqrt(max(np.linalg.inv(S0)[-1, -1], 0.0)))
        done = cost - cost_new < 1e-4 * cost
        x, cost = x_new, cost_new
        if done:
            break
    return x, std

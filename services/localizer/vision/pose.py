"""Pose of the live stereo frame relative to a reference submap (thesis 2.2.2, eq. 2.3-2.5).

Transforms: `T_a_b` (4x4) maps a point expressed in frame b into frame a, p_a = T_a_b p_b; it is also
the pose of frame b seen from frame a. `T_live_ref` is eq. 2.5's T_{k,m}.

Perturbations and covariances: T = exp(xi^) T_hat with xi = (rho, phi), translation first, then
rotation, expressed in the live (left, "a") frame. Every 6x6 covariance here is the covariance of xi.

Pipeline: Hamming nearest neighbours (gated by the predicted image position when a prior pose is
given), RANSAC on the left-image projections (cv2.solvePnPRansac; its RNG is re-seeded to a constant on
every call inside OpenCV, so results are repeatable), then Gauss-Newton on the (u, v, d) reprojection
error weighted by the live measurement's inverse covariance, with a Huber weight, re-selecting inliers
by their Mahalanobis distance between rounds. When the reference keypoints' own (u, v, d) variances are
given (`ref_cov_uvd`), their noise carried into the live image is added to W_n^-1 (the thesis weights
by the live measurement only; with it the covariance stays honest for far, poorly triangulated points).
The covariance is the inverse Gauss-Newton Hessian times the a-posteriori variance factor (>= 1).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from common.se3 import exp as se3_exp
from common.se3 import transform
from services.localizer.vision.camera import StereoCamera
from services.localizer.vision.features import StereoKeypoints, hamming, window_pairs
from services.localizer.vision.settings import VisionSettings


# ---------------------------------------------------------------- result
@dataclass
class PoseEstimate:
    """`T_live_ref` maps reference points into the live camera frame (eq. 2.5). `cov` (6x6) is the
    covariance of the left perturbation (translation, rotation) of T_live_ref. When `ok` is False the
    pose is identity, the covariance infinite and `reason` says why: never a fabricated pose."""
    ok: bool
    T_live_ref: np.ndarray
    cov: np.ndarray
    inliers: int
    matched: int
    reason: str = ""
    pairs: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))   # inlier (live, ref)

    @classmethod
    def failed(cls, reason: str, matched: int = 0, inliers: int = 0) -> PoseEstimate:
        return cls(False, np.eye(4), np.full((6, 6), np.inf), inliers, matched, reason)


# ---------------------------------------------------------------- matching
def best_pairs(qi: np.ndarray, ti: np.ndarray, dist: np.ndarray, max_dist: int,
               ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """From candidate pairs (query, train, Hamming distance): per query the nearest train descriptor,
    kept when within max_dist and below ratio x the second nearest; then one query per train index."""
    if len(qi) == 0:
        return qi, ti
    o = np.lexsort((dist, qi))
    qi, ti, dist = qi[o], ti[o], dist[o].astype(np.int64)
    head = np.flatnonzero(np.r_[True, qi[1:] != qi[:-1]])
    nxt = head + 1
    has2 = (nxt < len(qi)) & np.isin(nxt, head, invert=True)
    second = np.where(has2, dist[np.minimum(nxt, len(qi) - 1)], np.iinfo(np.int64).max)
    good = (dist[head] <= max_dist) & (dist[head] < ratio * second)
    bq, bt, bd = qi[head][good], ti[head][good], dist[head][good]
    if len(bq) == 0:
        return bq, bt
    o = np.lexsort((bd, bt))
    first = np.r_[True, bt[o][1:] != bt[o][:-1]]
    keep = np.sort(o[first])
    return bq[keep], bt[keep]


def match(live: StereoKeypoints, ref_desc: np.ndarray, s: VisionSettings,
          ref_uv_pred: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(live index, ref index) of descriptor matches; with predicted reference positions in the live
    image only pairs within `gate_px` in u and v are candidates (NaN predictions never match)."""
    n, m = len(live), len(ref_desc)
    if ref_uv_pred is None:
        dist, nidx = cv2.batchDistance(live.desc, ref_desc, cv2.CV_32S, normType=cv2.NORM_HAMMING,
                                       K=min(2, m))
        qi = np.repeat(np.arange(n), dist.shape[1])
        ti, dd = nidx.ravel().astype(np.int64), dist.ravel()
        valid = ti >= 0
        qi, ti, dd = qi[valid], ti[valid], dd[valid]
    else:
        valid = np.flatnonzero(np.isfinite(ref_uv_pred[:, 0]))
        qi, ti = window_pairs(live.uvd[:, 0], ref_uv_pred[valid, 0], s.gate_px)
        ti = valid[ti]
        near = np.abs(live.uvd[qi, 1] - ref_uv_pred[ti, 1]) <= s.gate_px
        qi, ti = qi[near], ti[near]
        dd = hamming(live.desc[qi], ref_desc[ti])
    return best_pairs(qi, ti, dd, s.match_max_hamming, s.match_ratio)


# ---------------------------------------------------------------- Gauss-Newton on eq. 2.4
def _info(T: np.ndarray, p: np.ndarray, Jh: np.ndarray, var: np.ndarray, ref_J: np.ndarray | None,
          ref_var: np.ndarray | None) -> np.ndarray:
    """(n, 3, 3) inverse covariance of e_n: the live measurement's, plus the reference point's own
    stereo noise carried into the live image when it is known (M = dh/dp C dg/dy_ref)."""
    if ref_J is None:
        W = np.zeros((len(p), 3, 3))
        W[:, [0, 1, 2], [0, 1, 2]] = 1.0 / var
        return W
    M = Jh @ T[:3, :3] @ ref_J
    S = (M * ref_var[:, None, :]) @ M.transpose(0, 2, 1)
    S[:, [0, 1, 2], [0, 1, 2]] += var
    return _inv_sym3(S)


def _inv_sym3(S: np.ndarray) -> np.ndarray:
    """Inverse of a stack of symmetric positive definite 3x3 matrices by cofactors (much cheaper than
    np.linalg.inv's per-matrix LU at this size)."""
    a, b, c = S[:, 0, 0], S[:, 0, 1], S[:, 0, 2]
    d, e, f = S[:, 1, 1], S[:, 1, 2], S[:, 2, 2]
    A, B, C = d * f - e * e, c * e - b * f, b * e - c * d
    D, E, F = a * f - c * c, b * c - a * e, a * d - b * b
    det = a * A + b * B + c * C
    return np.stack([A, B, C, B, D, E, C, E, F], axis=1).reshape(-1, 3, 3) / det[:, None, None]


def _mahalanobis(T, q, y, var, cam, ref_J, ref_var) -> np.ndarray:
    p, front, e = _residuals(T, q, y, cam)
    W = _info(T, p, cam.project_jacobian(p), var, ref_J, ref_var)
    return np.where(front, np.einsum("ni,nij,nj->n", e, W, e), np.inf)


def _residuals(T, q, y, cam):
    p = transform(T, q)
    front = p[:, 2] > 1e-3
    p = np.where(front[:, None], p, 1.0)
    return p, front, np.where(front[:, None], y - cam.project(p), 0.0)


def _gn(T: np.ndarray, q: np.ndarray, y: np.ndarray, var: np.ndarray, cam: StereoCamera, s: VisionSettings,
        ref_J: np.ndarray | None = None, ref_var: np.ndarray | None = None
        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Minimize sum_n rho(e_n^T W_n e_n), e_n = y_n - h(T q_n), over T. Returns (T, information matrix
    at the solution (robust weights included), squared Mahalanobis distances)."""
    H = np.zeros((6, 6))
    for it in range(s.gn_iters + 1):
        p, front, e = _residuals(T, q, y, cam)
        Jh = cam.project_jacobian(p)
        W = _info(T, p, Jh, var, ref_J, ref_var)
        m2 = np.where(front, np.einsum("ni,nij,nj->n", e, W, e), np.inf)
        r = np.sqrt(m2)
        w = np.where(r <= s.huber_k, 1.0, s.huber_k / np.maximum(r, 1e-12)) * front
        A = np.empty((len(q), 3, 6))
        A[:, :, :3] = Jh
        A[:, :, 3] = Jh[:, :, 2] * p[:, None, 1] - Jh[:, :, 1] * p[:, None, 2]   # Jh @ (-p^) columns
        A[:, :, 4] = Jh[:, :, 0] * p[:, None, 2] - Jh[:, :, 2] * p[:, None, 0]
        A[:, :, 5] = Jh[:, :, 1] * p[:, None, 0] - Jh[:, :, 0] * p[:, None, 1]
        WA = (w[:, None, None] * (W @ A)).reshape(-1, 6)
        H = A.reshape(-1, 6).T @ WA
        if it == s.gn_iters:
            break
        g = WA.T @ e.ravel()
        try:
            xi = np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            break
        T = se3_exp(xi) @ T
        if np.linalg.norm(xi[:3]) < 1e-6 and np.linalg.norm(xi[3:]) < 1e-7:     # um, 0.1 urad
            m2 = _mahalanobis(T, q, y, var, cam, ref_J, ref_var)
            break
    return T, H, m2


def estimate_pose(ref_points: np.ndarray, ref_desc: np.ndarray, live: StereoKeypoints, camera: StereoCamera,
                  settings: VisionSettings, T_init: np.ndarray | None = None,
                  ref_cov_uvd: np.ndarray | None = None) -> PoseEstimate:
    """T_live_ref from a reference submap (3D points in its frame + descriptors) and the live keypoints.
    `T_init` (a prior T_live_ref) gates the descriptor search by predicted image position; if the gated
    search fails the search is repeated without the gate."""
    s = settings
    ref_points = np.asarray(ref_points, dtype=np.float64)
    if ref_points.ndim != 2 or ref_points.shape[1] != 3:
        raise ValueError(f"ref_points must be (M, 3), got {ref_points.shape}")
    if ref_desc.dtype != np.uint8 or ref_desc.shape != (len(ref_points), 32):
        raise ValueError(f"ref_desc must be uint8 ({len(ref_points)}, 32), got {ref_desc.dtype} {ref_desc.shape}")
    if ref_cov_uvd is not None and np.shape(ref_cov_uvd) != (len(ref_points), 3):
        raise ValueError(f"ref_cov_uvd must be ({len(ref_points)}, 3), got {np.shape(ref_cov_uvd)}")
    if T_init is not None and np.asarray(T_init).shape != (4, 4):
        raise ValueError("T_init must be 4x4")
    if len(live) < s.min_inliers or len(ref_points) < s.min_inliers:
        return PoseEstimate.failed(f"too few keypoints: live {len(live)}, reference {len(ref_points)} "
                                   f"(need {s.min_inliers})")
    if T_init is not None:
        est = _estimate(ref_points, ref_desc, live, camera, s, np.asarray(T_init, dtype=np.float64), ref_cov_uvd)
        if est.ok:
            return est
    return _estimate(ref_points, ref_desc, live, camera, s, None, ref_cov_uvd)


def _estimate(ref_points, ref_desc, live, camera, s, T_init, ref_cov_uvd) -> PoseEstimate:
    pred = None
    if T_init is not None:
        p = transform(T_init, ref_points)
        pred = np.full((len(p), 2), np.nan)
        front = p[:, 2] > 0.1
        pred[front] = camera.project(p[front])[:, :2]
    qi, ri = match(live, ref_desc, s, pred)
    matched = len(qi)
    if matched < s.min_inliers:
        return PoseEstimate.failed(f"too few descriptor matches: {matched} (need {s.min_inliers})", matched)
    ok, rvec, tvec, inl = cv2.solvePnPRansac(ref_points[ri], live.uvd[qi, :2].copy(), camera.K, None,
                                             iterationsCount=s.ransac_iters, reprojectionError=s.ransac_px,
                                             confidence=s.ransac_confidence, flags=cv2.SOLVEPNP_AP3P)
    n_ransac = 0 if inl is None else len(inl)
    if not ok or n_ransac < s.min_inliers:
        return PoseEstimate.failed(f"too few RANSAC inliers: {n_ransac} of {matched} matches "
                                   f"(need {s.min_inliers})", matched, n_ransac)
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec.ravel()
    q, y, var = ref_points[ri], live.uvd[qi], live.cov_uvd[qi]
    rJ = rv = None
    if ref_cov_uvd is not None:
        rJ, rv = camera.triangulate_jacobian(camera.project(q)), ref_cov_uvd[ri]
    sel = np.zeros(matched, bool)
    sel[inl.ravel()] = True
    for rnd in range(s.gn_rounds + 1):
        T, H, m2_sel = _gn(T, q[sel], y[sel], var[sel], camera, s, None if rJ is None else rJ[sel],
                           None if rv is None else rv[sel])
        if rnd == s.gn_rounds:
            break
        new = _mahalanobis(T, q, y, var, camera, rJ, rv) < s.inlier_chi2
        if new.sum() < s.min_inliers or np.array_equal(new, sel):
            break
        sel = new
    final = m2_sel < s.inlier_chi2          # the inliers at the pose returned, whatever the round count
    sel[np.flatnonzero(sel)[~final]] = False
    m2_sel = m2_sel[final]
    n_in = int(sel.sum())
    if n_in < s.min_inliers:
        return PoseEstimate.failed(f"too few inliers after refinement: {n_in} of {matched} matches "
                                   f"(need {s.min_inliers})", matched, n_in)
    # a-posteriori variance factor: the (u, v, d) noise of reference points also ends up in the residual;
    # never below 1 because the chi2 inlier gate truncates the residuals
    m2_in = np.minimum(m2_sel, s.huber_k * np.sqrt(m2_sel))
    factor = max(1.0, float(m2_in.sum()) / max(3 * n_in - 6, 1))
    try:
        cov = factor * np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return PoseEstimate.failed("degenerate geometry: singular information matrix", matched, n_in)
    if not np.all(np.isfinite(cov)) or not np.all(np.isfinite(T)):
        return PoseEstimate.failed("degenerate geometry: non-finite estimate", matched, n_in)
    cov = 0.5 * (cov + cov.T)
    pairs = np.column_stack([qi[sel], ri[sel]])
    return PoseEstimate(True, T, cov, n_in, matched, "", pairs)

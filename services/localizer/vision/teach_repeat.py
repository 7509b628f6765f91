"""Visual Teach & Repeat on top of stereo keypoints and `estimate_pose` (thesis 2.2.3-2.2.4).

Transform convention (as in pose.py): `T_a_b` maps points from frame b into frame a, p_a = T_a_b p_b,
i.e. it is the pose of b seen from a. Frames are left-camera frames (x right, y down, z forward).
  - Keyframe.T_prev_this: this keyframe's points into the previous keyframe's frame (identity for 0).
  - Keyframe.T_first_this: this keyframe's points into keyframe 0's frame (the chain of the above).
  - TeachStep.T_kf_live: live points into the current keyframe's frame (the live camera's pose there).
  - RepeatStep.T_live_kf: keyframe points into the live frame (PoseEstimate.T_live_ref; thesis T_{k,i}).
Covariances are 6x6 over the left perturbation (translation, rotation) of the reported transform.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace

import numpy as np

from services.localizer.vision.camera import StereoCamera
from services.localizer.vision.features import StereoKeypoints
from common.se3 import adjoint, rotation_angle_deg
from common.se3 import inverse as inv_T
from common.se3 import transform
from services.localizer.vision.pose import PoseEstimate, estimate_pose, match
from services.localizer.vision.settings import VisionSettings
from services.localizer.vision.window_ba import KeyframeWindow

log = logging.getLogger("localizer.vision")

MIN_DISPARITY_PX = 0.25     # a keypoint's corrected disparity below this is at or beyond infinity
MIN_SUBMAP_DEPTH_M = 0.5    # a tracked feature nearer than this to the keyframe's camera is not added
MAX_OFFSET_PX = 3.0         # a window's disparity offset beyond this is a failed adjustment, not the rig


@dataclass
class Keyframe:
    """One path vertex: the stereo keypoints of the frame that defined it and its link to the previous
    vertex. `cov_uvd` (variances of the keypoints' u, v, d) lets localization weight the map's own noise;
    None treats the map points as exact. `T_first_this` is filled in by VisionMap from the chain."""
    index: int
    points: np.ndarray          # (N, 3) float64, in this keyframe's camera frame
    desc: np.ndarray            # (N, 32) uint8
    uvd: np.ndarray             # (N, 3) float64
    T_prev_this: np.ndarray     # 4x4
    T_first_this: np.ndarray | None = None
    cov_uvd: np.ndarray | None = None


@dataclass
class VisionMap:
    keyframes: list[Keyframe]
    camera: StereoCamera
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        T = np.eye(4)
        for i, kf in enumerate(self.keyframes):
            if kf.index != i:
                raise ValueError(f"keyframe {i} has index {kf.index}")
            T = T @ kf.T_prev_this if i else np.eye(4)
            kf.T_first_this = T.copy()
        self._T_first = np.array([kf.T_first_this for kf in self.keyframes]).reshape(-1, 4, 4)

    def __len__(self) -> int:
        return len(self.keyframes)

    def T_i_j(self, i: int, j: int) -> np.ndarray:
        """Keyframe j's points into keyframe i's frame."""
        return inv_T(self._T_first[i]) @ self._T_first[j]


@dataclass
class TeachStep:
    ok: bool
    new_keyframe: bool
    keyframe: int               # the keyframe T_kf_live refers to (the new one if one was made)
    T_kf_live: np.ndarray
    cov: np.ndarray
    inliers: int
    reason: str = ""


@dataclass
class RepeatStep:
    status: str                 # "ok" (refined against the keyframe), "vo" (dead-reckoning), "lost"
    keyframe: int
    T_live_kf: np.ndarray | None
    cov: np.ndarray | None
    matched: int                # inliers against the keyframe (0 unless refined)
    reason: str = ""
    vo_frames: int = 0          # consecutive frames without a refinement


def _motion(T: np.ndarray) -> tuple[float, float]:
    return float(np.linalg.norm(T[:3, 3])), rotation_angle_deg(T)


def _vo_floor(s: VisionSettings) -> np.ndarray:
    return np.diag([s.vo_sigma_m ** 2] * 3 + [np.radians(s.vo_sigma_deg) ** 2] * 3)


class VisualTeach:
    """Builds the map while the robot is driven. Each frame is registered against the current keyframe
    (less drift than chaining frame-to-frame), with a constant-velocity prior; if that fails, against the
    previous frame, chained. The live frame becomes the next keyframe once it is keyframe_dist_m or
    keyframe_angle_deg away from the current one. A frame that registers against neither is reported
    (ok=False) and skipped: the next frame tries again against the last good one."""

    def __init__(self, camera: StereoCamera, settings: VisionSettings):
        self.camera, self.s = camera, settings
        self.keyframes: list[Keyframe] = []
        self._last: StereoKeypoints | None = None
        self._T_last_kf = np.eye(4)         # last good frame's T_live_kf ...
        self._cov_last = np.zeros((6, 6))   # ... its covariance, and whether it is the keyframe itself
        self._last_is_kf = True
        self._T_vel: np.ndarray | None = None
        self.frames = self.failures = 0
        self._window = KeyframeWindow(camera, settings) if settings.ba_window >= 2 else None
        # the disparity offset's estimate: information (1/px^2) and information-weighted mean, from the
        # prior (mean 0) and what each window's data add
        self._offset_info = settings.disparity_offset_prior_px ** -2
        self._offset_info_mean = 0.0
        self.offset_windows = 0

    @property
    def disparity_offset_px(self) -> float:
        """The rig's disparity offset as the teach pass has estimated it so far."""
        return self._offset_info_mean / self._offset_info

    @property
    def disparity_offset_std_px(self) -> float:
        return self._offset_info ** -0.5

    def _calibrated(self) -> StereoCamera:
        return replace(self.camera, doffs_px=self.camera.doffs_px + self.disparity_offset_px)

    def _make_keyframe(self, kp: StereoKeypoints, T_prev_this: np.ndarray, pairs: np.ndarray | None) -> None:
        """`pairs`: the new keyframe's inlier matches (its index, the previous keyframe's), None when it
        was registered another way; the window's bundle adjustment then refines the last chain edges."""
        self.keyframes.append(Keyframe(len(self.keyframes), kp.points.copy(), kp.desc.copy(), kp.uvd.copy(),
                                       T_prev_this.copy(), None, kp.cov_uvd.copy()))
        if self._window is None:
            return
        s = self.s
        self._window.push(kp, T_prev_this, pairs)
        prior_std = self.disparity_offset_std_px if s.estimate_disparity_offset else None   # None: held
        out = self._window.adjust(self.disparity_offset_px, prior_std)
        if out is None:
            return
        for kf, edge in zip(self.keyframes[len(self.keyframes) - len(out.edges):], out.edges):
            kf.T_prev_this = edge
        if prior_std is not None and out.offset_std_px is not None:
            self._learn_offset((self.disparity_offset_px, prior_std), out.offset_px, out.offset_std_px,
                               len(out.edges) + 1)

    def _learn_offset(self, prior: tuple[float, float], offset: float, std: float, frames: int) -> None:
        """Fold a window's estimate into the running one: what its data alone say (its posterior less
        the prior it was given), counted 1 / frames times, since every keyframe's observations come
        back in the next windows that hold it."""
        info = std ** -2 - prior[1] ** -2
        if not np.isfinite(info) or info <= 0.0:
            return
        mean = (offset * std ** -2 - prior[0] * prior[1] ** -2) / info
        if abs(mean) > MAX_OFFSET_PX:
            log.debug("window disparity offset %.2f px ignored (beyond %.1f px)", mean, MAX_OFFSET_PX)
            return
        self._offset_info += info / frames
        self._offset_info_mean += info * mean / frames
        self.offset_windows += 1

    def _augment(self, kf: Keyframe, kp: StereoKeypoints, T_live_kf: np.ndarray, pairs: np.ndarray,
                 cam: StereoCamera) -> None:
        """Thesis 2.2.3: features the keyframe's submap does not hold, tracked from the previous frame
        into this one (a descriptor match at the predicted position whose (u, v, d) agrees with the
        motion), join the submap, placed by this frame's measurement: the repeat pass then finds them
        when its view differs from the keyframe's (turned, offset sideways, closer)."""
        if self._last is None or self._last_is_kf:
            return                   # the previous frame is the keyframe: its features are in already
        new = np.setdiff1d(np.arange(len(kp)), pairs[:, 0])
        if len(new) == 0:
            return
        live = kp.subset(new)
        p = transform(T_live_kf @ inv_T(self._T_last_kf), self._last.points)
        front = p[:, 2] > 0.1
        pred = np.full((len(p), 3), np.nan)
        pred[front] = cam.project(p[front])
        qi, ti = match(live, self._last.desc, self.s, pred[:, :2])
        e = live.uvd[qi] - pred[ti]
        agree = np.sum(e * e / (live.cov_uvd[qi] + self._last.cov_uvd[ti]), axis=1) < self.s.inlier_chi2
        pts = transform(inv_T(T_live_kf), live.points[qi[agree]])
        ok = pts[:, 2] > MIN_SUBMAP_DEPTH_M
        if not ok.any():
            return
        idx = qi[agree][ok]
        kf.points = np.vstack([kf.points, pts[ok]])
        kf.desc = np.vstack([kf.desc, live.desc[idx]])
        kf.uvd = np.vstack([kf.uvd, cam.project(pts[ok])])   # where the keyframe's camera would see them
        if kf.cov_uvd is not None:
            kf.cov_uvd = np.vstack([kf.cov_uvd, live.cov_uvd[idx]])

    def add(self, kp: StereoKeypoints) -> TeachStep:
        self.frames += 1
        s = self.s
        cam = self._calibrated()
        kp = retriangulated(kp, cam)
        if not self.keyframes:
            if len(kp) < s.min_inliers:
                self.failures += 1
                return TeachStep(False, False, -1, np.eye(4), np.full((6, 6), np.inf), 0,
                                 f"too few keypoints for the first keyframe: {len(kp)} (need {s.min_inliers})")
            self._make_keyframe(kp, np.eye(4), None)
            self._last = kp
            return TeachStep(True, True, 0, np.eye(4), np.zeros((6, 6)), len(kp))
        kf = self.keyframes[-1]
        pred = None if self._T_vel is None else self._T_vel @ self._T_last_kf
        est = estimate_pose(kf.points, kf.desc, kp, cam, s, pred, kf.cov_uvd)
        T_live_kf, cov, reason = est.T_live_ref, est.cov, est.reason
        pairs = est.pairs if est.ok else None
        if not est.ok and self._last is not None and not self._last_is_kf:
            vo = estimate_pose(self._last.points, self._last.desc, kp, cam, s, self._T_vel,
                               self._last.cov_uvd)
            if vo.ok:
                A = adjoint(vo.T_live_ref)
                T_live_kf = vo.T_live_ref @ self._T_last_kf
                cov = vo.cov + A @ self._cov_last @ A.T
                est = vo
            else:
                reason = f"keyframe: {est.reason}; previous frame: {vo.reason}"
        if not est.ok:
            self.failures += 1
            log.debug("teach frame %d not registered: %s", self.frames, reason)
            return TeachStep(False, False, kf.index, np.eye(4), np.full((6, 6), np.inf), est.inliers, reason)
        self._T_vel = T_live_kf @ inv_T(self._T_last_kf)
        if pairs is not None and s.submap_augment:
            self._augment(kf, kp, T_live_kf, pairs, cam)
        self._last, self._T_last_kf, self._cov_last, self._last_is_kf = kp, T_live_kf, cov, False
        T_kf_live = inv_T(T_live_kf)
        dist, ang = _motion(T_kf_live)
        if dist > s.keyframe_dist_m or ang > s.keyframe_angle_deg:
            self._make_keyframe(kp, T_kf_live, pairs)
            self._T_last_kf, self._cov_last, self._last_is_kf = np.eye(4), np.zeros((6, 6)), True
            return TeachStep(True, True, len(self.keyframes) - 1, np.eye(4), np.zeros((6, 6)), est.inliers)
        # cov is of T_live_kf's perturbation in the live frame; report it for T_kf_live (keyframe frame)
        A = adjoint(T_kf_live)
        return TeachStep(True, False, kf.index, T_kf_live, A @ cov @ A.T, est.inliers)

    def finish(self, meta: dict | None = None) -> VisionMap:
        """The map, its keyframes' points triangulated with the disparity offset estimated over the
        whole pass (the map's camera carries it in doffs_px, so the repeat pass measures with it)."""
        cam = self._calibrated()
        for kf in self.keyframes:
            keep = _finite_depth(kf.uvd, cam)
            kf.points, kf.desc, kf.uvd = cam.triangulate(kf.uvd[keep]), kf.desc[keep], kf.uvd[keep]
            kf.cov_uvd = None if kf.cov_uvd is None else kf.cov_uvd[keep]
        info = {"frames": self.frames, "failures": self.failures, "keyframe_dist_m": self.s.keyframe_dist_m,
                "keyframe_angle_deg": self.s.keyframe_angle_deg, "disparity_offset_px": self.disparity_offset_px,
                "disparity_offset_std_px": self.disparity_offset_std_px,
                "disparity_offset_windows": self.offset_windows}
        info.update(meta or {})
        return VisionMap(list(self.keyframes), cam, info)


def retriangulated(kp: StereoKeypoints, cam: StereoCamera) -> StereoKeypoints:
    """`kp` with its points triangulated by `cam` (whose doffs_px may carry an estimated offset),
    without the keypoints that would then lie at or beyond infinity."""
    keep = _finite_depth(kp.uvd, cam)
    kp = kp.subset(np.flatnonzero(keep)) if not keep.all() else kp
    return StereoKeypoints(kp.uvd, kp.desc, cam.triangulate(kp.uvd), kp.cov_uvd)


def _finite_depth(uvd: np.ndarray, cam: StereoCamera) -> np.ndarray:
    return uvd[:, 2] + cam.doffs_px > MIN_DISPARITY_PX


class VisualRepeat:
    """Localizes live frames against a taught map. Call `start(kf_hint)` first: the next frame is searched
    for among the keyframes around the hint (the most inliers wins). Then, per frame: VO against the
    previous frame propagates the pose relative to the current keyframe, the nearest keyframe (by the
    propagated position, among `nearest_window` either side) is chosen and the pose refined against it
    with the propagated pose as prior. A refinement that fails or that disagrees with the prediction by
    more than the jump gate is discarded and the VO pose kept (status "vo", covariance growing). After
    `max_vo_frames` such frames, or if VO itself fails, the status is "lost" with no pose, and the
    following frames search around the last keyframe again."""

    def __init__(self, vmap: VisionMap, settings: VisionSettings):
        if not vmap.keyframes:
            raise ValueError("the map has no keyframes")
        self.map, self.s = vmap, settings
        self.start(0)

    def start(self, kf_hint: int = 0) -> None:
        self._hint = int(np.clip(kf_hint, 0, len(self.map) - 1))
        self._searching = True
        self._prev: StereoKeypoints | None = None
        self._kf = self._hint
        self._T = np.eye(4)                 # last T_live_kf
        self._cov = np.zeros((6, 6))
        self._T_vel: np.ndarray | None = None
        self._vo_frames = 0

    def _against(self, j: int, kp: StereoKeypoints, T_init: np.ndarray | None) -> PoseEstimate:
        kf = self.map.keyframes[j]
        return estimate_pose(kf.points, kf.desc, kp, self.map.camera, self.s, T_init, kf.cov_uvd)

    def _lost(self, reason: str) -> RepeatStep:
        kf, vo_frames = self._kf, self._vo_frames
        self.start(kf)
        log.info("vision repeat lost near keyframe %d: %s", kf, reason)
        return RepeatStep("lost", kf, None, None, 0, reason, vo_frames)

    def _search(self, kp: StereoKeypoints) -> RepeatStep:
        lo, hi = max(0, self._hint - self.s.search_radius), min(len(self.map), self._hint + self.s.search_radius + 1)
        best: tuple[int, PoseEstimate] | None = None
        reasons = []
        for j in range(lo, hi):
            est = self._against(j, kp, None)
            if est.ok and (best is None or est.inliers > best[1].inliers):
                best = (j, est)
            elif not est.ok:
                reasons.append(est.reason)
        if best is None:
            self._prev = None
            return RepeatStep("lost", self._hint, None, None, 0,
                              f"no keyframe in {lo}..{hi - 1} localizes this frame ({reasons[0] if reasons else ''})")
        j, est = best
        self._searching, self._kf, self._T, self._cov = False, j, est.T_live_ref, est.cov
        self._prev, self._T_vel, self._vo_frames = kp, None, 0
        return RepeatStep("ok", j, est.T_live_ref.copy(), est.cov.copy(), est.inliers, "initial localization")

    def _nearest(self, T_live_i: np.ndarray) -> int:
        i, w = self._kf, self.s.nearest_window
        cands = range(max(0, i - w), min(len(self.map), i + w + 1))
        T_i_live = inv_T(T_live_i)
        return min(cands, key=lambda j: float(np.linalg.norm((self.map.T_i_j(j, i) @ T_i_live)[:3, 3])))

    def localize(self, kp: StereoKeypoints) -> RepeatStep:
        kp = retriangulated(kp, self.map.camera)     # measured as the map was: with its disparity offset
        if self._searching:
            return self._search(kp)
        s = self.s
        vo = estimate_pose(self._prev.points, self._prev.desc, kp, self.map.camera, s, self._T_vel,
                           self._prev.cov_uvd)
        if not vo.ok:
            return self._lost(f"VO failed: {vo.reason}")
        A = adjoint(vo.T_live_ref)
        cov_pred = vo.cov + _vo_floor(s) + A @ self._cov @ A.T
        T_pred_i = vo.T_live_ref @ self._T
        j = self._nearest(T_pred_i)
        T_pred = T_pred_i @ self.map.T_i_j(self._kf, j)     # a map edge is exact: the covariance stays
        self._prev, self._T_vel = kp, vo.T_live_ref
        est = self._against(j, kp, T_pred)
        reason = est.reason
        if est.ok:
            dist, ang = _motion(est.T_live_ref @ inv_T(T_pred))
            if dist <= s.jump_gate_m and ang <= s.jump_gate_deg:
                self._kf, self._T, self._cov, self._vo_frames = j, est.T_live_ref, est.cov, 0
                return RepeatStep("ok", j, est.T_live_ref.copy(), est.cov.copy(), est.inliers)
            reason = f"relocalization jump rejected ({dist:.2f} m, {ang:.1f} deg from the VO prediction)"
        self._vo_frames += 1
        if self._vo_frames > s.max_vo_frames:
            self._kf = j
            return self._lost(f"{self._vo_frames} frames without a keyframe refinement; last: {reason}")
        self._kf, self._T, self._cov = j, T_pred, cov_pred
        return RepeatStep("vo", j, T_pred.copy(), cov_pred.copy(), 0, reason, self._vo_frames)

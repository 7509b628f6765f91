"""The `vision` localization source: Visual Teach & Repeat on stereo frames (thesis chapter 2).

Teach: every frame goes through the stereo frontend and VO; keyframes (each with its submap) are the
route's vertices, their poses chained from the relative transforms. The map is written to disk beside
the route, and the route the controller tracks is made of those vertices, so vertex i *is* keyframe i.
Repeat: each frame is localized against the nearest keyframe (VO carries it between refinements); the
live camera pose relative to that keyframe becomes the robot's SE(2) pose in the vertex frame, with its
covariance. Nothing here looks at simulator truth.

Frames: the left camera (x right, y down, z forward) sits at `T_robot_camera` in the robot frame
(x forward, y left, z up, its origin the ground contact point). A vertex frame is the robot frame at its
keyframe levelled: same origin and heading, z up. A robot tilted by the terrain (a side slope, a rut)
has its body frame rolled and pitched, and the SE(2) pose the controller tracks is the horizontal one:
the live robot's ground contact point and heading seen from the vertex's, both projected on the level
plane. Expressing them in the tilted keyframe body frame instead would shrink a lateral offset by
cos(roll) and mix in height. Level is what the map's first keyframe says (the teach starts on level
ground): each keyframe's roll and pitch come from its pose in the first one, T_first_this, whose roll
and pitch drift only slowly with VO.
"""
from __future__ import annotations

import logging
import math
from pathlib import Path as FsPath

import cv2
import numpy as np

from common import se3
from common.messages import LocState, StereoFrame
from common.path import Path
from services.localizer.vision.camera import StereoCamera
from services.localizer.vision.features import StereoFrontend
from services.localizer.vision.map_file import MapFileError, load_map, save_map
from services.localizer.vision.settings import VisionSettings
from services.localizer.vision.teach_repeat import VisualRepeat, VisualTeach

log = logging.getLogger("localizer.vision")

MAP_SUFFIX = ".vmap"


def frame_images(frame: StereoFrame) -> tuple[np.ndarray, np.ndarray]:
    """The two mono8 images of a frame; ValueError with the reason when they cannot be had."""
    h, w = frame.height_px, frame.width_px
    if frame.encoding == "mono8":
        return (np.frombuffer(frame.left, np.uint8).reshape(h, w),
                np.frombuffer(frame.right, np.uint8).reshape(h, w))
    out = []
    for name, data in (("left", frame.left), ("right", frame.right)):
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE) if data else None
        if img is None:
            raise ValueError(f"{name} image is not a readable PNG ({len(data)} bytes)")
        if img.shape != (h, w):
            raise ValueError(f"{name} image is {img.shape[1]}x{img.shape[0]}, the frame says {w}x{h}")
        out.append(img)
    return out[0], out[1]


def frame_camera(frame: StereoFrame) -> tuple[StereoCamera, np.ndarray]:
    cam = StereoCamera(fu=frame.fu_px, fv=frame.fv_px, cu=frame.cu_px, cv=frame.cv_px,
                       baseline_m=frame.baseline_m, width=frame.width_px, height=frame.height_px)
    T_rc = np.asarray(frame.T_robot_camera, dtype=float).reshape(4, 4)
    R = T_rc[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or not np.allclose(T_rc[3], [0, 0, 0, 1]):
        raise ValueError("T_robot_camera is not a rigid transform")
    return cam, T_rc


def _same_calibration(a: StereoCamera, b: StereoCamera) -> str:
    """'' when a and b describe the same rig (to 0.1 %), else what differs."""
    for name in ("width", "height"):
        if getattr(a, name) != getattr(b, name):
            return f"{name} {getattr(a, name)} != {getattr(b, name)}"
    for name in ("fu", "fv", "cu", "cv", "baseline_m"):
        x, y = getattr(a, name), getattr(b, name)
        if abs(x - y) > 1e-3 * max(abs(x), abs(y), 1.0):
            return f"{name} {x:g} != {y:g}"
    return ""


def level_from_robot(T_first_robot: np.ndarray) -> np.ndarray:
    """4x4 rotation from a robot frame to its levelled frame (same heading, z up), from the robot's pose
    in a level frame: R = Rz(yaw) R_level_robot, so R_level_robot = Rz(-yaw) R."""
    R = np.asarray(T_first_robot, dtype=float)[:3, :3]
    yaw = math.atan2(R[1, 0], R[0, 0])
    c, s = math.cos(yaw), math.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]]) @ R
    return T


def vertex_robot_se2(T_live_kf: np.ndarray, T_rc: np.ndarray, T_level_kf: np.ndarray) -> np.ndarray:
    """(x, y, yaw) of the live robot in the levelled vertex frame, from the keyframe camera's pose seen
    from the live camera (T_live_kf) and the keyframe robot's levelling rotation (`level_from_robot`)."""
    return se3.to_se2(T_level_kf @ T_rc @ se3.inverse(T_live_kf) @ se3.inverse(T_rc))


def cov_vertex_robot(T_live_kf: np.ndarray, cov6: np.ndarray, T_rc: np.ndarray,
                     T_level_kf: np.ndarray | None = None) -> np.ndarray:
    """3x3 covariance of (x, y, yaw) of the robot in the (levelled) vertex frame, from the 6x6 covariance
    of the left perturbation T_live_kf = exp(xi) T (xi = translation, rotation), by a central difference."""
    T_level = np.eye(4) if T_level_kf is None else T_level_kf

    def se2_of(T_live_kf_: np.ndarray) -> np.ndarray:
        return vertex_robot_se2(T_live_kf_, T_rc, T_level)

    J = np.empty((3, 6))
    h = 1e-6
    for i in range(6):
        e = np.zeros(6)
        e[i] = h
        d = se2_of(se3.exp(e) @ T_live_kf) - se2_of(se3.exp(-e) @ T_live_kf)
        d[2] = (d[2] + np.pi) % (2 * np.pi) - np.pi
        J[:, i] = d / (2 * h)
    C = J @ cov6 @ J.T
    return 0.5 * (C + C.T)


class VisionSource:
    name = "vision"

    def __init__(self, settings: VisionSettings, maps_dir: str | FsPath):
        self.settings = settings
        self.maps_dir = FsPath(maps_dir)
        self.maps_dir.mkdir(parents=True, exist_ok=True)
        self.trial = 0
        self.mode = "idle"
        self.path: Path | None = None
        self.camera: StereoCamera | None = None
        self.T_rc: np.ndarray | None = None
        self.frontend: StereoFrontend | None = None
        self.teach: VisualTeach | None = None
        self.repeat: VisualRepeat | None = None
        self._T_level_kf: list[np.ndarray] = []     # per keyframe: its robot frame -> levelled vertex frame
        self._vertex = 0

    def map_file(self, path_id: str) -> FsPath:
        return self.maps_dir / f"{path_id}{MAP_SUFFIX}"

    # --- modes -------------------------------------------------------------------------------
    def start_teach(self, trial: int) -> None:
        self.mode, self.trial = "teach", trial
        self.teach = self.repeat = None
        self.camera = self.T_rc = None
        self.path = None
        self._vertex = 0

    def finish_teach(self, path_id: str, loop: bool, taught_by: str) -> Path:
        if self.mode != "teach":
            raise RuntimeError("not teaching")
        self.mode = "idle"
        if self.teach is None:
            raise ValueError("teach saw no stereo frame: is the bridge publishing sensors/stereo?")
        vmap = self.teach.finish()
        self.teach = None
        if len(vmap.keyframes) < 2:
            raise ValueError(f"teach made only {len(vmap.keyframes)} keyframe(s); drive further")
        T_rc, T_cr = self.T_rc, se3.inverse(self.T_rc)
        poses = np.array([se3.to_se2(T_rc @ kf.T_first_this @ T_cr) for kf in vmap.keyframes])
        path = Path(path_id, poses, loop=loop, spacing_m=self.settings.keyframe_dist_m, taught_by=taught_by)
        vmap.meta.update({"path_id": path_id, "taught_by": taught_by,
                          "T_robot_camera": [float(v) for v in T_rc.ravel()]})
        save_map(self.map_file(path_id), vmap)
        log.info("taught %s: %d keyframes, %.1f m, map in %s", path_id, len(path), path.length_m,
                 self.map_file(path_id))
        return path

    def start_repeat(self, path: Path, trial: int, rng: np.random.Generator | None = None) -> None:
        """Load the route's map; ValueError (with the reason) when it is missing, unreadable or does
        not belong to this route."""
        file = self.map_file(path.path_id)
        if not file.exists():
            raise ValueError(f"route {path.path_id!r} has no vision map ({file} is missing): "
                             "teach it with the vision source")
        try:
            vmap = load_map(file)
        except MapFileError as exc:
            raise ValueError(str(exc)) from None
        if len(vmap.keyframes) != len(path):
            raise ValueError(f"vision map {file} has {len(vmap.keyframes)} keyframes but route "
                             f"{path.path_id!r} has {len(path)} vertices: they were not taught together")
        T_rc = vmap.meta.get("T_robot_camera")
        if T_rc is None or len(T_rc) != 16:
            raise ValueError(f"vision map {file} does not say where the camera is on the robot")
        self.path, self.trial, self.mode = path, trial, "repeat"
        self.camera = vmap.camera
        self.T_rc = np.asarray(T_rc, dtype=float).reshape(4, 4)
        self.frontend = StereoFrontend(vmap.camera, self.settings)
        T_cr = se3.inverse(self.T_rc)
        self._T_level_kf = [level_from_robot(self.T_rc @ kf.T_first_this @ T_cr) for kf in vmap.keyframes]
        self.repeat = VisualRepeat(vmap, self.settings)
        self.repeat.start(0)   # a repeat starts at the beginning of the route
        self._vertex = 0

    # --- per frame ---------------------------------------------------------------------------
    def on_frame(self, frame: StereoFrame, path_id: str) -> LocState:
        try:
            left, right = frame_images(frame)
            cam, T_rc = frame_camera(frame)
        except ValueError as exc:
            return self._no_pose(frame, path_id, "teach" if self.mode == "teach" else "lost",
                                 f"bad stereo frame: {exc}")
        if self.mode == "teach":
            return self._teach_frame(frame, path_id, left, right, cam, T_rc)
        if self.mode != "repeat" or self.repeat is None:
            return self._no_pose(frame, path_id, "idle", "no route loaded")
        differs = _same_calibration(cam, self.camera)
        if differs or not np.allclose(T_rc, self.T_rc, atol=1e-3):
            return self._no_pose(frame, path_id, "lost", "camera calibration differs from the taught map's: "
                                 + (differs or "T_robot_camera"))
        kp = self.frontend.extract(left, right)
        step = self.repeat.localize(kp)
        if step.status == "lost":
            return self._no_pose(frame, path_id, "lost", step.reason, matched=step.matched)
        self._vertex = int(step.keyframe)
        T_level = self._T_level_kf[self._vertex]
        T_vr = vertex_robot_se2(step.T_live_kf, self.T_rc, T_level)
        cov = cov_vertex_robot(step.T_live_kf, step.cov, self.T_rc, T_level)
        return LocState(stamp_s=frame.stamp_s, capture_stamp_s=frame.stamp_s, tick=frame.tick,
                        capture_tick=frame.tick, trial=self.trial, path_id=path_id, source="vision",
                        status="ok" if step.status == "ok" else "vo", reason=step.reason, vertex=self._vertex,
                        distance_m=float(self.path.s[self._vertex] + T_vr[0]),
                        T_vertex_robot=tuple(float(v) for v in T_vr),
                        cov_T_vertex_robot=tuple(float(v) for v in cov.ravel()), matched_features=int(step.matched))

    def _teach_frame(self, frame, path_id, left, right, cam, T_rc) -> LocState:
        if self.teach is None:
            self.camera, self.T_rc = cam, T_rc
            self.frontend = StereoFrontend(cam, self.settings)
            self.teach = VisualTeach(cam, self.settings)
        elif _same_calibration(cam, self.camera) or not np.allclose(T_rc, self.T_rc, atol=1e-3):
            return self._no_pose(frame, path_id, "teach", "camera calibration changed during teach; frame ignored")
        step = self.teach.add(self.frontend.extract(left, right))
        n = len(self.teach.keyframes)
        self._vertex = max(n - 1, 0)
        reason = f"teaching: {n} keyframes" + ("" if step.ok else f"; VO failed: {step.reason}")
        return self._no_pose(frame, path_id, "teach", reason, matched=step.inliers)

    def _no_pose(self, frame: StereoFrame, path_id: str, status: str, reason: str,
                 matched: int | None = None) -> LocState:
        v = self._vertex
        distance = float(self.path.s[v]) if self.path is not None and v < len(self.path) else 0.0
        return LocState(stamp_s=frame.stamp_s, capture_stamp_s=frame.stamp_s, tick=frame.tick,
                        capture_tick=frame.tick, trial=self.trial, path_id=path_id, source="vision",
                        status=status, reason=reason, vertex=v, distance_m=distance, T_vertex_robot=None,
                        cov_T_vertex_robot=None, matched_features=None if matched is None else int(matched))

"""Rectified stereo pinhole camera: the observation model h (thesis eq. 2.1) and its inverse g (2.2).

Frames: left camera, x right, y down, z forward, metres. A measurement is (u, v, d): left-image pixel
column and row and the disparity d = u_left - u_right in pixels. `doffs_px` is the difference of the
right and left principal points (Middlebury calibrations), zero for a normally rectified rig.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class StereoCamera:
    fu: float
    fv: float
    cu: float
    cv: float
    baseline_m: float
    width: int
    height: int
    doffs_px: float = 0.0

    def __post_init__(self):
        vals = (self.fu, self.fv, self.cu, self.cv, self.baseline_m, self.doffs_px)
        if not all(np.isfinite(v) for v in vals):
            raise ValueError("camera parameters must be finite")
        if self.fu <= 0 or self.fv <= 0 or self.baseline_m <= 0:
            raise ValueError("focal lengths and baseline must be positive")
        if self.width <= 0 or self.height <= 0:
            raise ValueError("image size must be positive")

    @classmethod
    def from_projections(cls, P0: np.ndarray, P1: np.ndarray, width: int, height: int) -> StereoCamera:
        """From rectified 3x4 projection matrices of the left and right camera (KITTI calib.txt)."""
        P0, P1 = np.asarray(P0, float).reshape(3, 4), np.asarray(P1, float).reshape(3, 4)
        return cls(fu=P0[0, 0], fv=P0[1, 1], cu=P0[0, 2], cv=P0[1, 2],
                   baseline_m=(P0[0, 3] - P1[0, 3]) / P0[0, 0], width=width, height=height)

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fu, 0.0, self.cu], [0.0, self.fv, self.cv], [0.0, 0.0, 1.0]])

    def project(self, P: np.ndarray) -> np.ndarray:
        """(N, 3) points in the left camera frame -> (N, 3) (u, v, d). Points at z <= 0 give inf/nan;
        callers filter by depth first."""
        P = np.asarray(P, dtype=np.float64).reshape(-1, 3)
        with np.errstate(divide="ignore", invalid="ignore"):
            iz = 1.0 / P[:, 2]
            return np.column_stack([self.fu * P[:, 0] * iz + self.cu, self.fv * P[:, 1] * iz + self.cv,
                                    self.fu * self.baseline_m * iz - self.doffs_px])

    def project_jacobian(self, P: np.ndarray) -> np.ndarray:
        """(N, 3, 3) d(u, v, d)/d(x, y, z) at the points P."""
        P = np.asarray(P, dtype=np.float64).reshape(-1, 3)
        iz = 1.0 / P[:, 2]
        J = np.zeros((len(P), 3, 3))
        J[:, 0, 0] = self.fu * iz
        J[:, 0, 2] = -self.fu * P[:, 0] * iz * iz
        J[:, 1, 1] = self.fv * iz
        J[:, 1, 2] = -self.fv * P[:, 1] * iz * iz
        J[:, 2, 2] = -self.fu * self.baseline_m * iz * iz
        return J

    def triangulate(self, uvd: np.ndarray) -> np.ndarray:
        """(N, 3) (u, v, d) -> (N, 3) points in the left camera frame; d + doffs must be > 0."""
        uvd = np.asarray(uvd, dtype=np.float64).reshape(-1, 3)
        with np.errstate(divide="ignore", invalid="ignore"):
            z = self.fu * self.baseline_m / (uvd[:, 2] + self.doffs_px)
        return np.column_stack([(uvd[:, 0] - self.cu) * z / self.fu, (uvd[:, 1] - self.cv) * z / self.fv, z])

    def triangulate_jacobian(self, uvd: np.ndarray) -> np.ndarray:
        """(N, 3, 3) d(x, y, z)/d(u, v, d) of `triangulate` at the measurements uvd."""
        uvd = np.asarray(uvd, dtype=np.float64).reshape(-1, 3)
        P = self.triangulate(uvd)
        dd = uvd[:, 2] + self.doffs_px
        J = np.zeros((len(uvd), 3, 3))
        J[:, 0, 0] = P[:, 2] / self.fu
        J[:, 1, 1] = P[:, 2] / self.fv
        J[:, :, 2] = -P / dd[:, None]
        return J

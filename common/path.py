"""The taught route: a chain of vertex poses every ~`spacing` metres, as VT&R keyframes are.

A vertex frame has x along the route and y to the left, so the robot pose relative to its nearest
vertex (thesis fig. 2.5) gives the lateral error directly as y and the heading error as theta.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from common import se2
from common.messages import RouteMsg, check_name

DEFAULT_SPACING_M = 0.25   # metres between vertices (VT&R keyframes) unless a route says otherwise


@dataclass(frozen=True)
class Projection:
    """Continuous projection of a pose onto the route polyline."""
    vertex: int              # nearest vertex by Euclidean distance
    T_vertex_robot: np.ndarray
    distance_m: float        # arc length of the foot point along the route
    lateral_m: float         # signed, left of the route positive
    heading_rad: float       # robot heading minus route heading at the foot point
    segment: int             # foot point lies on segment (segment, segment+1)


class Path:
    def __init__(self, path_id: str, poses, *, loop: bool = False, spacing_m: float = DEFAULT_SPACING_M,
                 taught_by: str = "", curvature_window_m: float = 1.0, heading_window_m: float = 0.0):
        """`heading_window_m`: the taught heading is averaged over this much of the route into the
        reference heading a controller follows, and the curvature taken over at least as much (0: as
        taught). A robot that cannot steer the teach pass's wiggles back is asked for their mean."""
        self.path_id = check_name("path_id", path_id)
        poses = np.asarray(poses, dtype=float)
        if poses.ndim != 2 or poses.shape[1] != 3 or len(poses) < 2:
            raise ValueError("a path needs an (N>=2, 3) array of vertex poses (x, y, theta)")
        if not np.all(np.isfinite(poses)):
            raise ValueError("path poses must be finite")
        self.poses = poses.copy()
        self.poses[:, 2] = se2.wrap(self.poses[:, 2])
        self.poses.setflags(write=False)
        self.loop = bool(loop)
        self.spacing_m = float(spacing_m)
        self.taught_by = taught_by
        seg = np.hypot(np.diff(poses[:, 0]), np.diff(poses[:, 1]))
        if np.any(seg <= 1e-9):
            raise ValueError("consecutive path vertices must not coincide")
        self.segment_lengths = seg
        self.s = np.concatenate([[0.0], np.cumsum(seg)])
        self.length_m = float(self.s[-1])
        self.heading_window_m = float(heading_window_m)
        self.reference_heading = self._averaged_heading(self.heading_window_m)
        self.curvature_window_m = max(curvature_window_m, self.heading_window_m)
        self.curvature = self._curvature(self.curvature_window_m)
        self._tree = cKDTree(poses[:, :2])
        self._rows = self.poses.tolist()             # the same poses as floats: project() reads a few per call
        self._s_list = self.s.tolist()
        self._seg_list = seg.tolist()

    # --- construction -------------------------------------------------------------------
    @classmethod
    def from_msg(cls, msg: RouteMsg, heading_window_m: float = 0.0) -> "Path":
        return cls(msg.path_id, np.column_stack([msg.x_m, msg.y_m, msg.theta_rad]), loop=msg.loop,
                   spacing_m=msg.vertex_spacing_m, taught_by=msg.taught_by, heading_window_m=heading_window_m)

    def to_msg(self, stamp_s: float) -> RouteMsg:
        return RouteMsg(path_id=self.path_id, loop=self.loop, vertex_spacing_m=self.spacing_m,
                        x_m=self.poses[:, 0].tolist(), y_m=self.poses[:, 1].tolist(),
                        theta_rad=self.poses[:, 2].tolist(), taught_by=self.taught_by, stamp_s=stamp_s)

    def __len__(self) -> int:
        return len(self.poses)

    def _averaged_heading(self, window_m: float) -> np.ndarray:
        """The unwrapped taught heading per vertex averaged over `window_m` of route around it (the
        ends held; under two vertices' spacing: as taught)."""
        heading = np.unwrap(self.poses[:, 2])
        half = int(round(0.5 * window_m / max(self.spacing_m, 1e-6)))
        if half < 1:
            return heading
        padded = np.concatenate([np.full(half, heading[0]), heading, np.full(half, heading[-1])])
        return np.convolve(padded, np.ones(2 * half + 1) / (2 * half + 1), "valid")

    def curvature_over(self, window_m: float) -> np.ndarray:
        """Signed curvature (1/m) per vertex over `window_m` of route, at least the route's own window."""
        if window_m <= self.curvature_window_m:
            return self.curvature
        return self._curvature(window_m)

    def _curvature(self, window_m: float) -> np.ndarray:
        """Signed curvature (1/m) per vertex: heading change over arc length across a window."""
        n = len(self.poses)
        half = max(1, int(round(0.5 * window_m / max(self.spacing_m, 1e-6))))
        idx = np.arange(n)
        lo, hi = np.clip(idx - half, 0, n - 1), np.clip(idx + half, 0, n - 1)
        heading = np.unwrap(self.poses[:, 2])
        ds = self.s[hi] - self.s[lo]
        with np.errstate(invalid="ignore", divide="ignore"):
            kappa = np.where(ds > 0, (heading[hi] - heading[lo]) / ds, 0.0)
        return kappa

    # --- search -------------------------------------------------------------------------
    def nearest_vertex(self, xy, hint: int | None = None, back_m: float = 2.0, ahead_m: float = 5.0) -> int:
        """Nearest vertex by Euclidean distance. With a hint (the last known vertex) only a window
        around it is searched, O(window), which also keeps a route that crosses itself or closes a
        loop from jumping to the wrong pass; without one, a k-d tree search, O(log n)."""
        if hint is None:
            return int(self._tree.query(np.asarray(xy, dtype=float)[:2])[1])
        x, y = float(xy[0]), float(xy[1])
        hint = min(max(int(hint), 0), len(self) - 1)
        lo = max(0, hint - math.ceil(back_m / self.spacing_m))
        hi = min(len(self), hint + math.ceil(ahead_m / self.spacing_m) + 1)
        # a few dozen vertices: a plain loop beats numpy's per-call overhead here
        best, best_d2 = lo, math.inf
        for k, (px, py, _) in enumerate(self._rows[lo:hi], lo):
            d2 = (px - x) ** 2 + (py - y) ** 2
            if d2 < best_d2:
                best, best_d2 = k, d2
        return best

    def relative_pose(self, vertex: int, T_world_robot) -> np.ndarray:
        """T_vertex_robot: the robot pose in the frame of `vertex` (thesis fig. 2.5)."""
        return se2.between(self.poses[vertex], T_world_robot)

    def localize(self, T_world_robot, hint: int | None = None) -> tuple[int, np.ndarray]:
        i = self.nearest_vertex(T_world_robot, hint)
        return i, self.relative_pose(i, T_world_robot)

    def project(self, T_world_robot, hint: int | None = None) -> Projection:
        """Foot point on the polyline next to the nearest vertex, for accurate error metrics. Scalar
        arithmetic past the vertex search: the controller and the experiment runner call this several
        times a tick, and numpy's per-call overhead on 2-vectors was most of its cost."""
        x, y, th = (float(q) for q in T_world_robot[:3])
        i = self.nearest_vertex((x, y), hint)
        rows, n = self._rows, len(self._rows)
        best = None
        for a in (i - 1, i):
            if a < 0 or a + 1 >= n:
                continue
            (x0, y0, _), (x1, y1, _) = rows[a], rows[a + 1]
            dx, dy = x1 - x0, y1 - y0
            t = min(max(((x - x0) * dx + (y - y0) * dy) / (dx * dx + dy * dy), 0.0), 1.0)
            ex, ey = x - (x0 + t * dx), y - (y0 + t * dy)
            dist2 = ex * ex + ey * ey
            if best is None or dist2 < best[0]:
                best = (dist2, a, t, dx, dy, ex, ey)
        _, a, t, dx, dy, ex, ey = best
        h0, h1 = rows[a][2], rows[a + 1][2]
        heading = h0 + t * _wrap(h1 - h0)
        norm = math.sqrt(dx * dx + dy * dy)
        tx, ty = dx / norm, dy / norm
        along_extra, lateral = 0.0, tx * ey - ty * ex
        if (a == 0 and t == 0.0) or (a == n - 2 and t == 1.0):
            along_extra = ex * tx + ey * ty   # before the start / beyond the end
        elif t == 0.0 or t == 1.0:
            # outside a bend, the foot point is the vertex: the distance to it, signed by the side (its
            # component along one segment's normal would jump where the nearer segment changes)
            lateral = math.copysign(math.sqrt(ex * ex + ey * ey), lateral)
        return Projection(vertex=i, T_vertex_robot=_between(rows[i], x, y, th),
                          distance_m=self._s_list[a] + t * self._seg_list[a] + along_extra,
                          lateral_m=lateral, heading_rad=_wrap(th - heading), segment=a)

    def _segments(self, distance_m):
        """Arc length(s) clamped to the route and the index of the segment each lies on."""
        d = np.clip(np.asarray(distance_m, dtype=float), 0.0, self.length_m)
        return d, np.clip(np.searchsorted(self.s, d, side="right") - 1, 0, len(self) - 2)

    def tangent_at(self, distance_m):
        """Direction (rad) of the route polyline at arc length(s): the segment's, not the taught
        heading (which on a slope includes the robot's crab angle)."""
        _, a = self._segments(distance_m)
        diff = self.poses[a + 1, :2] - self.poses[a, :2]
        return np.arctan2(diff[..., 1], diff[..., 0])

    def heading_offset_at(self, distance_m):
        """The reference heading minus the taught heading at arc length(s), rad (zero without a
        heading window)."""
        if self.heading_window_m <= 0.0:
            return np.zeros(np.shape(distance_m))
        d, a = self._segments(distance_m)
        t = (d - self.s[a]) / self.segment_lengths[a]
        ref = self.reference_heading[a] + t * (self.reference_heading[a + 1] - self.reference_heading[a])
        taught = self.poses[a, 2] + t * se2.wrap(self.poses[a + 1, 2] - self.poses[a, 2])
        return se2.wrap(ref - taught)

    def curvature_at(self, distance_m: float) -> float:
        """The signed curvature (1/m) at an arc length, interpolated between vertices; a loop's arc
        length goes on round the loop, an open route's is clamped to it."""
        d = distance_m % self.length_m if self.loop else distance_m
        return float(np.interp(d, self.s, self.curvature))

    def pose_at(self, distance_m):
        """Interpolated route pose(s) at arc length(s), clamped to the route: (3,) or (M, 3)."""
        return self.frames_at(distance_m)[0]

    def frames_at(self, distance_m):
        """(pose_at, tangent_at, d(taught heading)/d(arc length) of pose_at's interpolation in rad/m) of
        the same arc length(s) from one segment lookup (the constrained NMPC needs all three per iterate)."""
        d, a = self._segments(distance_m)
        t = (d - self.s[a]) / self.segment_lengths[a]
        p0, p1 = self.poses[a], self.poses[a + 1]
        diff = p1 - p0
        dth = se2.wrap(diff[..., 2])
        xy = p0[..., :2] + t[..., None] * diff[..., :2]
        th = se2.wrap(p0[..., 2] + t * dth)
        pose = np.concatenate([xy, np.asarray(th)[..., None]], axis=-1)
        return pose, np.arctan2(diff[..., 1], diff[..., 0]), dth / self.segment_lengths[a]


class RouteRecorder:
    """Builds a route during teach: a new vertex whenever the robot has moved `spacing_m` from the
    last one (the VT&R keyframe rule), keeping the robot's own heading at that moment."""

    def __init__(self, spacing_m: float = DEFAULT_SPACING_M):
        if spacing_m <= 0:
            raise ValueError("spacing_m must be > 0")
        self.spacing_m = spacing_m
        self.vertices: list[tuple[float, float, float]] = []
        self.length_m = 0.0        # along the vertices so far

    def add(self, T_world_robot) -> bool:
        x, y, th = (float(v) for v in T_world_robot)
        if not self.vertices:
            self.vertices.append((x, y, th))
            return True
        lx, ly, _ = self.vertices[-1]
        step = float(np.hypot(x - lx, y - ly))
        if step >= self.spacing_m:
            self.vertices.append((x, y, th))
            self.length_m += step
            return True
        return False

    def finish(self, path_id: str, *, loop: bool, taught_by: str = "") -> Path:
        if len(self.vertices) < 2:
            raise ValueError(f"teach recorded only {len(self.vertices)} vertex(es); drive further")
        return Path(path_id, np.array(self.vertices), loop=loop, spacing_m=self.spacing_m, taught_by=taught_by)


def _wrap(angle: float) -> float:
    """se2.wrap for one float."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def _between(T_wa, x: float, y: float, th: float) -> np.ndarray:
    """se2.between(T_wa, (x, y, th)) for one pose, in scalars."""
    ax, ay, ath = T_wa
    c, s = math.cos(ath), math.sin(ath)
    ix, iy = -c * ax - s * ay, s * ax - c * ay
    return np.array([ix + c * x + s * y, iy - s * x + c * y, _wrap(_wrap(-ath) + th)])

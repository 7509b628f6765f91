"""The built-in teach driver: stands in for the operator who drives the route once.

Waypoints become a drivable reference (straight lines joined by circular arcs, as a person drives a
corner), which a pure-pursuit driver follows on the *simulated* robot, disturbances and all. What the
robot really drove is what gets taught.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from common import se2


class _Arc(NamedTuple):
    """The tangent arc that rounds one corner: it leaves the incoming leg at `start` heading along
    `d_in`, turns by `turn` radians (positive = left) on a circle of `radius`, and joins the outgoing
    leg at `end`."""
    start: np.ndarray
    end: np.ndarray
    radius: float
    turn: float
    d_in: np.ndarray


def smooth_waypoints(waypoints, corner_radius_m: float, loop: bool, step_m: float = 0.05) -> np.ndarray:
    """Dense (M, 3) poses along waypoints with every corner replaced by a tangent arc.

    The arc radius is `corner_radius_m`, reduced where the neighbouring legs are too short for it.
    A loop also rounds the corner at the first waypoint and ends where it started.
    """
    pts = _distinct_waypoints(waypoints, loop)
    n = len(pts)
    corners = list(range(n)) if loop else list(range(1, n - 1))
    arcs = _corner_arcs(pts, corners, corner_radius_m)
    if loop:
        # start mid-way along the first leg so that the loop closes on a straight
        start = 0.5 * (pts[0] + pts[1])
        out, cursor = _trace_corners(pts, arcs, start, list(range(1, n)) + [0], step_m)
        out += _line_poses(cursor, start, step_m)
        out.append(np.array([start[0], start[1], out[0][2]]))
    else:
        out, cursor = _trace_corners(pts, arcs, pts[0], range(1, n - 1), step_m)
        out += _line_poses(cursor, pts[-1], step_m)
        out.append(np.array([pts[-1][0], pts[-1][1], out[-1][2] if out else 0.0]))
    poses = np.array(out)
    poses[:, 2] = se2.wrap(poses[:, 2])
    return poses


def _distinct_waypoints(waypoints, loop: bool) -> np.ndarray:
    """(N, 2) waypoints without repeats; a loop also drops a last point that repeats the first."""
    pts = np.asarray(waypoints, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) < 2:
        raise ValueError("waypoints must be a list of at least two [x, y] pairs")
    keep = np.concatenate([[True], np.hypot(*np.diff(pts, axis=0).T) > 1e-6])
    pts = pts[keep]
    if loop:
        if np.hypot(*(pts[-1] - pts[0])) < 1e-6:
            pts = pts[:-1]
        if len(pts) < 3:
            raise ValueError("a loop needs at least three distinct waypoints")
    return pts


def _corner_arcs(pts: np.ndarray, corners, corner_radius_m: float) -> dict[int, _Arc]:
    """The arc at each corner index in `corners` that turns at all (straight-through corners have none)."""
    n = len(pts)
    arcs = {}
    for c in corners:
        arc = _corner_arc(pts[(c - 1) % n], pts[c], pts[(c + 1) % n], corner_radius_m, c)
        if arc is not None:
            arcs[c] = arc
    return arcs


def _corner_arc(p_prev, p, p_next, corner_radius_m: float, index: int) -> _Arc | None:
    d_in = (p - p_prev) / np.linalg.norm(p - p_prev)
    d_out = (p_next - p) / np.linalg.norm(p_next - p)
    turn = math.atan2(d_in[0] * d_out[1] - d_in[1] * d_out[0], float(np.dot(d_in, d_out)))
    if abs(turn) < 1e-6:
        return None
    if abs(abs(turn) - math.pi) < 1e-3:
        raise ValueError(f"waypoint {index} reverses the route; a robot cannot drive a 180 degree cusp")
    # the tangent points may use at most half of each leg, so that neighbouring arcs never overlap
    t_max = 0.5 * min(np.linalg.norm(p - p_prev), np.linalg.norm(p_next - p))
    t = min(corner_radius_m * math.tan(abs(turn) / 2), t_max)
    radius = t / math.tan(abs(turn) / 2)
    return _Arc(p - t * d_in, p + t * d_out, radius, turn, d_in)


def _trace_corners(pts: np.ndarray, arcs: dict[int, _Arc], cursor, order, step_m: float):
    """Poses from `cursor` through the corners in `order` (a line to each, then its arc if it has
    one); returns them and the point where the last corner is left."""
    out: list[np.ndarray] = []
    for c in order:
        arc = arcs.get(c)
        out += _line_poses(cursor, pts[c] if arc is None else arc.start, step_m)
        if arc is not None:
            out += _arc_poses(arc, step_m)
        cursor = pts[c] if arc is None else arc.end
    return out, cursor


def _line_poses(a, b, step_m: float) -> list[np.ndarray]:
    """Poses every <= `step_m` from `a` (included) towards `b` (excluded); none if a == b."""
    d = b - a
    length = float(np.linalg.norm(d))
    if length < 1e-9:
        return []
    k = max(1, int(math.ceil(length / step_m)))
    th = math.atan2(d[1], d[0])
    return [np.array([q[0], q[1], th]) for q in (a + d * (j / k) for j in range(k))]


def _arc_poses(arc: _Arc, step_m: float) -> list[np.ndarray]:
    """Poses every <= `step_m` along `arc` from its start (included) to its end (excluded)."""
    th0 = math.atan2(arc.d_in[1], arc.d_in[0])
    sign = 1.0 if arc.turn > 0 else -1.0
    center = arc.start + sign * arc.radius * np.array([-arc.d_in[1], arc.d_in[0]])
    k = max(1, int(math.ceil(arc.radius * abs(arc.turn) / step_m)))
    out = []
    for j in range(k):
        th = th0 + arc.turn * j / k
        q = center + sign * arc.radius * np.array([math.sin(th), -math.cos(th)])
        out.append(np.array([q[0], q[1], th]))
    return out


class PurePursuitDriver:
    """Drives a dense reference at a set speed and stops at its end."""

    def __init__(self, reference: np.ndarray, speed_mps: float, max_curvature: float = math.inf,
                 w_max_radps: float = math.inf, stop_decel_mps2: float = 0.3):
        self.ref = np.asarray(reference, dtype=float)
        seg = np.hypot(*np.diff(self.ref[:, :2], axis=0).T)
        self.s = np.concatenate([[0.0], np.cumsum(seg)])
        self.length = float(self.s[-1])
        self.speed = speed_mps
        self.max_curvature = max_curvature
        self.w_max = w_max_radps
        self.stop_decel = stop_decel_mps2
        self.index = 0
        self.done = False

    @property
    def start_pose(self) -> np.ndarray:
        return self.ref[0].copy()

    def command(self, pose) -> tuple[float, float]:
        x, y, th = pose
        # advance the progress index within a forward window (the route may cross itself)
        hi = min(len(self.ref), self.index + 200)
        d2 = np.sum((self.ref[self.index:hi, :2] - np.array([x, y])) ** 2, axis=1)
        self.index += int(np.argmin(d2))
        remaining = self.length - self.s[self.index]
        # stop once the end is reached or passed
        end = self.ref[-1]
        along_end = (x - end[0]) * math.cos(end[2]) + (y - end[1]) * math.sin(end[2])
        if remaining < 0.05 or (self.index >= len(self.ref) - 2 and along_end >= 0.0):
            self.done = True
        if self.done:
            return 0.0, 0.0
        v = min(self.speed, math.sqrt(2.0 * self.stop_decel * max(remaining, 0.0)) + 0.05)
        lookahead = max(0.8, 1.5 * v)
        target_s = self.s[self.index] + lookahead
        j = int(np.clip(np.searchsorted(self.s, target_s), 0, len(self.ref) - 1))
        tx, ty = self.ref[j, 0], self.ref[j, 1]
        if target_s > self.length:  # extend the last heading beyond the end
            extra = target_s - self.length
            tx += extra * math.cos(end[2])
            ty += extra * math.sin(end[2])
        alpha = math.atan2(ty - y, tx - x) - th
        alpha = math.atan2(math.sin(alpha), math.cos(alpha))
        dist = math.hypot(tx - x, ty - y)
        curvature = 2.0 * math.sin(alpha) / max(dist, 1e-3)
        curvature = max(-self.max_curvature, min(self.max_curvature, curvature))
        w = max(-self.w_max, min(self.w_max, v * curvature))
        return v, w

"""The controller's pure core: one call per control step, localization in, command and status out.

It owns everything that is not the control law itself: waiting for the first estimate, holding the
last command through a short dropout, stopping when localization is stale or lost, the speed
profile (scheduled speed, robot limits, a gentle stop into the end of the route) and the end.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from common import se2
from common.messages import LocState
from common.path import Path
from services.controller.fl import FLGains, fl_angular_rate


@dataclass(frozen=True)
class TrackerLimits:
    v_max_mps: float
    w_max_radps: float
    max_curvature: float = math.inf   # Ackermann: tan(steer_max) / L


@dataclass(frozen=True)
class Decision:
    v_mps: float
    w_radps: float
    state: str           # ControllerState
    reason: str
    vertex: int
    distance_m: float
    lateral_m: float
    heading_rad: float
    loc_age_s: float


class PathTracker:
    def __init__(self, path: Path, gains: FLGains, limits: TrackerLimits, *, speed_mps: float,
                 loc_timeout_s: float = 0.5, stop_decel_mps2: float = 0.4):
        self.path = path
        self.gains = gains
        self.limits = limits
        self.speed_mps = min(speed_mps, limits.v_max_mps)
        self.loc_timeout_s = loc_timeout_s
        self.stop_decel = stop_decel_mps2
        self.finished = False
        self._last_ok: LocState | None = None
        self._last_cmd = (0.0, 0.0)

    def scheduled_speed(self, vertex: int) -> float:
        """Speed at a vertex: one fixed speed for now; per-vertex schedules plug in here."""
        return self.speed_mps

    def route_errors(self, loc: LocState) -> tuple[float, float, float]:
        """(along, lateral, heading) errors of an estimate, continuous along the route.

        The vertex frame's axis is the robot's heading when it was taught, which on a slope differs
        from the route's direction (the robot crabbed). Taking y in the nearest vertex frame would make
        the lateral error jump at every vertex change, so the lateral error is measured against the
        route polyline next to that vertex, the heading error against the interpolated taught heading.
        """
        T_route_robot = se2.compose(self.path.poses[loc.vertex], loc.T_vertex_robot)
        pr = self.path.project(T_route_robot, hint=loc.vertex)
        return loc.T_vertex_robot[0], pr.lateral_m, pr.heading_rad

    def step(self, now_s: float, loc: LocState | None) -> Decision:
        if loc is not None and loc.status == "ok":
            self._last_ok = loc
        last = self._last_ok
        age = now_s - last.capture_stamp_s if last is not None else math.inf

        def stop(state: str, reason: str) -> Decision:
            self._last_cmd = (0.0, 0.0)
            if last is None:
                return Decision(0.0, 0.0, state, reason, 0, 0.0, 0.0, 0.0, age)
            _, y, th = self.route_errors(last)
            return Decision(0.0, 0.0, state, reason, last.vertex, last.distance_m, y, th, age)

        if self.finished:
            return stop("finished", "end of route reached")
        if last is None:
            return stop("waiting", f"no localization yet ({loc.status if loc else 'nothing received'})")
        if loc is not None and loc.status == "lost":
            return stop("stopped", f"localization lost: {loc.reason}")
        if age > self.loc_timeout_s:
            return stop("stopped", f"localization stale: newest estimate is {age:.2f} s old")

        vertex = last.vertex
        x, y, th = self.route_errors(last)
        if loc is not last:
            # short dropout: keep the last command, the robot is still within the timeout
            v, w = self._last_cmd
            return Decision(v, w, "holding", f"no fresh estimate ({loc.status if loc else 'none'}), "
                            f"holding last command", vertex, last.distance_m, y, th, age)

        remaining = self.path.length_m - last.distance_m
        if remaining <= 0.0 or (vertex == len(self.path) - 1 and x >= 0.0):
            self.finished = True
            return stop("finished", "end of route reached")

        v = min(self.scheduled_speed(vertex), math.sqrt(2.0 * self.stop_decel * remaining) + 0.02,
                self.limits.v_max_mps)
        w = fl_angular_rate(v, y, th, float(self.path.curvature[vertex]), self.gains)
        w_cap = min(self.limits.w_max_radps, abs(v) * self.limits.max_curvature)
        w = max(-w_cap, min(w_cap, w))
        self._last_cmd = (v, w)
        return Decision(v, w, "tracking", "", vertex, last.distance_m, y, th, age)

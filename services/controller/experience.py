"""Disturbance observations (thesis eq. 5.15 and 5.17) from the controller's own estimates and commands.

    a_k = (x_k, v_{k-1}, u_k, u_{k-1}),        g(a_k) = x_{k+1} - f(x_k, u_k)

Frames, chosen so that a place-specific disturbance generalizes along the route, between trials and
between robots on the same route:
- x_k enters `a` in route (Frenet) coordinates: distance along the taught route s, lateral error e_L and
  heading error e_H against it. These are the fig. 2.5 pose relative to the nearest vertex, made
  continuous along the route, so experiences gathered at neighbouring vertices share one input space
  and a side slope at s = 15 m is the same input whichever vertex was nearest.
- v_{k-1} = (v_act, w_act): body-frame speeds over the previous period, from consecutive estimates
  (thesis 5.3.1), so slip is seen against the ground, not the wheels.
- u_k, u_{k-1}: the commanded (v, w).
- g: the one-period residual of the nominal unicycle (eq. 5.26), position part rotated into the robot's
  body frame at k: (along, left, heading) metres/radians per period. With a drive lag configured
  (actuator.py) the unicycle moves at the lag's response to the commands, as in the NMPC's prediction:
  the GP must learn what that model misses, not what it already knows. Body-frame residuals are
  invariant to where the route happens to point, so only the place and the motion explain them.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from common import se2
from common.path import Path
from services.controller.actuator import ActuatorLag

A_NAMES = ("s_m", "e_lat_m", "e_head_rad", "v_act_mps", "w_act_radps", "v_cmd_mps", "w_cmd_radps",
           "v_cmd_prev_mps", "w_cmd_prev_radps")
G_NAMES = ("dx_body_m", "dy_body_m", "dtheta_rad")


def unicycle_step(pose, v: float, w: float, dt: float) -> np.ndarray:
    """Nominal model f(x, u) of eq. 5.26 (Euler step of the unicycle)."""
    x, y, th = pose
    return np.array([x + dt * v * math.cos(th), y + dt * v * math.sin(th), th + dt * w])


def body_residual(pose_k, v: float, w: float, pose_next, dt: float) -> np.ndarray:
    """g = x_{k+1} - f(x_k, u_k), position part in the body frame at k, heading wrapped."""
    pred = unicycle_step(pose_k, v, w, dt)
    d = np.asarray(pose_next, dtype=float) - pred
    c, s = math.cos(pose_k[2]), math.sin(pose_k[2])
    return np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1], float(se2.wrap(d[2]))])


def body_velocity(pose_prev, pose_k, dt: float) -> tuple[float, float]:
    """Actual (v, w) over one period from two poses: forward speed in the earlier body frame."""
    c, s = math.cos(pose_prev[2]), math.sin(pose_prev[2])
    dx, dy = pose_k[0] - pose_prev[0], pose_k[1] - pose_prev[1]
    return (c * dx + s * dy) / dt, float(se2.wrap(pose_k[2] - pose_prev[2])) / dt


@dataclass(frozen=True)
class Observation:
    stamp_s: float
    vertex: int
    v_cmd_mps: float
    a: tuple[float, ...]
    g: tuple[float, ...]


@dataclass(frozen=True)
class _Estimate:
    tick: int
    stamp_s: float
    vertex: int
    pose: np.ndarray          # in the route's frame
    route: tuple[float, float, float]   # (s, e_L, e_H)


class ExperienceBuilder:
    """Pairs estimates (by capture tick) with the commands applied at those ticks. An observation needs
    three consecutive estimates and the two commands in between; gaps (dropouts) simply yield nothing."""

    def __init__(self, path: Path, dt: float, min_speed_mps: float = 0.05, lag: ActuatorLag = ActuatorLag()):
        self.path = path
        self.dt = dt
        self.lag = lag
        self.min_speed = min_speed_mps
        self._est: deque[_Estimate] = deque(maxlen=3)
        self._cmd: dict[int, tuple[float, float]] = {}
        self.model_speeds = (0.0, 0.0)    # the latest observation's f(x, u): speed and turn rate over its period

    def command_at(self, tick: int) -> tuple[float, float] | None:
        return self._cmd.get(tick)

    def add_command(self, tick: int, v: float, w: float) -> None:
        self._cmd[tick] = (v, w)
        for old in [t for t in self._cmd if t < tick - 50 - self.lag.history_periods]:
            del self._cmd[old]

    def add_estimate(self, tick: int, stamp_s: float, vertex: int, T_vertex_robot) -> Observation | None:
        pose = se2.compose(self.path.poses[vertex], T_vertex_robot)
        pr = self.path.project(pose, hint=vertex)
        if self._est and tick == self._est[-1].tick:
            return None        # the same estimate again (a realtime loop without a fresh one)
        if self._est and tick < self._est[-1].tick:
            self._est.clear()  # clock went back (new trial): start over
        self._est.append(_Estimate(tick, stamp_s, vertex, pose, (pr.distance_m, pr.lateral_m, pr.heading_rad)))
        if len(self._est) < 3:
            return None
        e0, e1, e2 = self._est
        if not (e1.tick == e0.tick + 1 and e2.tick == e1.tick + 1):
            return None
        u1, u0 = self._cmd.get(e1.tick), self._cmd.get(e0.tick)
        if u1 is None or u0 is None:
            return None
        v_act, w_act = body_velocity(e0.pose, e1.pose, self.dt)
        if abs(u1[0]) < self.min_speed and abs(v_act) < self.min_speed:
            return None  # standing still teaches nothing about driving
        vb, wb = self.lag.step(self.lag.state_before(e1.tick, self.command_at), u1)[0] if self.lag.active else u1
        self.model_speeds = (float(vb), float(wb))
        g = body_residual(e1.pose, vb, wb, e2.pose, self.dt)
        a = (*e1.route, v_act, w_act, u1[0], u1[1], u0[0], u0[1])
        return Observation(stamp_s=e2.stamp_s, vertex=e1.vertex, v_cmd_mps=u1[0],
                           a=tuple(float(x) for x in a), g=tuple(float(x) for x in g))

"""The simulated robot and world as a pure, seeded core: commands in, truth and odometry out.

Time advances only through `step()` (one control period, integrated in `substeps` physics steps),
so the same seed and the same command sequence give the same run. The watchdog lives here, in robot
time: when the newest command is older than `watchdog_s` the robot brakes to a stop. Each sample also
says how the terrain tilts and lowers the body there (terrain.py `Terrain.attitude`), for the camera.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from common.robot import RobotParams
from common.scenario import TerrainPatch
from services.bridge.terrain import Attitude, Terrain
from services.bridge.vehicle import Vehicle


@dataclass(frozen=True)
class SimSample:
    stamp_s: float
    tick: int
    x: float
    y: float
    theta: float
    v_ground: float
    w_ground: float
    v_lateral: float
    odom_v: float
    odom_w: float
    odom_x: float
    odom_y: float
    odom_theta: float
    watchdog_tripped: bool
    cmd_age_s: float
    v_cmd: float
    w_cmd: float
    # the body on the terrain (terrain.py Attitude): roll and pitch in the heading's level frame, and
    # the ground contact point's height above the flat ground (negative in a rut)
    roll_rad: float
    pitch_rad: float
    z_m: float

    @property
    def attitude(self) -> Attitude:
        return Attitude(roll_rad=self.roll_rad, pitch_rad=self.pitch_rad, z_m=self.z_m)


class Simulator:
    def __init__(self, robot: RobotParams, terrain: list[TerrainPatch], seed: int, period_s: float = 0.1,
                 substeps: int = 10, watchdog_s: float = 0.3):
        self.robot = robot
        self.vehicle = Vehicle(robot)
        self.terrain = Terrain(terrain, seed, track_m=robot.track_m)
        self.seed = seed
        self.period_s = period_s
        self.substeps = substeps
        self.watchdog_s = watchdog_s
        self.t = 0.0
        self.tick = 0
        self._rng = np.random.default_rng([seed, 0])
        self._v_cmd = 0.0
        self._w_cmd = 0.0
        self._cmd_t = -math.inf
        self._odom = np.zeros(3)
        self._odom_vw = (0.0, 0.0)

    # --- trial management ------------------------------------------------------------------
    def reset(self, pose, trial: int) -> None:
        """Place the robot at `pose` at rest for a new trial; noise is reseeded per trial so each
        trial is reproducible on its own, while the clock keeps running."""
        self.vehicle.reset(*(float(v) for v in pose))
        self._rng = np.random.default_rng([self.seed, 1, trial])
        self._v_cmd = self._w_cmd = 0.0
        self._cmd_t = -math.inf
        self._odom = np.zeros(3)
        self._odom_vw = (0.0, 0.0)
        self.terrain.begin_trial()

    def end_trial(self) -> None:
        self.terrain.end_trial()
        self._v_cmd = self._w_cmd = 0.0
        self.vehicle.s.v_act = self.vehicle.s.w_act = 0.0

    def command(self, v_mps: float, w_radps: float) -> None:
        """A velocity command arriving now (robot time `self.t`)."""
        self._v_cmd, self._w_cmd = float(v_mps), float(w_radps)
        self._cmd_t = self.t

    # --- stepping ----------------------------------------------------------------------------
    def step(self) -> SimSample:
        h = self.period_s / self.substeps
        tripped = False
        for _ in range(self.substeps):
            tripped = (self.t - self._cmd_t) >= self.watchdog_s - 1e-9
            v, w = (0.0, 0.0) if tripped else (self._v_cmd, self._w_cmd)
            s = self.vehicle.s
            eff = self.terrain.effect(s.x, s.y)
            self.vehicle.step(h, v, w, tripped, eff, self._rng)
            self._integrate_odometry(h)
            self.t += h
        self.tick += 1
        self.t = round(self.t, 9)
        return self.sample(tripped)

    def _integrate_odometry(self, h: float) -> None:
        s = self.vehicle.s
        k = self.robot.odom_noise
        v = s.v_act * (1.0 + k * self._rng.standard_normal())
        w = s.w_act * (1.0 + k * self._rng.standard_normal())
        th = self._odom[2] + 0.5 * w * h
        self._odom += (v * math.cos(th) * h, v * math.sin(th) * h, w * h)
        self._odom[2] = math.atan2(math.sin(self._odom[2]), math.cos(self._odom[2]))
        self._odom_vw = (v, w)

    def sample(self, tripped: bool | None = None) -> SimSample:
        s = self.vehicle.s
        age = self.t - self._cmd_t
        if tripped is None:
            tripped = age >= self.watchdog_s - 1e-9
        att = self.terrain.attitude(s.x, s.y, s.theta)
        return SimSample(
            stamp_s=self.t, tick=self.tick, x=s.x, y=s.y, theta=s.theta, v_ground=s.v_ground,
            w_ground=s.w_ground, v_lateral=s.v_lateral, odom_v=self._odom_vw[0], odom_w=self._odom_vw[1],
            odom_x=float(self._odom[0]), odom_y=float(self._odom[1]), odom_theta=float(self._odom[2]),
            watchdog_tripped=tripped, cmd_age_s=min(age, 1e6), v_cmd=self._v_cmd, w_cmd=self._w_cmd,
            roll_rad=att.roll_rad, pitch_rad=att.pitch_rad, z_m=att.z_m)

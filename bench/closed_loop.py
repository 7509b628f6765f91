"""Teach and repeat with the pure cores of bridge, localizer and controller wired in one process:
the same code the services run, without the bus. Fast and deterministic, for unit tests and for
generating realistic experience data in benchmarks."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.messages import NominalModel, TruthPose
from common.path import Path
from common.robot import PRESETS, RobotParams
from services.bridge.simulator import SimSample, Simulator
from services.bridge.teach_driver import PurePursuitDriver, smooth_waypoints
from services.controller.actuator import ActuatorLag
from services.controller.core import ControllerCore
from services.controller.experience import Observation
from services.controller.fl import FLGains
from services.controller.identification import TeachRecorder, identify
from services.controller.laws import FLLaw, SteeringLaw
from services.controller.tracker import PathTracker, TrackerLimits
from services.controller.turn_speed import TURN_SHARE, TurnLoss
from services.localizer.pose_source import PoseSource, PoseSourceSettings


def truth_of(s: SimSample, trial: int) -> TruthPose:
    return TruthPose(stamp_s=s.stamp_s, tick=s.tick, trial=trial, x_world_m=s.x, y_world_m=s.y,
                     theta_world_rad=s.theta, v_mps=s.v_ground, w_radps=s.w_ground, lateral_slip_mps=s.v_lateral)


@dataclass
class RepeatResult:
    lateral_m: np.ndarray
    heading_rad: np.ndarray
    finished: bool
    steps: int
    observations: list[Observation]
    xy_m: np.ndarray | None = None      # (steps, 2) the truth's positions

    def rolled_m(self, since: int = 0) -> float:
        """How far the robot moved from step `since` on."""
        return float(np.sum(np.hypot(*np.diff(self.xy_m[since:], axis=0).T)))

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """The trial's disturbance observations as A (n, 9) and G (n, 3)."""
        return (np.array([o.a for o in self.observations], dtype=float).reshape(-1, 9),
                np.array([o.g for o in self.observations], dtype=float).reshape(-1, 3))

    @property
    def max_lateral(self) -> float:
        return float(np.max(np.abs(self.lateral_m)))


class ClosedLoop:
    def __init__(self, waypoints, terrain=(), preset: str | RobotParams = "husky", seed: int = 1,
                 teach_speed: float = 0.4, loop: bool = False, loc: PoseSourceSettings | None = None,
                 period_s: float = 0.1):
        self.robot = PRESETS[preset] if isinstance(preset, str) else preset
        self.period_s = period_s
        self.seed = seed
        self.sim = Simulator(self.robot, list(terrain), seed, period_s=period_s)
        self.ref = smooth_waypoints(waypoints, 3.0, loop)
        self.loop = loop
        self.source = PoseSource(loc or PoseSourceSettings(noise_m=0.0, noise_heading_rad=0.0),
                                 np.random.default_rng(seed))
        self.teach_speed = teach_speed
        self.path: Path | None = None
        self.teach_record = TeachRecorder(period_s)   # what the controller's node records of the last teach pass

    def teach(self) -> Path:
        drv = PurePursuitDriver(self.ref, self.teach_speed, self.robot.max_curvature, self.robot.w_max_radps)
        self.sim.reset(drv.start_pose, 0)
        self.source.start_teach(0)
        s = self.sim.sample()
        rec = self.teach_record = TeachRecorder(self.period_s)
        for _ in range(100000):
            loc = self.source.on_truth(truth_of(s, 0), "route")
            rec.add_applied(s.tick, s.v_cmd, s.w_cmd)
            rec.add_odometry(s.tick, s.odom_v, s.odom_w)
            rec.add_estimate(loc)
            v, w = drv.command((s.x, s.y, s.theta))
            if drv.done and abs(s.v_ground) < 1e-3:
                break
            self.sim.command(v, w)
            s = self.sim.step()
        self.sim.end_trial()
        self.path = self.source.finish_teach("route", loop=self.loop, taught_by="test")
        return self.path

    def identified(self) -> NominalModel:
        """The nominal model the controller identifies from this teach pass (nominal_models.py), with the
        robot's steering-rate limit as the deployment configures it."""
        return identify(self.teach_record, self.path, "bench", 0.0,
                        curvature_rate_max_per_ms=self.robot.max_curvature_rate)

    def repeat(self, trial: int, speed: float, law: SteeringLaw | None = None, max_steps: int = 20000,
               ic_vertices: int = 0, corridor=None, lag: ActuatorLag = ActuatorLag(), turn_share: float = TURN_SHARE,
               turn_loss: TurnLoss | None = None) -> RepeatResult:
        """One repeat with `law` (FL by default); `lag`: the drive lag the controller models; `turn_share`
        and `turn_loss` (the one learned in earlier trials): the speed cap from the robot's turn
        (turn_speed.py)."""
        path = self.path
        self.sim.reset(self.ref[0], trial)
        self.source.start_repeat(path, trial, np.random.default_rng([self.seed, 12, trial]))
        r = self.robot
        tracker = PathTracker(path, law or FLLaw(FLGains(), lag),
                              TrackerLimits(r.v_max_mps, r.w_max_radps, r.max_curvature, r.decel_max_mps2),
                              speed_mps=speed, ic_vertices=ic_vertices, corridor=corridor, lag=lag,
                              period_s=self.period_s, turn_share=turn_share, turn_loss=turn_loss)
        core = ControllerCore(path, tracker, self.period_s)
        s = self.sim.sample()
        lat, head, hint, finished, observations, xy = [], [], 0, False, [], []
        for n in range(max_steps):
            d, obs = core.step(s.stamp_s, s.tick, self.source.on_truth(truth_of(s, trial), "route"))
            observations += obs
            pr = path.project((s.x, s.y, s.theta), hint)
            hint = pr.vertex
            lat.append(pr.lateral_m)
            head.append(pr.heading_rad)
            xy.append((s.x, s.y))
            if d.state == "finished":
                finished = True
                if abs(s.v_ground) < 1e-3:
                    break
            self.sim.command(d.v_mps, d.w_radps)
            s = self.sim.step()
        self.sim.end_trial()
        return RepeatResult(np.array(lat), np.array(head), finished, n + 1, observations, np.array(xy))

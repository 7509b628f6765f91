"""Typed configuration of the bridge service (written by the experiment runner from a scenario)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from common.camera import StereoConfig
from common.robot import RobotParams
from common.scenario import TerrainPatch


@dataclass(frozen=True, kw_only=True)
class TeachConfig:
    waypoints: list[tuple[float, float]]
    loop: bool = False
    corner_radius_m: float = 3.0
    speed_mps: float = 0.5


@dataclass(frozen=True, kw_only=True)
class ClockConfig:
    mode: Literal["lockstep", "realtime"] = "lockstep"
    period_s: float = 0.1
    physics_substeps: int = 10
    watchdog_s: float = 0.3
    lockstep_timeout_s: float = 2.0


@dataclass(frozen=True, kw_only=True)
class BridgeConfig:
    robot_name: str
    backend: Literal["sim"] = "sim"
    seed: int = 0
    robot: RobotParams
    teach: TeachConfig
    terrain: list[TerrainPatch] = field(default_factory=list)
    clock: ClockConfig = field(default_factory=ClockConfig)
    start_offset_m: float = 0.0
    start_offset_deg: float = 0.0
    stereo: StereoConfig | None = None   # the simulated stereo camera; None: no frames

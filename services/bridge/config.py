"""Typed configuration of the bridge service (written by the experiment runner from a scenario)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from common.camera import StereoConfig
from common.robot import RobotParams
from common.scenario import PathSection, SimSection, TerrainPatch


@dataclass(frozen=True, kw_only=True)
class TeachConfig:
    """The built-in teach driver: the scenario's [path] (its defaults are the scenario's)."""
    waypoints: list[tuple[float, float]]
    loop: bool = False
    corner_radius_m: float = PathSection.corner_radius_m
    speed_mps: float = PathSection.teach_speed_mps


@dataclass(frozen=True, kw_only=True)
class ClockConfig:
    """The scenario's [sim] (its defaults are the scenario's)."""
    mode: Literal["lockstep", "realtime"] = SimSection.clock
    period_s: float = SimSection.period_s
    physics_substeps: int = SimSection.physics_substeps
    watchdog_s: float = SimSection.watchdog_s
    lockstep_timeout_s: float = SimSection.lockstep_timeout_s


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
